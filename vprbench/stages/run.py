"""Running a spec's stages over retrieval's candidates, each timed and checked on its own."""
from __future__ import annotations

import resource
import sys
import time

from ..errors import VPRBenchError
from ..hashing import exact_data
from ..loader import plugin_part
from .base import Candidates, StageContext, check_candidates, check_reordered


def in_stage(stage, part: str):
    """Runs a call into `stage`'s code: a plugin stage's failure is one line naming it (`plugin_part`)."""
    return plugin_part(stage, part, f"Stage {getattr(stage, 'name', '?')!r}")


def check_compares(stages, compare: str) -> None:
    """Refuse, before any work, a stage that cannot use descriptors compared by `compare` (the method's:
    aqe cannot use sad's distances)."""
    for stage in stages:
        with in_stage(stage, "check_compare"):
            stage.check_compare(compare)


def create_stages(spec) -> list:
    from .registry import create_stage

    return [create_stage(stage.name, stage.options) for stage in spec.stages]


def stage_fingerprint(stage) -> dict:
    """The stage's fingerprint as its record keeps it (JSON), {} by default."""
    import json

    with in_stage(stage, "fingerprint"):
        found = stage.fingerprint()
    if not isinstance(found, dict):
        raise VPRBenchError(f"Stage {stage.name!r}: fingerprint() returned {type(found).__name__}, not a dict; fix "
                            "the stage.")
    return json.loads(json.dumps(exact_data(found, f"Stage {stage.name!r}: fingerprint()"), sort_keys=True))


def track_of(stages) -> str:
    """single-image (no stage), sequence (any sequence stage), else re-ranked."""
    if not stages:
        return "single-image"
    return "sequence" if any(stage.track == "sequence" for stage in stages) else "re-ranked"


def check_stage_chain(stages, ks) -> None:
    """A spec's stages (StageSpec) refused, before any work, where a stage would be scored on candidates it
    never saw or its work thrown away: a re-ranker re-orders its top `k` (at least the largest K reported,
    at most what the re-ranker before it hands over); a sequence stage matches every query against the
    whole database, so a re-ranker before it would be computed and ignored."""
    from .registry import stage_entry

    handed = None  # (stage, k): the last re-ranker and its depth
    for position, stage in enumerate(stages):
        depth = stage.options.get("k")
        if stage_entry(stage.name).cls.track == "sequence":
            earlier = [s.name for s in stages[:position] if stage_entry(s.name).cls.track == "sequence"]
            if earlier:
                raise VPRBenchError(f"A run takes one sequence stage, got {earlier[0]!r} and {stage.name!r}: each "
                                    "matches against the whole database, so the later ignores the earlier; keep one.")
            if position:
                raise VPRBenchError(f"Stage {stages[position - 1].name!r} runs before sequence stage {stage.name!r}, "
                                    "which matches every query against the whole database and ignores the candidates "
                                    f"it is given: put {stage.name!r} first (a re-ranker then re-orders its top K), or "
                                    "drop the other stage.")
            continue
        if isinstance(depth, int) and depth < ks[-1]:
            raise VPRBenchError(f"Stage {stage.name!r} re-ranks the top {depth} (--rerank-k), fewer than the largest "
                                f"K reported ({ks[-1]}): give --rerank-k >= {ks[-1]} or lower --k.")
        if isinstance(depth, int) and handed is not None and depth > handed[1]:
            raise VPRBenchError(f"Stage {stage.name!r} re-ranks the top {depth}, but stage {handed[0]!r} before it hands "
                                f"over only its top {handed[1]}: give {stage.name!r} k <= {handed[1]}, or "
                                f"{handed[0]!r} a larger k.")
        if isinstance(depth, int):
            handed = (stage.name, depth)


def retrieval_depth(stages, ks, database: int, dataset: str) -> int:
    """How many candidates retrieval must find: the largest K, or more for a re-ranker; never more than
    the database holds."""
    depth = ks[-1]
    for stage in stages:
        with in_stage(stage, "candidates_needed"):
            needed = stage.candidates_needed()
        if needed is None:
            continue
        if needed > database:
            raise VPRBenchError(f"Stage {stage.name!r} re-ranks the top {needed} (--rerank-k), but the database of "
                                f"{dataset} holds {database} images: give --rerank-k <= {database}.")
        depth = max(depth, needed)
    return depth


def _peak_rss_bytes() -> int:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)  # Linux reports KiB


def run_stages(stages, candidates: Candidates, context: StageContext, ks, positives=None,
               all_zero=None) -> tuple[Candidates, list[dict]]:
    """The candidates after every stage, in order, and each stage's cost: ms per query for the stage
    alone, bytes it stores per database image, the process's peak RSS after it and how far the stage
    raised it (0 when it stayed under an earlier peak; no tracer, so the timing is the stage's own), how
    many images' per-image data it computed rather than read from the cache, and where its weights
    come from when it has any.
    With `positives`, each re-ranker's cost has its ceiling: the % of queries with a positive among the
    candidates it was given (a re-ranker of them can reach no higher recall; a query flagged in `all_zero`
    has none: its descriptor is all zero, so it counts as a failure whatever a stage makes of its candidates).
    A sequence stage has no ceiling: it matches against the whole database, not what it was given."""
    queries, database = candidates.query_count, context.database.row_count
    costs = []
    for stage in stages:
        with in_stage(stage, "candidates_needed"):
            needed = stage.candidates_needed()
        given = candidates.top(needed) if needed is not None else candidates
        before, computed = _peak_rss_bytes(), context.features_computed
        started = time.perf_counter()
        with in_stage(stage, "apply"):
            found = stage.apply(given, context)
        seconds = time.perf_counter() - started
        after = _peak_rss_bytes()
        candidates = check_candidates(found, stage.name, queries, database, ks[-1])
        if stage.track == "re-ranked":
            check_reordered(candidates, given, stage.name, database)
        with in_stage(stage, "stored_bytes"):
            stored = int(stage.stored_bytes(context))
        with in_stage(stage, "provenance"):
            provenance = stage.provenance()
        code = stage_fingerprint(stage)
        ceiling = {}
        if positives is not None and stage.track == "re-ranked":  # a sequence stage ignores what it is given: no ceiling
            from ..evaluation.metrics import RECALL_DECIMALS, correct_at, percent_true

            found_any = correct_at(given.indices, positives, all_zero).any(1)
            ceiling = {"ceiling_recall": round(percent_true(found_any), RECALL_DECIMALS)}
        costs.append({**ceiling, "name": stage.name, "track": stage.track, "options": stage.options.model_dump(mode="json"),
                      "candidates_in": given.k, "ms_per_query": round(1000 * seconds / max(queries, 1), 3),
                      "seconds": round(seconds, 3), "stored_bytes_per_database_image": round(stored / max(database, 1), 1),
                      "peak_rss_bytes": after, "peak_rss_growth_bytes": after - before,
                      "features_computed": context.features_computed - computed,
                      **({"provenance": provenance} if provenance else {}), **({"fingerprint": code} if code else {})})
    return candidates, costs
