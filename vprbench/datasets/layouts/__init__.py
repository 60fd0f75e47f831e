"""Layout readers: how a dataset lies on disk -> `Dataset`. Datasets sharing a layout share its reader.

A manifest names its primary layout (usually the authors' release) and may list
`[[options.alternatives]]`: other layouts the same data is commonly found in (e.g. the
`images/test/{database,queries}` layout with UTM in file names, or VPR-Bench's
`ref/ query/ ground_truth_new.npy`). `read_layout` picks the first whose expected
folders and files are present, and otherwise says what each layout expects.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from ...errors import VPRBenchError
from ...paths import regular_file
from ..locations import how_to_get, verify_command
from ..manifest import DatasetManifest
from ..model import Dataset
from . import oxford, own_data, release, utm_names, vpr_bench  # noqa: F401 - readers register themselves on import
from .base import EXPECTS, LAYOUTS, MissingPart


def candidates(manifest: DatasetManifest) -> list[DatasetManifest]:
    """The manifest's primary layout, then each alternative as a manifest of its own."""
    options = {k: v for k, v in manifest.options.items() if k != "alternatives"}
    found = [dataclasses.replace(manifest, options=options)]
    for alternative in manifest.options.get("alternatives", []):
        alternative = dict(alternative)
        keys = ("layout", "database_count", "query_count", "radius", "unit", "radius_unit")
        overrides = {k: alternative.pop(k) for k in keys if k in alternative}
        if "unit" in overrides:
            overrides.setdefault("radius_unit", "")
        found.append(dataclasses.replace(manifest, options=alternative, **overrides))
    return found


def missing_paths(root: Path, manifest: DatasetManifest) -> list[str]:
    if manifest.layout not in LAYOUTS:
        raise VPRBenchError(f"Dataset {manifest.name!r}: unknown layout {manifest.layout!r} (known: {sorted(LAYOUTS)})")
    missing = []
    for relative in EXPECTS[manifest.layout](manifest.options):
        path = root / relative
        if not (path.is_dir() if relative.endswith("/") else regular_file(path, f"Dataset {manifest.name!r}: file")):
            missing.append(relative)
    return missing


def describe_layout(manifest: DatasetManifest) -> str:
    expected = EXPECTS[manifest.layout](manifest.options)
    return f"layout {manifest.layout!r} ({', '.join(expected) or 'any'})"


def describe_missing(missing: list[str]) -> str:
    return ", ".join(f"folder '{m[:-1]}'" if m.endswith("/") else f"file '{m}'" for m in missing)


def detect_layout(root: Path, manifest: DatasetManifest, data_dir=None) -> DatasetManifest:
    """The first candidate layout whose expected folders and files are all under root; else an error
    saying how to get the data into the data root `data_dir` (the one the user named, not root's
    parent: an imported copy, or a folder being imported, lies elsewhere)."""
    options = candidates(manifest)
    report = []
    for candidate in options:
        missing = missing_paths(root, candidate)
        if not missing:
            return candidate
        report.append((candidate.layout, missing))
    if manifest.layout == "own":
        hint = "Put the database images in database/ and the query images in queries/ (see the own-data guide)."
    else:
        hint = how_to_get(manifest, data_dir)
    if len(report) == 1:
        layout_name, missing = report[0]
        text = f"expected {describe_missing(missing)} under {root} (layout {layout_name!r}) but {'it is' if len(missing) == 1 else 'they are'} missing"
        raise VPRBenchError(f"Dataset {manifest.name!r}: {text}. {hint}")
    parts = [f"layout {report[0][0]!r} (the authors' release) is missing {describe_missing(report[0][1])}"]
    parts += [f"layout {name!r} is missing {describe_missing(missing)}" for name, missing in report[1:]]
    raise VPRBenchError(f"Dataset {manifest.name!r}: {root} is in none of its known layouts: " + "; ".join(parts) + f". {hint}")


def read_layout(root: Path, manifest: DatasetManifest, data_dir=None) -> Dataset:
    """The dataset at root in the first layout it is in; `data_dir` is the data root it is read from
    (or imported into): the commands an error suggests name it."""
    candidate = detect_layout(root, manifest, data_dir)
    try:
        dataset = LAYOUTS[candidate.layout](root, candidate)
    except MissingPart as error:
        command = None if manifest.layout == "own" else verify_command(manifest, root, data_dir)
        if command is None:
            raise  # a folder of one's own, or one being imported: nothing checks it but reading it
        raise MissingPart(f"{error} The copy is incomplete: '{command}' checks all of it.", str(error)) from None
    dataset.layout = candidate.layout
    return dataset
