"""One evaluation, top to bottom: describe both splits (through the store), post-process, search, score."""
from __future__ import annotations

import time

from ..datasets import Dataset
from ..distributed import Ranks
from ..methods import Method
from ..rows import DEFAULT_MEMORY_BUDGET
from .extract import describe_splits
from .metrics import DEFAULT_KS, check_ks
from .record import result_record
from .search import retrieve


def evaluate(method: Method, dataset: Dataset, *, ks=DEFAULT_KS, cache_dir=None, progress=None, workers: int = 0,
             store_dtype: str = "float32", lock_timeout: float | None = None, ranks: Ranks | None = None,
             memory_budget=DEFAULT_MEMORY_BUDGET, index: str = "exact", index_options: dict | None = None) -> dict | None:
    """Recall@K and PR metrics of `method` on `dataset`, with a full result record.

    Descriptors come from the stores (computed where missing: `describe_splits`); retrieval
    streams them within `memory_budget` (`retrieve`: post-processing, exact or approximate
    `index`). Under torchrun (`ranks` from `Ranks.from_environment()`) every rank describes
    its shard; rank 0 returns the record, the other ranks None.
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
    timings = {"fit_s": described.timings["fit_s"], "database_s": described.timings["database_s"],
               "queries_s": described.timings["queries_s"]}
    t = time.perf_counter()
    found = retrieve(method, described.stores["database"], described.stores["queries"], ks[-1],
                     memory_budget=memory_budget, index=index, index_options=index_options)
    timings["search_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - started
    context = {"store": {"folder": described.folder.key}}  # where the descriptors are (vprbench.store.run_store)
    if ranks.distributed:
        context["distributed"] = {**ranks.describe(), "computed_per_rank": described.per_rank}
    return result_record(
        method=method, fingerprint=described.fingerprint, dataset=dataset, dataset_key=dataset.fingerprint(), ks=ks,
        scores=found.scores, indices=found.indices, positives=positives, descriptor_dim=int(found.info["dim"]),
        computed=described.computed, timings=timings, search=found.info, context=context,
    )
