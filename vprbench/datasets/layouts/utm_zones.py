"""UTM positions and zones from file names `@easting@northing@zone_number@zone_letter@...@.jpg`.

Easting and northing are coordinates in one zone's plane: 500000 E in zone 10 and 500000 E in
zone 11 lie ~530 km apart. So positions are compared only within one zone, a zone being its
number and hemisphere (the letter band N..X is north, C..M south; bands of one hemisphere share
one northing system). Names that carry no zone (`@0@5000@@@...`, SPED's mock UTM) form one
plane, as before; names with and without a zone in one dataset are refused.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ...errors import VPRBenchError

#: the largest |coordinate| accepted: beyond it no real position lies, and distances overflow
MAX_COORDINATE = 1e12
#: UTM latitude bands, south to north (no I or O)
BANDS = "CDEFGHJKLMNPQRSTUVWX"


def utm_from_name(path: Path) -> tuple[float, float]:
    """(easting, northing) from a name like @0551234.5@4178910.2@10@S@....jpg"""
    parts = path.name.split("@")
    try:
        easting, northing = float(parts[1]), float(parts[2])
        if not (abs(easting) <= MAX_COORDINATE and abs(northing) <= MAX_COORDINATE):
            raise ValueError("not finite or out of range")
        return easting, northing
    except (IndexError, ValueError):
        raise VPRBenchError(
            f"Cannot read UTM coordinates from the file name {path.name!r}: expected "
            "'@easting@northing@...' (or provide positions.csv)."
        ) from None


def zone_from_name(path: Path) -> tuple[str, str]:
    """(zone, as written): zone "10 north" for "10S" ("" for a name without one). The last '@' field is the
    file's ending, never a zone ("@1@2@.jpg" has none)."""
    parts = path.name.split("@")
    number, letter = (parts[3] if len(parts) > 4 else ""), (parts[4] if len(parts) > 5 else "")
    if not number.strip() and not letter.strip():
        return "", ""
    written = f"{number}{letter}"
    if not (number.isdigit() and 1 <= int(number) <= 60 and len(letter) == 1 and letter.upper() in BANDS):
        raise VPRBenchError(
            f"Cannot read the UTM zone {written!r} from the file name {path.name!r}: expected a zone number 1-60 "
            "and a latitude band letter C-X after easting and northing (@0551234.50@4178910.20@10@S@...), "
            "or both fields empty."
        )
    return f"{int(number)} {'north' if letter.upper() >= 'N' else 'south'}", f"{int(number)}{letter.upper()}"


def positions_from_names(paths: list[Path], root: Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) easting/northing and (N,) zones from the file names, naming the first file that has none;
    names with a zone and names without one together are refused (their positions share no plane)."""
    try:
        positions = np.array([utm_from_name(p) for p in paths], dtype=np.float64).reshape(len(paths), 2)
        zones = [zone_from_name(p) for p in paths]
    except VPRBenchError as error:
        raise VPRBenchError(f"{error} (under {root})") from None
    with_zone = next((i for i, z in enumerate(zones) if z[0]), None)
    without = next((i for i, z in enumerate(zones) if not z[0]), None)
    if with_zone is not None and without is not None:
        raise VPRBenchError(
            f"{_named(paths[with_zone], root)} names UTM zone {zones[with_zone][1]} but {_named(paths[without], root)} "
            "names no zone: their positions cannot be compared; give every file name its zone, or none."
        )
    return positions, np.array([z[0] for z in zones], dtype=object)


def zone_names(zones) -> list[str]:
    """The distinct zones, in order ("" for no zone: none listed)."""
    return sorted({str(z) for z in zones if z}, key=lambda z: (int(z.split()[0]), z))


def warn_cross_zone_pairs(ground_truth, database: list[Path], queries: list[Path], root: Path) -> None:
    """Say the pairs within the radius by easting/northing alone that join two zones: the rule reading
    easting/northing only (the field's evaluation code) counts them as positives; they are not."""
    from ..model import GroundTruth

    gt = ground_truth
    if len(zone_names(np.concatenate([gt.database_zones, gt.query_zones]))) < 2:
        return
    plane = GroundTruth(unit=gt.unit, radius=gt.radius, database_positions=gt.database_positions,
                        query_positions=gt.query_positions).positives()
    pairs = [(q, d) for q, found in enumerate(plane) for d in found if gt.query_zones[q] != gt.database_zones[d]]
    if not pairs:
        return
    q, d = pairs[0]
    warnings.warn(
        f"{len(pairs)} query-database pair(s) within {gt.radius:g} m by easting/northing alone lie in different "
        f"UTM zones, e.g. {_named(queries[q], root)} (zone {zone_from_name(queries[q])[1]}) and "
        f"{_named(database[d], root)} (zone {zone_from_name(database[d])[1]}): not positives, as each zone's "
        "easting/northing is its own plane (code reading easting/northing only counts them).", stacklevel=2)


def _named(path: Path, root: Path) -> str:
    return path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
