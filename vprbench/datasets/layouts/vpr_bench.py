"""VPR-Bench layout: ref/, query/ and ground_truth_new.npy (rows [query index, [positive ref indices]])."""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ...images import list_images
from ..manifest import DatasetManifest
from ..model import GroundTruth
from . import from_manifest, layout, require


def read_positive_lists(path: Path, n_queries: int) -> list[np.ndarray]:
    """VPR-Bench's object array of [query_index, [db indices]] rows -> one array per query."""
    try:
        rows = np.load(path, allow_pickle=True)
        lists: list[np.ndarray] = [np.zeros(0, np.int64) for _ in range(n_queries)]
        for query, positives in rows:
            lists[int(query)] = np.asarray(positives, dtype=np.int64).reshape(-1)
    except (OSError, ValueError, TypeError, IndexError, EOFError, pickle.UnpicklingError) as error:
        raise VPRBenchError(
            f"Cannot read ground truth {path}: {error}. Expected VPR-Bench rows "
            "[query_index, [positive reference indices]] for each of the "
            f"{n_queries} queries; re-download the file."
        ) from None
    return lists


@layout("vpr-bench")
def read_vpr_bench(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    database = list_images(require(root, opts.get("database", "ref"), manifest))
    queries = list_images(require(root, opts.get("queries", "query"), manifest))
    gt_path = require(root, opts.get("ground_truth", "ground_truth_new.npy"), manifest, kind="file")
    ground_truth = GroundTruth(
        unit="positives", radius=manifest.radius, positive_lists=read_positive_lists(gt_path, len(queries))
    )
    return from_manifest(manifest, root, database, queries, ground_truth)
