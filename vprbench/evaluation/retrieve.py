"""Retrieval: a method's stored descriptors post-processed (postprocess.py) and searched, exactly
(search/exact.py) or with an approximate index (search/approximate.py): the top K per query."""
from __future__ import annotations

import time

from ..errors import VPRBenchError
from ..row_sources import DEFAULT_MEMORY_BUDGET, as_rows, parse_memory
from ..search.approximate import approximate_search
from ..search.exact import INDEXES, SearchResult, exact_search
from ..search.row_checks import check_pair
from .postprocess import postprocessed


def retrieve(method, database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET, index: str = "exact",
             state_folder=None, index_options: dict | None = None, fit_on=None, check=None) -> SearchResult:
    """Top-k database rows per query for `method`'s descriptors, within `memory_budget` bytes
    (or "1GB"): its post-processor fitted on the database or on `fit_on` (rows of several
    databases, joint.py), or loaded from `state_folder` (default the folder of the rows it is
    fitted on), applied chunk by chunk, then searched with `index`
    ("exact", "ivf-pq" or "hnsw"; `index_options` tune the approximate ones, see
    search/approximate.py). `method` None searches the rows as they are. The result's info is the
    result record's "search" section. `check(database, queries, parts=())`, if given, sees the rows
    as the search reads them before it starts (the run's budget plan, budget.py), and before a
    post-processor is fitted, when it says its output's shape, those rows by shape with the fit's
    need in `parts` ((part, bytes), postprocess.planned)."""
    budget = parse_memory(memory_budget)
    if index not in INDEXES:
        raise VPRBenchError(f"Unknown index {index!r}: use one of {', '.join(INDEXES)}.")
    database, queries = as_rows(database, "database"), as_rows(queries, "queries")
    if getattr(method, "compare", "cosine") != "cosine":
        return compared_search(method, database, queries, k, index, index_options, budget, check)
    database, queries, postprocess = postprocessed(method, database, queries, budget, state_folder, fit_on, check)
    if check is not None:  # again on the rows made (a plugin's state it did not say, a state loaded, not fitted)
        check(database, queries)
    started = time.perf_counter()
    if index == "exact":
        if index_options:
            raise VPRBenchError(f"index='exact' takes no index options, got {sorted(index_options)}: drop them, or "
                                "choose an approximate index (index='ivf-pq' or 'hnsw').")
        result = exact_search(database, queries, k, memory_budget=budget)
    else:
        result = approximate_search(database, queries, k, kind=index, memory_budget=budget, options=index_options)
    result.info.update(dim=database.dim, postprocess=postprocess, search_s=round(time.perf_counter() - started, 3))
    return result


def compared_search(method, database, queries, k: int, index: str, index_options, budget: int,
                    check=None) -> SearchResult:
    """Exact top-k for a method whose descriptors are compared by a distance (the mean absolute
    difference of `sad`): the sequence search with sequences of one frame; scores are minus the
    distance, so higher is still better."""
    from ..stages.sequence.search import sequence_search

    check_compare(method.name, method.compare, index, index_options)
    started = time.perf_counter()
    check_pair(database, queries, k)
    if check is not None:
        check(database, queries)
    found = sequence_search(database, queries, k, score="diagonal", compare=method.compare, length=1,
                            memory_budget=budget)
    return SearchResult(found.scores, found.indices, {
        "index": "exact", "compare": method.compare, "memory_budget": budget, "block_rows": found.info["block_rows"],
        "dim": database.dim, "postprocess": None, "search_s": round(time.perf_counter() - started, 3),
        "tie_order": "distance ascending, then database index ascending"})


def check_compare(name: str, compare: str | None, index: str, index_options=None) -> None:
    """Refuse a search other than exact for method `name` whose descriptors are compared by a
    distance (`compare`, e.g. sad's; None: not known until the method is made): the indexes rank by
    inner product. The one check, made when a spec is resolved (a plan lists it with its other
    problems), when its method is made (before any image is described) and here."""
    if compare not in (None, "cosine") and (index != "exact" or index_options):
        raise VPRBenchError(f"Method {name!r} compares descriptors by {compare}, which only exact search does; drop "
                            f"--index {index} (and its options; in a plan, its search) for this method.")
