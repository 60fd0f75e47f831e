"""The `images/<split>/{database,queries}` layout whose file names carry UTM coordinates.

File names follow `@easting@northing@zone_number@zone_letter@latitude@longitude@...@.jpg`
(the convention of the VPR datasets downloader used for Pitts-30k, Pitts-250k, Tokyo 24/7,
St Lucia, MSLS, SPED...). A query's positives are the database images within `radius`
metres (easting/northing plane), as in the AnyLoc and deep-visual-geo-localization code, and
in the same UTM zone (number and hemisphere): the zones' planes are apart (utm_zones.py).

Options: `split` ("test"), `database` ("database"), `queries` ("queries").
"""
from __future__ import annotations

from pathlib import Path

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from ...images import list_images
from .base import from_manifest, layout, require
from .utm_zones import positions_from_names, warn_cross_zone_pairs


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
    positions, zones = positions_from_names(database + queries, root)  # one check of the zones across both splits
    ground_truth = GroundTruth(
        unit="metres",
        radius=manifest.radius,
        database_positions=positions[: len(database)],
        query_positions=positions[len(database):],
        database_zones=zones[: len(database)],
        query_zones=zones[len(database):],
    )
    warn_cross_zone_pairs(ground_truth, database, queries, root)
    return from_manifest(manifest, root, database, queries, ground_truth)
