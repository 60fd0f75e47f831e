"""Name -> stage class. Core stages register by import path (their code, e.g. OpenCV, is
imported only when a stage is built); other packages through entry points, as methods do.

A separate package adds a stage without touching vprbench by declaring, in its pyproject.toml::

    [project.entry-points."vprbench.stages"]
    my-stage = "my_package:register"

where `my_package.register()` calls `vprbench.stages.register_stage("my-stage", "my_package.stage:MyStage")`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pydantic import ValidationError

from ..errors import VPRBenchError, closest_names
from ..registration import Registry, check_name, check_target, imported, looked_up, source_of

ENTRY_POINT_GROUP = "vprbench.stages"


@dataclass(frozen=True)
class StageEntry:
    name: str
    target: type | str  # the Stage subclass, or its import path "module:attribute"
    description: str = ""
    source: str = "vprbench"

    @property
    def cls(self) -> type:
        from .base import Stage

        found = imported("Stage", self.name, self.source, self.target)
        if not (isinstance(found, type) and issubclass(found, Stage)):
            raise VPRBenchError(f"Stage {self.name!r} ({self.source}) is not a vprbench Stage class; fix the plugin.")
        if found.apply is Stage.apply:  # refused when the spec is made, not after retrieval has run
            raise VPRBenchError(f"Stage {self.name!r} ({self.source}): {found.__name__} does not define "
                                "apply(candidates, context), which every stage needs; define it (see 'Stages', "
                                "writing a stage).")
        return found


def register_stage(name: str, target: type | str, *, description: str = "", source: str | None = None) -> None:
    """Make `name` available to `--rerank name` / `--sequence name` and plans' `stages`; a name
    already taken by another stage is refused (ValueError naming who registered it)."""
    check_name("Stage", name)
    check_target("Stage", name, target, description, source)
    entry = StageEntry(name, target, description, source or source_of(target))
    STAGES.claim(entry)


def core_stages() -> list[dict]:
    return [
        {"name": "sift-ransac", "target": "vprbench.stages.geometric:SiftRansac",
         "description": "SIFT/RootSIFT, ratio test, USAC on a fundamental matrix or homography; score = inliers"},
        {"name": "patch-mnn", "target": "vprbench.stages.patches:PatchMNN",
         "description": "dense patch matching: mutual nearest neighbours of an AnyLoc backbone's per-patch features"},
        {"name": "aqe", "target": "vprbench.stages.expansion:AlphaQE",
         "description": "alpha query expansion on the global descriptors (re-ranks the top K)"},
        {"name": "dba", "target": "vprbench.stages.expansion:DatabaseAugmentation",
         "description": "database-side augmentation (alpha-weighted) on the global descriptors"},
        {"name": "seqslam", "target": "vprbench.stages.sequence:SeqSLAM",
         "description": "SeqSLAM over the stored descriptors (enhancement, velocity search; OpenSeqSLAM's defaults)"},
        {"name": "diagonal", "target": "vprbench.stages.sequence:DiagonalSequence",
         "description": "descriptor-sequence score: similarities along the matching diagonal over a window"},
    ]


def _register_core() -> None:
    for entry in core_stages():
        register_stage(**entry, source="vprbench")


STAGES = Registry("Stage", ENTRY_POINT_GROUP, _register_core)


def available_stages() -> dict[str, StageEntry]:
    return STAGES.available()


def stage_entry(name: str) -> StageEntry:
    stages, name = available_stages(), looked_up(name)
    if name not in stages:
        raise VPRBenchError(f"Unknown stage {name!r}.{closest_names(str(name), stages)} "
                            f"Stages: {', '.join(stages) or 'none'}.{STAGES.unloaded_hint()}")
    return stages[name]


def stage_options(name: str, options: dict):
    """`options` validated by stage `name`'s Options model (unknown names and wrong types refused)."""
    from ..loader import plugin_part

    cls = stage_entry(name).cls
    # what a plugin's validator raises beyond ValueError (pydantic's ValidationError, below) is its one line
    with plugin_part(cls.Options, f"its options {cls.Options.__name__}", f"Stage {name!r}"):
        try:
            return cls.Options(**options)
        except ValidationError as error:
            raise _refused(name, cls, error) from None


def _refused(name: str, cls, error: ValidationError) -> VPRBenchError:
    """The first problem pydantic found in stage `name`'s options, as one line."""
    problem = error.errors()[0]
    option = ".".join(str(p) for p in problem["loc"]) or "its options"
    accepted = ", ".join(cls.Options.model_fields) or "none"
    if problem["type"] == "extra_forbidden":
        return VPRBenchError(f"Stage {name!r} does not take option {option}.{closest_names(option, cls.Options.model_fields)} "
                             f"It accepts: {accepted}.")
    if problem["type"] == "value_error":  # a check of the stage's own: its message as written
        message = str(problem["ctx"]["error"]).rstrip(".")
        return VPRBenchError(f"Stage {name!r} option {option}: {message}." if problem["loc"] else
                             f"Stage {name!r}: {message}.")
    return VPRBenchError(f"Stage {name!r} option {option}: {problem['msg']} (got {problem.get('input')!r}).")


def create_stage(name: str, options: dict | None = None):
    """The stage `name` with its options validated; its `name` set."""
    from ..loader import plugin_part

    cls = stage_entry(name).cls
    options = stage_options(name, options or {})
    with plugin_part(cls, f"its constructor {cls.__name__}", f"Stage {name!r}"):
        stage = cls(options)
    stage.name = looked_up(name)
    return stage
