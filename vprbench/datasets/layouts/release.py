"""`folders`: image folders plus one ground-truth source, configured by manifest options.

This one reader covers the AnyLoc authors' release layouts (Baidu Mall, Gardens Point,
Hawkins, Laurel Caverns, Nardo-Air, VP-Air, Mid-Atlantic Ridge):

    [options]
    database = "db_images"            # or a list of folders, concatenated in order
    queries = "q_images"
    [options.ground_truth]
    kind = "positive-lists"           # see below
    file = "eiffel_gt.npy"

Ground-truth kinds (images are indexed in natural name order, as the authors' loaders do):
- positive-lists: .npy rows [index, [database indices]]; row r (after `skip_rows`) is query r.
- pose-rows: .npy of poses; rows `database_rows = [start, stop]` and `query_rows` give the
  database and query positions (first `dimensions` columns, metres); radius from the manifest.
- camera-files: one pose file per image (`database_poses`, `query_poses` folders, same stem,
  `suffix`); the camera centre is the second-to-last line; radius in metres.
- top-k-csv: a CSV with one row per query; the database indices in `columns` are positives.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from ...images import list_images
from .base import from_manifest, layout, require
from .npy import as_indices, read_npy
from .vpr_bench import load_rows


def as_list(value) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def folders_expects(options: dict) -> list[str]:
    gt = options.get("ground_truth", {})
    expected = [f + "/" for f in as_list(options.get("database", "database"))]
    expected.append(options.get("queries", "queries") + "/")
    if gt.get("kind") == "camera-files":
        expected += [gt["database_poses"] + "/", gt["query_poses"] + "/"]
    elif "file" in gt:
        expected.append(gt["file"])
    return expected


def positive_lists(path: Path, gt: dict, n_queries: int) -> list[np.ndarray]:
    rows = load_rows(path)[int(gt.get("skip_rows", 0)):]
    if len(rows) != n_queries:
        raise VPRBenchError(
            f"Ground truth {path} has {len(rows)} query rows (after skipping {gt.get('skip_rows', 0)}) "
            f"but {n_queries} query images were found; the images or the file are incomplete."
        )
    try:
        return [as_indices(p) for p in rows[:, 1]]
    except (ValueError, TypeError) as error:
        raise VPRBenchError(f"Cannot read ground truth {path}: {error}; expected integer positive lists.") from None


def pose_rows(path: Path, gt: dict, n_database: int, n_queries: int) -> tuple[np.ndarray, np.ndarray]:
    dims = int(gt.get("dimensions", 2))
    expected = f"an (N, >= {dims}) array of positions"
    poses = read_npy(path, "poses", expected)
    try:
        poses = np.asarray(poses[:, :dims], dtype=np.float64)
    except (ValueError, TypeError, IndexError, OverflowError) as error:  # OverflowError: an int beyond any float
        raise VPRBenchError(f"Cannot read poses {path}: {error}. Expected {expected}.") from None
    if poses.shape[1] < dims:
        raise VPRBenchError(f"Cannot read poses {path}: {poses.shape[1]} columns. Expected {expected}.")
    if not np.isfinite(poses).all():
        raise VPRBenchError(f"Cannot read poses {path}: they hold non-finite numbers (NaN or infinity). Expected {expected}.")
    parts = []
    for split, (start, stop), count in (("database", gt["database_rows"], n_database), ("query", gt["query_rows"], n_queries)):
        if stop > len(poses):
            raise VPRBenchError(f"Poses {path} have {len(poses)} rows; the {split} needs rows {start}:{stop}. The file is incomplete.")
        if stop - start != count:
            raise VPRBenchError(
                f"Poses {path}: the {split} uses rows {start}:{stop} ({stop - start} poses) "
                f"but {count} {split} images were found; the image folder is incomplete or has extra files."
            )
        parts.append(poses[start:stop])
    return parts[0], parts[1]


def camera_centre(path: Path) -> np.ndarray:
    """Camera centre (x, y, z) = the second-to-last line of a Baidu Mall .camera file."""
    try:
        lines = path.read_text(encoding="utf-8").strip().splitlines()
        centre = np.array(lines[-2].split(), dtype=np.float64)
        if centre.shape != (3,) or not np.isfinite(centre).all():
            raise ValueError(f"its second-to-last line holds {centre.size} numbers, expected 3 finite ones")
    except (OSError, ValueError, IndexError) as error:
        raise VPRBenchError(f"Cannot read camera pose {path}: {error}.") from None
    return centre


def camera_positions(images: list[Path], folder: Path, suffix: str) -> np.ndarray:
    missing = [p.stem for p in images if not (folder / (p.stem + suffix)).is_file()]
    if missing:
        raise VPRBenchError(
            f"{len(missing)} image(s) have no pose file in {folder}, e.g. {missing[0]}{suffix}; "
            "the pose folder is incomplete."
        )
    return np.stack([camera_centre(folder / (p.stem + suffix)) for p in images]) if images else np.zeros((0, 3))


def _index_cell(text):
    """A cell's text as a whole number (an int however long) or a float for as_indices to judge; an
    empty cell (NaN) and other text are left as they are, and refused there by name."""
    if not isinstance(text, str):
        return text
    for parse in (int, float):
        try:
            return parse(text)
        except ValueError:
            pass
    return text


def top_k_csv(path: Path, gt: dict, n_queries: int) -> list[np.ndarray]:
    import pandas as pd

    columns = gt.get("columns", [f"top_{k}_ref_ind" for k in range(1, 6)])
    try:  # read as text, each cell parsed by Python: pandas's own parse of a long number differs by version
        table = pd.read_csv(path, dtype=str)
        values = [as_indices([_index_cell(cell) for cell in row]) for row in table[columns].to_numpy()]
    except (OSError, ValueError, KeyError) as error:
        raise VPRBenchError(f"Cannot read ground truth {path}: {str(error).strip()}. Expected columns {columns}.") from None
    if len(values) != n_queries:
        raise VPRBenchError(f"Ground truth {path} has {len(values)} rows but {n_queries} query images were found.")
    return values


@layout("folders", expects=folders_expects)
def read_folders(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    database = [p for f in as_list(opts.get("database", "database")) for p in list_images(require(root, f, manifest), natural=True)]
    queries = list_images(require(root, opts.get("queries", "queries"), manifest), natural=True)
    if not database or not queries:
        raise VPRBenchError(f"Dataset {manifest.name!r}: found {len(database)} database and {len(queries)} query images under {root}.")
    gt = opts.get("ground_truth", {})
    kind = gt.get("kind")
    if kind == "positive-lists":
        lists = positive_lists(require(root, gt["file"], manifest, "file"), gt, len(queries))
        ground_truth = GroundTruth(unit="positives", radius=manifest.radius, positive_lists=lists)
    elif kind == "top-k-csv":
        lists = top_k_csv(require(root, gt["file"], manifest, "file"), gt, len(queries))
        ground_truth = GroundTruth(unit="positives", radius=manifest.radius, positive_lists=lists)
    elif kind == "pose-rows":
        db_pos, q_pos = pose_rows(require(root, gt["file"], manifest, "file"), gt, len(database), len(queries))
        ground_truth = GroundTruth(unit="metres", radius=manifest.radius, database_positions=db_pos, query_positions=q_pos)
    elif kind == "camera-files":
        suffix = gt.get("suffix", ".camera")
        db_pos = camera_positions(database, require(root, gt["database_poses"], manifest), suffix)
        q_pos = camera_positions(queries, require(root, gt["query_poses"], manifest), suffix)
        ground_truth = GroundTruth(unit="metres", radius=manifest.radius, database_positions=db_pos, query_positions=q_pos)
    else:
        raise VPRBenchError(f"Dataset {manifest.name!r}: unknown ground-truth kind {kind!r} in its manifest.")
    return from_manifest(manifest, root, database, queries, ground_truth)
