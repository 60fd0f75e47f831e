"""Running a spec's stages over retrieval's candidates, each timed and checked on its own."""
from __future__ import annotations

import resource
import sys
import time

from ..errors import VPRBenchError
from .base import Candidates, StageContext, check_candidates


def create_stages(spec) -> list:
    from .registry import create_stage

    return [create_stage(stage.name, stage.options) for stage in spec.stages]


def stage_fingerprint(stage) -> dict:
    """The stage's fingerprint as its record keeps it (JSON), {} by default."""
    import json

    found = stage.fingerprint()
    if not isinstance(found, dict):
        raise VPRBenchError(f"Stage {stage.name!r}: fingerprint() returned {type(found).__name__}, not a dict; fix "
                            "the stage.")
    return json.loads(json.dumps(found, sort_keys=True, default=str))


def track_of(stages) -> str:
    """single-image (no stage), sequence (any sequence stage), else re-ranked."""
    if not stages:
        return "single-image"
    return "sequence" if any(stage.track == "sequence" for stage in stages) else "re-ranked"


def retrieval_depth(stages, ks, database: int, dataset: str) -> int:
    """How many candidates retrieval must find: the largest K, or more for a re-ranker; never more than
    the database holds."""
    depth = ks[-1]
    for stage in stages:
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


def run_stages(stages, candidates: Candidates, context: StageContext, ks, positives=None) -> tuple[Candidates, list[dict]]:
    """The candidates after every stage, in order, and each stage's cost: ms per query for the stage
    alone, bytes it stores per database image, the process's peak RSS after it and how far the stage
    raised it (0 when it stayed under an earlier peak; no tracer, so the timing is the stage's own), how
    many images' per-image data it computed rather than read from the cache, and where its weights
    come from when it has any.
    With `positives`, each cost has the stage's ceiling: the % of queries with a positive among the
    candidates it was given (a re-ranker of them can reach no higher recall)."""
    queries, database = candidates.query_count, context.database.row_count
    costs = []
    for stage in stages:
        needed = stage.candidates_needed()
        given = candidates.top(needed) if needed is not None else candidates
        before, computed = _peak_rss_bytes(), context.features_computed
        started = time.perf_counter()
        found = stage.apply(given, context)
        seconds = time.perf_counter() - started
        after = _peak_rss_bytes()
        candidates = check_candidates(found, stage.name, queries, database, ks[-1])
        stored, provenance, code = int(stage.stored_bytes(context)), stage.provenance(), stage_fingerprint(stage)
        ceiling = {}
        if positives is not None:
            from ..evaluation.metrics import correct_at

            ceiling = {"ceiling_recall": round(100 * float(correct_at(given.indices, positives).any(1).mean()), 4)}
        costs.append({**ceiling, "name": stage.name, "track": stage.track, "options": stage.options.model_dump(mode="json"),
                      "candidates_in": given.k, "ms_per_query": round(1000 * seconds / max(queries, 1), 3),
                      "seconds": round(seconds, 3), "stored_bytes_per_database_image": round(stored / max(database, 1), 1),
                      "peak_rss_bytes": after, "peak_rss_growth_bytes": after - before,
                      "features_computed": context.features_computed - computed,
                      **({"provenance": provenance} if provenance else {}), **({"fingerprint": code} if code else {})})
    return candidates, costs
