"""A user's own dataset: database/ and queries/ folders, positions from a CSV or UTM file names.

    mydata/
      database/*.jpg
      queries/*.jpg
      positions.csv      # optional if file names carry UTM as @easting@northing@...
      dataset.toml       # optional: name, title, radius, domain, citation, licence

positions.csv has a column `image` (path relative to mydata/, e.g. database/0001.jpg) and
one of: `x,y` or `easting,northing` (metres), `latitude,longitude` or `lat,lon` (degrees,
converted to UTM metres in the zone of the first row), or `frame` (frame index). Radius: 25 m by default for metres; give `radius`
in dataset.toml for frames. Each image has one row: a repeated image is an error, a row naming
an image that is not in database/ or queries/ a warning.
"""
from __future__ import annotations

import os
import re
import unicodedata
import warnings
from pathlib import Path

import numpy as np

from ...errors import VPRBenchError, toml_data
from ...images import IMAGE_SUFFIXES, list_images, nested_image_folders
from ...paths import regular_file
from ...text import CONTROL
from ..manifest import DatasetManifest
from ..model import GroundTruth
from .base import climbs_out, from_manifest, layout, require
# utm_from_name lived here: still importable from here
from .utm_zones import MAX_COORDINATE, positions_from_names, utm_from_name, warn_cross_zone_pairs  # noqa: F401

DEFAULT_RADIUS_M = 25.0


#: a dataset's name becomes part of file names (stores, records) and is shown: a plain file name
NAME_RULE = "1 to 100 letters, digits, '.', '_', '+' or '-', starting with a letter or digit, without '..'"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,99}")


def is_safe_name(name: str) -> bool:
    return bool(_NAME.fullmatch(name)) and ".." not in name


def safe_name(folder_name: str) -> str:
    """The default name of a folder of one's own: its name, with each run of other characters
    (spaces, '<', controls...) made one '-' ("Lab photos" -> "Lab-photos")."""
    name = re.sub(r"\.{2,}", ".", re.sub(r"[^A-Za-z0-9._+-]+", "-", folder_name)).lstrip("._+-")[:100]
    return name if is_safe_name(name) else "own-data"


def latlon_to_metres(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """UTM easting/northing in the zone of the first point, so all points share one plane."""
    import utm

    zone_number, zone_letter = utm.from_latlon(float(lat[0]), float(lon[0]))[2:]
    easting, northing, _, _ = utm.from_latlon(
        np.asarray(lat, float), np.asarray(lon, float), force_zone_number=zone_number, force_zone_letter=zone_letter
    )
    return np.stack([easting, northing], axis=1)


def positions_from_csv(csv: Path, root: Path, images: list[Path]) -> tuple[np.ndarray, str]:
    import pandas as pd

    try:
        # skipinitialspace: "image, x, y" as typed by hand is no column ' x'; low_memory=False: read in one
        # piece, as a long file (100,000s of rows) read in chunks had a typo in its last chunk said as pandas'
        # DtypeWarning before the refusal naming its row
        table = pd.read_csv(csv, skipinitialspace=True, low_memory=False)
        header = pd.read_csv(csv, skipinitialspace=True, header=None, nrows=1, dtype=str).iloc[0].tolist()
    except OSError as error:
        raise VPRBenchError(f"Cannot read {csv}: {error}") from None
    except pd.errors.ParserError as error:  # a row of more values than the header has names
        raise VPRBenchError(f"Cannot read {csv}: {str(error).strip()}; give each row one value for each column "
                            "of the header row (e.g. image,x,y).") from None
    except ValueError as error:  # not UTF-8 (a spreadsheet's "CSV" in a Windows code page), empty, malformed
        raise VPRBenchError(f"Cannot read {csv}: {str(error).strip()}. Save it as UTF-8 text, a header row first "
                            "(e.g. image,x,y).") from None
    # pandas renames a repeated column (x, x.1) and the first would be used unseen; empty names are NaN here
    repeated = sorted({name for name in header if isinstance(name, str) and header.count(name) > 1})
    if repeated:
        raise VPRBenchError(f"{csv} names the column(s) {repeated} more than once in its header row; keep one of each.")
    if "image" not in table.columns:
        # one column whose name holds ';' or a tab: a spreadsheet's export in another separator
        other = next((sep for sep in (";", "\t") if len(table.columns) == 1 and sep in str(table.columns[0])), None)
        hint = f" (one column: the file is separated by {other!r}; save it separated by commas)" if other else ""
        raise VPRBenchError(f"{csv} needs a column 'image' (path relative to {root}); it has "
                            f"{list(table.columns)}{hint}")
    columns = set(table.columns)
    choices = (
        (("x", "y"), "metres"), (("easting", "northing"), "metres"),
        (("latitude", "longitude"), "degrees"), (("lat", "lon"), "degrees"), (("frame",), "frames"),
    )
    chosen = next(((names, unit) for names, unit in choices if set(names) <= columns), None)
    if chosen is None:
        raise VPRBenchError(
            f"{csv} needs position columns x,y or easting,northing (metres), latitude,longitude (or lat,lon), "
            f"or frame; it has {list(table.columns)}"
        )
    names, unit = chosen
    others = [",".join(n) for n, _ in choices if set(n) <= columns and n != names]
    if others:  # the first in the documented order is used: say so, or the wrong one is used unseen
        warnings.warn(f"{csv.resolve()} has several kinds of position: {','.join(names)} ({unit}) is used, "
                      f"{' and '.join(others)} ignored (the first kind of x,y; easting,northing; latitude,longitude; "
                      "lat,lon; frame is used): to use another, remove the columns of the one used.", stacklevel=2)
    unnamed = int(table["image"].isna().sum())
    if unnamed:  # a spreadsheet's trailing ',,' row: said as the row it is, not as an image named 'nan'
        warnings.warn(f"{csv.resolve()} has {unnamed} row(s) with no image name; they are left out.", stacklevel=2)
        table = table[table["image"].notna()].reset_index(drop=True)
    written = [str(name) for name in table["image"]]
    # rows are matched to the images found by name and never opened; one naming a file outside
    # the folder is still refused, as everything a data file names must lie inside its dataset
    outside = [name for name in written if climbs_out(name)]
    if outside:
        raise VPRBenchError(
            f"{csv} names {len(outside)} image(s) outside {root}, e.g. {outside[:3]}; the column 'image' holds "
            "paths relative to the folder (database/0001.jpg): fix those rows."
        )
    found, listed = image_row_names(images, root), [row_name(name) for name in written]
    names_column = pd.Series(listed)
    repeated = sorted(set(names_column[names_column.duplicated()]))
    if repeated:
        raise VPRBenchError(
            f"{csv} lists {len(repeated)} image(s) more than once, e.g. {repeated[:3]}; keep one row per image."
        )
    values = np.stack([_numbers(table[name]) for name in names], axis=1)
    bad = np.flatnonzero(np.isnan(values).any(axis=1))
    if len(bad):
        raise VPRBenchError(
            f"{csv} has missing or non-numeric positions in {len(bad)} row(s), e.g. for "
            f"{[str(table['image'].iloc[i]) for i in bad[:3]]}; every row needs a value."
        )
    huge = np.flatnonzero((np.abs(values) > MAX_COORDINATE).any(axis=1))
    if len(huge):
        raise VPRBenchError(
            f"{csv} has positions beyond +-{MAX_COORDINATE:.0e} in {len(huge)} row(s), e.g. for "
            f"{[str(table['image'].iloc[i]) for i in huge[:3]]}; give metres, degrees or frame numbers."
        )
    fractional = np.flatnonzero(values[:, 0] != np.round(values[:, 0])) if unit == "frames" else []
    if len(fractional):  # a frame is an index along the route: 12.5 is a typo or another unit (seconds?)
        raise VPRBenchError(
            f"{csv} has frame numbers that are not whole in {len(fractional)} row(s), e.g. for "
            f"{[str(table['image'].iloc[i]) for i in fractional[:3]]}; give each image's frame index (0, 1, 2, ...)."
        )
    if unit == "degrees":
        outside = np.flatnonzero((np.abs(values[:, 0]) > 84) | (np.abs(values[:, 1]) > 180))
        if len(outside):  # named as the other bad rows are, so the user finds them (often swapped columns)
            raise VPRBenchError(
                f"{csv} has latitudes beyond +-84 degrees (outside UTM) or longitudes beyond +-180 in {len(outside)} "
                f"row(s), e.g. for {[str(table['image'].iloc[i]) for i in outside[:3]]}; fix those rows (latitude "
                "and longitude swapped?), or give x,y in metres of a local frame."
            )
        values, unit = latlon_to_metres(values[:, 0], values[:, 1]), "metres"
    by_name = dict(zip(listed, values))
    missing = [name for name in found if name not in by_name]
    if missing:
        by_case = {name.casefold(): name for name in listed}
        near = [(name, by_case[name.casefold()]) for name in missing if name.casefold() in by_case]
        hint = (f"; names must match in case: the row {near[0][1]!r} is not the file {near[0][0]!r}" if near else "")
        by_file = {name.rpartition("/")[2]: name for name in missing}  # a row of the bare file name
        bare = [(name, by_file[name]) for name in listed if "/" not in name and name in by_file]
        if bare and not hint:
            hint = (f"; rows name images by their path in {root}: write {bare[0][1]!r}, not {bare[0][0]!r}")
        raise VPRBenchError(f"{csv} has no position for {len(missing)} image(s), e.g. {missing[:3]}{hint}; "
                            "add a row for each.")
    absent = sorted(set(listed) - set(found))
    folder = root.resolve()
    there = [name for name in absent if os.path.isfile(root / name)]  # a file not read as an image: not "not there"
    if there:
        warnings.warn(f"{csv.resolve()} lists {len(there)} file(s) that are not read as images, e.g. {there[:3]}: "
                      f"only files directly in {folder}/database and {folder}/queries ending in "
                      f"{', '.join(IMAGE_SUFFIXES)} are; they are left out (convert or move them to be evaluated).",
                      stacklevel=2)
        absent = [name for name in absent if name not in there]
    if absent:
        # named in full: the folder is read for the run's identity as the user wrote it and again for the
        # run by its absolute path, and the CLI shows one text once
        warnings.warn(f"{csv.resolve()} lists {len(absent)} image(s) that are not in {folder}/database or "
                      f"{folder}/queries, e.g. {absent[:3]}; they are left out.", stacklevel=2)
    return np.stack([by_name[name] for name in found]), unit


def _numbers(column) -> np.ndarray:
    """A column's values as floats: NaN where not a number, +-inf where too large for a float (refused as
    too large, as 1e300 is). Text is parsed by Python, as every pandas reads a number of hundreds of digits
    differently (a Python int, text, or an overflow), and pandas 2.1 called it non-numeric."""
    if column.dtype.kind in "fiub":
        return column.to_numpy(float)

    def number(value) -> float:
        try:
            return float(value)
        except OverflowError:  # an int beyond any float
            return float("inf") if value > 0 else float("-inf")
        except (TypeError, ValueError):
            return float("nan")

    return np.array([number(value) for value in column], dtype=float)


def row_name(name: str) -> str:
    """How an image is named for matching rows to files: one spelling per path (`queries/../database/a.jpg`
    is `database/a.jpg`) in Unicode NFC, as the same name typed or copied may arrive in either form."""
    return unicodedata.normalize("NFC", os.path.normpath(name))


def image_row_names(images: list[Path], root: Path) -> list[str]:
    """The images' row names; two files whose names differ only in Unicode form are refused (which
    row is whose cannot be told, and they print alike)."""
    names, seen = [], {}
    for path in images:
        relative = path.relative_to(root).as_posix()
        name = row_name(relative)
        if name in seen:
            raise VPRBenchError(f"{root}: {ascii(seen[name])} and {ascii(relative)} are one name in two Unicode forms "
                                "(they print alike); rename one of the two files.")
        seen[name] = relative
        names.append(name)
    return names


@layout("own", expects=lambda options: ["database/", "queries/"])
def read_own(root: Path, manifest: DatasetManifest):
    database = list_images(require(root, "database", manifest))
    queries = list_images(require(root, "queries", manifest))
    empty = [f"{root}/{name}" for name, images in (("database", database), ("queries", queries)) if not images]
    nested = {name: nested_image_folders(root / name) for name in ("database", "queries")}
    if empty:
        hint = next((f"{root}/{name} has images only in its subfolders ({nested[name]}): move them up into it"
                     for name in ("database", "queries") if f"{root}/{name}" in empty and nested[name]),
                    f"put {', '.join(s[1:] for s in IMAGE_SUFFIXES)} files there")
        raise VPRBenchError(f"Dataset {manifest.name!r}: no images in {' or '.join(empty)}; {hint}.")
    for name, folders in nested.items():
        if folders:
            warnings.warn(f"{root}/{name}: the images in its subfolders ({folders}) are not read, only those "
                          f"directly in {name}/; move them up to include them.", stacklevel=2)
    csv, zones = root / "positions.csv", None
    if regular_file(csv, "Positions file"):
        positions, unit = positions_from_csv(csv, root, database + queries)
    else:
        positions, zones = positions_from_names(database + queries, root)
        unit = "metres"
    radius = manifest.radius
    if radius is None:
        if unit == "frames":
            raise VPRBenchError(f"{root}: frame positions need 'radius = N' (frames) in {root}/dataset.toml")
        radius = DEFAULT_RADIUS_M
    split = {"database_zones": zones[: len(database)], "query_zones": zones[len(database):]} if zones is not None else {}
    ground_truth = GroundTruth(unit=unit, radius=radius, database_positions=positions[: len(database)],
                               query_positions=positions[len(database):], **split)
    if zones is not None:
        warn_cross_zone_pairs(ground_truth, database, queries, root)
    dataset = from_manifest(manifest, root, database, queries, ground_truth)
    dataset.radius_unit = unit  # the positions' unit (frames or metres), not the manifest's default
    if not any(len(p) for p in dataset.positives):  # computed once: the evaluation reads the same
        # every method would score Recall@K = 0: the positions or the radius are wrong
        raise VPRBenchError(
            f"Dataset {manifest.name!r}: no query in {root}/queries has a database image within "
            f"{radius:g} {unit} of its position; check the positions' columns and units "
            f"({csv.name if csv.is_file() else 'file names'}) or set radius in {root}/dataset.toml."
        )
    return dataset


def own_manifest(root: Path) -> DatasetManifest:
    """The manifest of a folder of the user's own: defaults, overridden by its dataset.toml."""
    settings, toml = {}, root / "dataset.toml"
    if regular_file(toml, "Dataset settings"):
        try:
            text = toml.read_text(encoding="utf-8")
        except UnicodeDecodeError as error:
            raise VPRBenchError(f"Cannot read {toml}: {error}. It must be a UTF-8 TOML file.") from None
        settings = toml_data(text, str(toml))
    allowed = {"name", "title", "radius", "domain", "citation", "licence"}
    if set(settings) - allowed:
        raise VPRBenchError(f"{toml}: unknown key(s) {sorted(set(settings) - allowed)}; allowed: {sorted(allowed)}")
    for key, value in settings.items():
        if key == "radius":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0 or value == float("inf"):
                raise VPRBenchError(f"{toml}: radius must be a number of metres or frames, 0 or more; got {value!r}.")
        elif not isinstance(value, str) or (key == "name" and not value.strip()):
            raise VPRBenchError(f"{toml}: {key} must be {'a non-empty' if key == 'name' else 'a'} string; got {value!r}.")
        elif CONTROL.search(value):
            raise VPRBenchError(f"{toml}: {key} holds the control character {CONTROL.search(value).group()!r}; remove it.")
        elif key == "name" and not is_safe_name(value):
            raise VPRBenchError(f"{toml}: name {value!r} is not a safe dataset name ({NAME_RULE}); choose another.")
    return DatasetManifest(
        name=settings.get("name", safe_name(root.resolve().name)),
        title=settings.get("title", root.resolve().name),
        layout="own",
        directory=str(root),
        domain=settings.get("domain", "custom"),
        unit="metres",
        radius=settings.get("radius"),
        citation=settings.get("citation", ""),
        licence=settings.get("licence", ""),
    )
