"""Which datasets are ordered traverses, and each split's images in capture order.

Sequence matching compares a query's neighbours in time with neighbours in the database, so
it needs both splits to be traverses (a camera driven or walked along a route, frame after
frame). A manifest says how its capture order is known (`sequence_order`):

- "listing": the images as listed (Corridor, Nordland, Gardens Point: frame-numbered names);
- "file-name-frame": by the frame number closing the 7th '@' field of each file name
  (St Lucia: `@easting@northing@zone@letter@lat@lon@<date>_<time>_<frame>@...`);
- "" (the default): not a traverse (Pitts-30k, Tokyo 24/7: places photographed one by one).

A folder of one's own is a traverse when positions.csv gives frame numbers (column `frame`):
each split in frame order.
"""
from __future__ import annotations

import numpy as np

from ..errors import VPRBenchError
from .manifest import dataset_manifest


def traverse_orders(dataset, stage: str = "Sequence matching") -> dict[str, np.ndarray]:
    """{"database": ..., "queries": ...}: each split's image indices in capture order, or one
    line saying why `dataset` is no traverse and where sequences do run."""
    how = getattr(dataset, "sequence_order", "")
    if dataset.kind == "own" and dataset.ground_truth.unit == "frames":
        gt = dataset.ground_truth
        return {"database": _by_frame(gt.database_positions), "queries": _by_frame(gt.query_positions)}
    if how == "listing":
        return {split: np.arange(len(getattr(dataset, split)), dtype=np.int64) for split in ("database", "queries")}
    if how == "file-name-frame":
        return {split: _by_name_frame(getattr(dataset, split), dataset.name) for split in ("database", "queries")}
    raise VPRBenchError(_not_a_traverse(stage, dataset.name, " (its positions are not frame numbers)"
                                        if dataset.kind == "own" else ""))


def require_traverse_manifest(name: str, stage: str = "Sequence matching") -> None:
    """Refuse a benchmark that is no traverse from its manifest alone (before its data is read)."""
    if not dataset_manifest(name).sequence_order:
        raise VPRBenchError(_not_a_traverse(stage, name, ""))


def _not_a_traverse(stage: str, name: str, why: str) -> str:
    return (f"{stage} needs a dataset whose database and queries are ordered traverses (frames in capture order); "
            f"{name!r} is not one{why}: its images are separate photographs of places, so a query has no "
            "neighbours in time to match. Use Nordland, St Lucia, Corridor or Gardens Point, or a folder of your own "
            "whose positions.csv gives a frame column.")


def _by_frame(positions) -> np.ndarray:
    frames = np.asarray(positions, dtype=np.float64).reshape(len(positions), -1)[:, 0]
    return np.argsort(frames, kind="stable").astype(np.int64)


def _by_name_frame(paths, name: str) -> np.ndarray:
    frames = []
    for path in paths:
        parts = path.name.split("@")
        field = parts[7].rsplit("_", 1)[-1] if len(parts) > 7 else ""
        if not field.isdigit():
            raise VPRBenchError(f"Dataset {name!r}: file {path.name!r} has no frame number in its 7th '@' field "
                                "(e.g. @...@210809_1210_02647@.jpg), so its capture order is unknown; the files are "
                                "not that release's.")
        frames.append(int(field))
    return np.argsort(np.array(frames, dtype=np.int64), kind="stable").astype(np.int64)
