"""The `images/<split>/{database,queries}` layout whose file names carry UTM coordinates.

File names follow `@easting@northing@zone_number@zone_letter@latitude@longitude@...@.jpg`
(the convention of the VPR datasets downloader used for Pitts-30k, Pitts-250k, Tokyo 24/7,
St Lucia, MSLS, SPED...). A query's positives are the database images within `radius`
metres (easting/northing plane), as in the AnyLoc and deep-visual-geo-localization code.

Options: `split` ("test"), `database` ("database"), `queries` ("queries").
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from ...images import list_images
from .base import from_manifest, layout, require
from .own_data import utm_from_name


def utm_positions(paths: list[Path], root: Path) -> np.ndarray:
    """(N, 2) easting/northing from the file names, naming the first file that has none."""
    if not paths:
        return np.zeros((0, 2))
    try:
        return np.array([utm_from_name(p) for p in paths], dtype=np.float64)
    except VPRBenchError as error:
        raise VPRBenchError(f"{error} (under {root})") from None


def split_folder(options: dict) -> str:
    return f"images/{options.get('split', 'test')}"


def utm_expects(options: dict) -> list[str]:
    base = split_folder(options)
    return [f"{base}/{options.get('database', 'database')}/", f"{base}/{options.get('queries', 'queries')}/"]


@layout("utm-names", expects=utm_expects)
def read_utm_names(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    base = split_folder(opts)
    database = list_images(require(root, f"{base}/{opts.get('database', 'database')}", manifest), recursive=True, natural=True)
    queries = list_images(require(root, f"{base}/{opts.get('queries', 'queries')}", manifest), recursive=True, natural=True)
    if not database or not queries:
        raise VPRBenchError(
            f"Dataset {manifest.name!r}: no images in {root / base}/database or {root / base}/queries "
            f"({len(database)} database, {len(queries)} query images found)."
        )
    if manifest.radius is None:
        raise VPRBenchError(f"Dataset {manifest.name!r}: its manifest needs a radius (metres) for layout 'utm-names'.")
    ground_truth = GroundTruth(
        unit="metres",
        radius=manifest.radius,
        database_positions=utm_positions(database, root),
        query_positions=utm_positions(queries, root),
    )
    return from_manifest(manifest, root, database, queries, ground_truth)
