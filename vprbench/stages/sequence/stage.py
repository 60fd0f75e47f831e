"""The sequence stages: SeqSLAM and the descriptor-sequence score, on datasets that are traverses.

They ignore retrieval's shortlist (a sequence can find what single images missed) and match every
query against the whole database from the retriever's stored descriptors, within the run's memory
budget. `mode` (offline: a window centred on the query; causal: the query and the frames before
it, as a robot has them) is an option, so it is part of the run's identity and its record.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ...errors import VPRBenchError
from ...methods.attributes import COMPARES
from ..base import Candidates, Stage, StageContext, StageOptions
from .matching import SEQSLAM_DEFAULTS, query_offsets
from .search import sequence_search

#: more trajectories than this would be a typo (v_step 0.0001), not a search
MAX_VELOCITIES = 1000


class SequenceOptions(StageOptions):
    #: frames in a query's sequence (--sequence-length)
    length: int = Field(SEQSLAM_DEFAULTS["length"], ge=1, le=10_000)
    mode: Literal["offline", "causal"] = "offline"


class SeqSLAMOptions(SequenceOptions):
    enhance_window: int = Field(SEQSLAM_DEFAULTS["enhance_window"], ge=2, le=10_000)
    v_min: float = Field(SEQSLAM_DEFAULTS["v_min"], gt=0, le=100)
    v_max: float = Field(SEQSLAM_DEFAULTS["v_max"], gt=0, le=100)
    v_step: float = Field(SEQSLAM_DEFAULTS["v_step"], gt=0, le=100)
    uniqueness_window: int = Field(SEQSLAM_DEFAULTS["uniqueness_window"], ge=0, le=10_000)

    @model_validator(mode="after")
    def _velocity_range(self):
        if self.v_min > self.v_max:
            raise ValueError(f"v_min ({self.v_min}) must not exceed v_max ({self.v_max})")
        if (self.v_max - self.v_min) / self.v_step >= MAX_VELOCITIES:
            raise ValueError(f"v_min..v_max in steps of v_step gives more than {MAX_VELOCITIES} velocities")
        return self


class _SequenceStage(Stage):
    track = "sequence"
    score = ""

    def check(self, dataset) -> None:
        from ...datasets.traverse import traverse_orders

        traverse_orders(dataset, f"Sequence stage {self.name!r}")
        if self.options.length > len(dataset.queries):
            raise VPRBenchError(f"Sequence stage {self.name!r}: --sequence-length {self.options.length} exceeds the "
                                f"{len(dataset.queries)} queries of {dataset.name}; give a shorter length.")

    def check_compare(self, compare: str) -> None:
        if compare not in COMPARES:
            raise VPRBenchError(f"Sequence stage {self.name!r} compares descriptors by {', '.join(COMPARES)}; the "
                                f"method's are compared by {compare!r}.")

    def candidates_needed(self) -> int | None:
        return None  # the run's largest K: how many it returns

    def search_options(self) -> dict:
        return {}

    def least_budget(self, database, queries, k: int) -> int:
        from .search import sequence_need

        return sequence_need(database, queries, k, score=self.score, length=self.options.length,
                             mode=self.options.mode)

    @classmethod
    def query_window(cls, options: dict) -> int:
        """The frames of a query's sequence, offline or causal (their offsets' span: `length`);
        options it refuses raise pydantic's ValidationError, a ValueError."""
        chosen = cls.Options(**options)
        offsets = query_offsets(chosen.length, chosen.mode)
        return int(offsets.max() - offsets.min()) + 1

    def fingerprint(self) -> dict:
        from .search import TIE_ORDER

        # 2: costs on a grid, ties to the lower database index; 3: products on one thread each (the same for
        # every thread count; on several threads a version 2 cost could differ by a grid step)
        return {"version": 3, "tie_order": TIE_ORDER}

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        from ...datasets.traverse import traverse_orders

        orders = traverse_orders(context.dataset, f"Sequence stage {self.name!r}")
        compare = getattr(context, "compare", "cosine")
        self.check_compare(compare)
        found = sequence_search(context.database, context.queries, candidates.k, score=self.score, compare=compare,
                                length=self.options.length, mode=self.options.mode,
                                database_order=orders["database"], query_order=orders["queries"],
                                memory_budget=context.memory_budget, grid=True, **self.search_options())
        return Candidates(found.indices, found.scores)


class SeqSLAM(_SequenceStage):
    Options = SeqSLAMOptions
    description = ("SeqSLAM: contrast-enhanced difference matrix, best trajectory over a velocity range; "
                   "OpenSeqSLAM's defaults")
    score = "seqslam"

    def check(self, dataset) -> None:
        super().check(dataset)
        # a window leaving out every database image around a match in the middle leaves it no second best: its
        # score fell back to minus the bare cost, another scale than the other queries' ratios in one PR curve
        n, half = len(dataset.database), self.options.uniqueness_window // 2
        if half >= n // 2:
            raise VPRBenchError(f"Sequence stage {self.name!r}: uniqueness_window {self.options.uniqueness_window} "
                                f"leaves out every one of the {n} database images of {dataset.name} around a match "
                                "in its middle, so that match has no second best to be scored against: "
                                + (f"give uniqueness_window <= {2 * (n // 2) - 1}." if n > 1 else
                                   "SeqSLAM needs two database images or more."))

    def search_options(self) -> dict:
        o = self.options
        return {"enhance_window": o.enhance_window, "v_min": o.v_min, "v_max": o.v_max, "v_step": o.v_step,
                "uniqueness_window": o.uniqueness_window}


class DiagonalSequence(_SequenceStage):
    Options = SequenceOptions
    description = "descriptor-sequence score: similarities averaged along the matching diagonal over the window"
    score = "diagonal"
