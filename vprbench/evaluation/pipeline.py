"""One evaluation, top to bottom: describe both splits (through the store), post-process, search, score."""
from __future__ import annotations

import time

from ..datasets import Dataset
from ..distributed import Ranks
from ..methods import Method
from .extract import describe_splits
from .metrics import DEFAULT_KS, check_ks, search
from .record import result_record


def evaluate(method: Method, dataset: Dataset, *, ks=DEFAULT_KS, cache_dir=None, progress=None, workers: int = 0,
             store_dtype: str = "float32", lock_timeout: float | None = None, ranks: Ranks | None = None) -> dict | None:
    """Recall@K and PR metrics of `method` on `dataset`, with a full result record.

    Under torchrun (`ranks` from `Ranks.from_environment()`) every rank describes its shard;
    rank 0 returns the record, the other ranks None.
    """
    started = time.perf_counter()
    ranks = ranks or Ranks()
    ks = check_ks(ks, len(dataset.database))
    positives = dataset.positives
    method.use_dataset(dataset.name)
    described = describe_splits(
        method, {"database": dataset.database, "queries": dataset.queries}, root=dataset.root, label=dataset.name,
        image_keys=dataset.images_fingerprint(cache_dir), cache_dir=cache_dir, store_dtype=store_dtype,
        workers=workers, lock_timeout=lock_timeout, ranks=ranks, progress=progress)
    if described.stores is None:  # not rank 0: its shard is written; rank 0 evaluates
        return None
    database, queries = described.stores["database"], described.stores["queries"]
    database, queries = method.postprocess(database.read_rows(0, database.row_count),
                                           queries.read_rows(0, queries.row_count))
    timings = {"fit_s": described.timings["fit_s"], "database_s": described.timings["database_s"],
               "queries_s": described.timings["queries_s"]}
    t = time.perf_counter()
    scores, indices = search(database, queries, ks[-1])
    timings["search_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - started
    context = None
    if ranks.distributed:
        context = {"distributed": {**ranks.describe(), "computed_per_rank": described.per_rank}}
    return result_record(
        method=method, fingerprint=described.fingerprint, dataset=dataset, dataset_key=dataset.fingerprint(), ks=ks,
        scores=scores, indices=indices, positives=positives,
        descriptor_dim=int(database.shape[1]), computed=described.computed, timings=timings, context=context,
    )
