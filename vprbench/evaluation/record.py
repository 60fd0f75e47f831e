"""The result record: everything needed to read, compare and repeat one evaluation."""
from __future__ import annotations

import json
import os
import platform
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .. import __version__
from ..paths import cache_root


def environment() -> dict:
    import faiss
    import h5py
    import torch

    versions = {"vprbench": __version__, "python": platform.python_version(), "numpy": np.__version__,
                "torch": torch.__version__, "faiss": faiss.__version__, "h5py": h5py.__version__}
    hardware = {"platform": platform.platform(), "machine": platform.machine(),
                "processor": platform.processor() or None, "cpu_count": os.cpu_count(),
                "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    return {"versions": versions, "hardware": hardware}


def result_record(*, method, fingerprint, dataset, dataset_key, ks, scores, indices, positives,
                  descriptor_dim, computed, timings, search=None, context=None) -> dict:
    """The record of one run, from the search's top-K (scores and database indices per query):
    every metric is computed here, from what the record keeps."""
    from .metrics import correct_at, recall_at_k, top1_precision_recall

    recalls = recall_at_k(indices, positives, ks)
    pr = top1_precision_recall(scores[:, 0], correct_at(indices[:, :1], positives)[:, 0])
    predictions = indices[:, : min(ks[-1], 5)]
    summary = dataset.summary()
    described = computed["database"] + computed["queries"]
    extract_s = timings["database_s"] + timings["queries_s"]
    return {
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "method": method.name,
        "method_options": {k: list(v) if isinstance(v, tuple) else v for k, v in method.options.items()},
        "method_fingerprint": fingerprint,
        "dataset": dataset.name,
        "dataset_fingerprint": dataset_key,
        "domain": dataset.domain,
        "counts": {
            "database": summary["database"], "queries": summary["queries"],
            "queries_without_positives": summary["queries"] - summary["queries_with_positives"],
            "positive_pairs": summary["positive_pairs"],
        },
        "ground_truth": {"unit": summary["unit"], "radius": summary["radius"]},
        "descriptor_dim": descriptor_dim,
        "recall": {str(k): round(v, 4) for k, v in recalls.items()},
        "auc_pr": round(pr["auc_pr"], 6),
        "recall_at_100_precision": round(pr["recall_at_100_precision"], 6),
        "pr_curve": pr["curve"],
        "descriptors_computed": computed,
        "timings": {k: round(v, 4) for k, v in timings.items()},
        "images_per_second": round(described / extract_s, 3) if described and extract_s > 0 else None,
        "top_predictions": np.asarray(predictions).tolist(),
        "provenance": method.provenance(),
        "search": search or {"index": "exact"},
        **({"context": context} if context else {}),
        **environment(),
    }


def results_path(cache_dir=None) -> Path:
    return cache_root(cache_dir) / "results.jsonl"


def append_result(record: dict, cache_dir=None) -> Path:
    """One JSON line per evaluation; a single write keeps lines whole."""
    path = results_path(cache_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps(record, sort_keys=True) + "\n"
    with open(path, "a", encoding="utf-8") as f:
        f.write(line)
    return path


def read_results(cache_dir=None) -> list[dict]:
    path = results_path(cache_dir)
    if not path.is_file():
        return []
    records = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.strip():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                import warnings

                warnings.warn(f"{path}:{number} is not a JSON record; skipped.", stacklevel=2)
    return records
