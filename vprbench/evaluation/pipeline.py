"""One evaluation, top to bottom: fit on the database, describe (through the store), search, score."""
from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..datasets import Dataset
from ..errors import VPRBenchError
from ..methods import Method
from ..store import DescriptorStore
from .metrics import DEFAULT_KS, check_ks, search
from .record import result_record


def _names(dataset: Dataset, paths: Sequence[Path]) -> list[str]:
    root = dataset.root
    return [str(p.relative_to(root)) if root and p.is_relative_to(root) else p.name for p in paths]


def _checked(method: Method, descriptors, n: int) -> np.ndarray:
    out = np.asarray(descriptors, dtype=np.float32)
    if out.ndim != 2 or out.shape[0] != n:
        raise VPRBenchError(f"Method {method.name!r} returned shape {out.shape} for {n} images; expected ({n}, dim).")
    if not np.isfinite(out).all():
        raise VPRBenchError(f"Method {method.name!r} returned non-finite descriptors.")
    return out


def extract(method: Method, paths: Sequence[Path], store: DescriptorStore, progress=None, label="") -> int:
    """Describe the images the store lacks; returns how many were computed now."""
    if store.complete:
        return 0
    handle, done = None, None
    dim = store.partial_dim()
    if dim is not None:
        handle, done = store.open_partial(dim)
    todo = [i for i in range(len(paths)) if done is None or not done[i]]
    task = progress.add_task(label, total=len(paths), completed=len(paths) - len(todo)) if progress else None
    try:
        for start in range(0, len(todo), max(1, method.batch_size)):
            rows = todo[start:start + method.batch_size]
            descriptors = _checked(method, method.describe([paths[i] for i in rows]), len(rows))
            if handle is None:
                handle, done = store.open_partial(descriptors.shape[1])
            store.write_rows(handle, rows, descriptors)
            if progress:
                progress.advance(task, len(rows))
        if handle is None:  # nothing to describe: an empty split
            raise VPRBenchError(f"No images to describe for {label or 'this split'}.")
        store.finish(handle)
        handle = None
    finally:
        if handle is not None:
            handle.close()
    return len(todo)


def evaluate(method: Method, dataset: Dataset, *, ks=DEFAULT_KS, cache_dir=None, progress=None) -> dict:
    """Recall@K and PR metrics of `method` on `dataset`, with a full result record."""
    started = time.perf_counter()
    ks = check_ks(ks, len(dataset.database))
    positives = dataset.positives
    method.use_dataset(dataset.name)
    fingerprint = {"method": method.name, **method.fingerprint()}
    key = dataset.fingerprint()
    stores = {
        split: DescriptorStore.for_split(method.name, fingerprint, dataset.name, key, split, _names(dataset, paths), cache_dir)
        for split, paths in (("database", dataset.database), ("queries", dataset.queries))
    }
    timings = {"fit_s": 0.0, "database_s": 0.0, "queries_s": 0.0}
    computed = {"database": 0, "queries": 0}
    if not all(s.complete for s in stores.values()) and method.needs_fit:
        state = stores["database"].read_fit_state()
        if state is None:
            t = time.perf_counter()
            method.fit(dataset.database)
            timings["fit_s"] = time.perf_counter() - t
            stores["database"].save_fit_state(method.fit_state())
        else:
            method.load_fit_state(state)
    for split, paths in (("database", dataset.database), ("queries", dataset.queries)):
        t = time.perf_counter()
        computed[split] = extract(method, paths, stores[split], progress, f"{method.name} {dataset.name} {split}")
        timings[f"{split}_s"] = time.perf_counter() - t
    database, queries = method.postprocess(stores["database"].read(), stores["queries"].read())

    t = time.perf_counter()
    scores, indices = search(database, queries, ks[-1])
    timings["search_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - started
    return result_record(
        method=method, fingerprint=fingerprint, dataset=dataset, dataset_key=key, ks=ks,
        scores=scores, indices=indices, positives=positives,
        descriptor_dim=int(database.shape[1]), computed=computed, timings=timings,
    )
