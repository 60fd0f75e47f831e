"""Synthetic result records built by the real record builder (`result_record`) from a made-up
search: a dataset with the real Corridor's counts and ground-truth rule (or any other), a
method with declared weights, and top-K lists whose quality is chosen."""
from __future__ import annotations

import numpy as np

from vprbench.datasets.model import Dataset, GroundTruth
from vprbench.methods import Method
from vprbench.spec import RUN_SETTINGS, DatasetSpec, RunSpec, SearchSpec
from vprbench.spec_options import plain


class FakeMethod(Method):
    def __init__(self, name, options, weights, needs_fit=False):
        self.name, self.options, self._weights, self.needs_fit = name, dict(options), weights, needs_fit

    def describe(self, images):  # pragma: no cover - never called: the search is made up
        raise AssertionError

    def provenance(self):
        return {"weights": dict(self._weights)}


def synthetic_ground_truth(n_database, n_queries, unit="positives", radius=None):
    """Database and queries along one line; each query's positives are its ~5 database neighbours,
    in the manifest's own unit (explicit lists, frames or metres) so the protocol matches."""
    if unit == "positives":
        lists = [np.arange(max(0, q * n_database // n_queries - 2), min(n_database, q * n_database // n_queries + 3))
                 for q in range(n_queries)]
        return GroundTruth("positives", radius=radius, positive_lists=lists)
    step = float(radius) / 2
    database = np.arange(n_database, dtype=float)[:, None] * step
    queries = (np.arange(n_queries) * n_database // n_queries).astype(float)[:, None] * step
    if unit == "metres":
        database, queries = np.hstack([database, 0 * database]), np.hstack([queries, 0 * queries])
    return GroundTruth(unit, radius=radius, database_positions=database, query_positions=queries)


def synthetic_search(positives, n_database, k, quality, seed):
    """The top-1 is a positive with probability `quality`; the rest of the top K is drawn at
    random (without repeats)."""
    rng = np.random.default_rng(seed)
    n_queries = len(positives)
    draws = rng.integers(0, n_database, size=(n_queries, 3 * k + 10))
    hit = rng.random(n_queries) < quality
    indices = np.empty((n_queries, k), dtype=np.int64)
    for q in range(n_queries):
        order = draws[q].tolist()
        if hit[q]:
            order = [int(positives[q][len(positives[q]) // 2])] + [d for d in order if d not in set(positives[q].tolist())]
        indices[q] = list(dict.fromkeys(order))[:k]
    scores = np.sort(rng.random((n_queries, k)).astype(np.float32), axis=1)[:, ::-1]
    return scores, indices, positives


def synthetic_spec(method: str, options: dict, weights: dict, data: Dataset, ks, search: dict, stages=()) -> RunSpec:
    """The spec such a run would have (the method need not be registered: the search is made up;
    `stages` are named, as on the command line, e.g. [{"name": "diagonal", "length": 5}])."""
    from vprbench.spec import resolve_stage

    protocol = data.protocol
    kind = "own" if protocol["name"] == "own" else "benchmark"
    files = {"weights": f"sha256:{weights['sha256']}"} if weights.get("sha256") else {}
    options = {k: v for k, v in options.items() if k not in RUN_SETTINGS}
    return RunSpec(method=method, options=plain(options), given=plain(options), files=files,
                   dataset=DatasetSpec(name=data.name, kind=kind, protocol=protocol["name"], protocol_id=protocol["id"],
                                       protocol_hash=protocol["hash"]),
                   search=SearchSpec(**search), ks=tuple(ks), stages=tuple(resolve_stage(s) for s in stages))
