"""VPR-Bench layout: ref/, query/ and ground_truth_new.npy (rows [query index, [positive ref indices]]).

Options: `database`, `queries`, `ground_truth` (names), `drop_out_of_range` (VPR-Bench's
17 Places and Gardens Point lists name frames past the last reference; the AnyLoc code keeps
only positives that exist among the references, and so do we when this is true).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from ...images import list_images
from ...text import plural
from .base import from_manifest, layout, require
from .npy import as_indices, read_npy

ROWS = ("rows [query_index, [positive reference indices]] of integers; the file is damaged "
        "or not this dataset's; re-download it")


def load_rows(path: Path) -> np.ndarray:
    """An .npy of [index, [positives]] rows (an object array, read without unpickling code)."""
    rows = read_npy(path, "ground truth", ROWS)
    if rows.ndim != 2 or rows.shape[1] < 2:
        raise VPRBenchError(f"Cannot read ground truth {path}: shape {rows.shape}. Expected {ROWS}.")
    return rows


def read_positive_lists(path: Path, n_queries: int) -> list[np.ndarray]:
    """VPR-Bench's object array of [query_index, [db indices]] rows -> one array per query."""
    rows = load_rows(path)
    lists: list[np.ndarray | None] = [None] * n_queries
    try:
        for query, positives in rows[:, :2]:
            if isinstance(query, (list, tuple)) or getattr(query, "ndim", 0):  # else read as its first number
                raise ValueError(f"{query!r} is not a query index (one whole number)")
            query = int(as_indices(query)[0])
            # a query without its row would be scored as a failure, unseen; -1 would wrap to the last
            if not 0 <= query < n_queries:
                raise IndexError(f"a row for query {query}, outside 0..{n_queries - 1}")
            if lists[query] is not None:
                raise ValueError(f"two rows for query {query}")
            lists[query] = as_indices(positives)
            if lists[query].tolist() == [-1]:  # VPR-Bench's mark of a query with no true match (GardensPoint_TN)
                lists[query] = lists[query][:0]
        missing = [q for q, found in enumerate(lists) if found is None]
        if missing:
            raise ValueError(f"no row for {len(missing)} of the {n_queries} query images (the first: query {missing[0]})")
    except (ValueError, TypeError, IndexError) as error:
        raise VPRBenchError(
            f"Cannot read ground truth {path}: {error}. Expected VPR-Bench rows "
            "[query_index, [positive reference indices]] for each of the "
            f"{n_queries} queries; the images or the file are incomplete: re-download them."
        ) from None
    return lists


def vpr_bench_expects(options: dict) -> list[str]:
    return [options.get("database", "ref") + "/", options.get("queries", "query") + "/",
            options.get("ground_truth", "ground_truth_new.npy")]


@layout("vpr-bench", expects=vpr_bench_expects)
def read_vpr_bench(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    database = list_images(require(root, opts.get("database", "ref"), manifest), natural=True)
    queries = list_images(require(root, opts.get("queries", "query"), manifest), natural=True)
    gt_path = require(root, opts.get("ground_truth", "ground_truth_new.npy"), manifest, kind="file")
    lists = read_positive_lists(gt_path, len(queries))
    dropped = 0
    if opts.get("drop_out_of_range", False):  # frames past the last reference only: a negative is an error
        kept = [p[p < len(database)] for p in lists]
        dropped = sum(len(p) - len(k) for p, k in zip(lists, kept))
        lists = kept
    ground_truth = GroundTruth(unit="positives", radius=manifest.radius, positive_lists=lists)
    dataset = from_manifest(manifest, root, database, queries, ground_truth)
    if dropped:  # said by `datasets verify` and `info`, not only in the manifest's notes
        dataset.notes.append(f"{plural(dropped, 'positive')} of the ground truth name references past the "
                             f"{len(database)} there are: dropped, as AnyLoc evaluates")
    return dataset
