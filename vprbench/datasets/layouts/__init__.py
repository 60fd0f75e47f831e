"""Layout readers: how a dataset lies on disk -> `Dataset`. Datasets sharing a layout share its reader.

A manifest names its primary layout (usually the authors' release) and may list
`[[options.alternatives]]`: other layouts the same data is commonly found in (e.g. the
`images/test/{database,queries}` layout with UTM in file names, or VPR-Bench's
`ref/ query/ ground_truth_new.npy`). `read_layout` picks the first whose expected
folders and files are present, and otherwise says what each layout expects.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

from ...errors import VPRBenchError
from ...paths import regular_file
from ..manifest import DatasetManifest
from ..model import Dataset

Reader = Callable[[Path, DatasetManifest], Dataset]
#: what a layout needs on disk, given the manifest options: relative paths (folders end in "/")
Expects = Callable[[dict], list[str]]
LAYOUTS: dict[str, Reader] = {}
EXPECTS: dict[str, Expects] = {}


def layout(name: str, expects: Expects | None = None):
    def register(reader: Reader) -> Reader:
        LAYOUTS[name] = reader
        EXPECTS[name] = expects or (lambda options: [])
        return reader

    return register


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
        from ..download import how_to_get

        hint = how_to_get(manifest, data_dir)
    if len(report) == 1:
        layout_name, missing = report[0]
        text = f"expected {describe_missing(missing)} under {root} (layout {layout_name!r}) but {'it is' if len(missing) == 1 else 'they are'} missing"
        raise VPRBenchError(f"Dataset {manifest.name!r}: {text}. {hint}")
    parts = [f"layout {report[0][0]!r} (the authors' release) is missing {describe_missing(report[0][1])}"]
    parts += [f"layout {name!r} is missing {describe_missing(missing)}" for name, missing in report[1:]]
    raise VPRBenchError(f"Dataset {manifest.name!r}: {root} is in none of its known layouts: " + "; ".join(parts) + f". {hint}")


class MissingPart(VPRBenchError):
    """A folder or file a layout reader needs is missing (`require`); `read_layout` adds what to do,
    `detail` is the message without it (`datasets verify` says it as one problem of its report)."""

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail or message


def read_layout(root: Path, manifest: DatasetManifest, data_dir=None) -> Dataset:
    """The dataset at root in the first layout it is in; `data_dir` is the data root it is read from
    (or imported into): the commands an error suggests name it."""
    candidate = detect_layout(root, manifest, data_dir)
    try:
        dataset = LAYOUTS[candidate.layout](root, candidate)
    except MissingPart as error:
        from ..storage import verify_command

        command = None if manifest.layout == "own" else verify_command(manifest, root, data_dir)
        if command is None:
            raise  # a folder of one's own, or one being imported: nothing checks it but reading it
        raise MissingPart(f"{error} The copy is incomplete: '{command}' checks all of it.", str(error)) from None
    dataset.layout = candidate.layout
    return dataset


def climbs_out(entry: str) -> bool:
    """Whether a relative path written in a file leaves the folder it is relative to, by its
    text alone: absolute, or more '..' than folders (a NUL byte counts, as no file has one)."""
    text = str(entry)
    if "\0" in text or os.path.isabs(text):
        return True
    normal = os.path.normpath(text)
    return normal == ".." or normal.startswith(".." + os.sep)


def inside(folder: Path, entry: str, source: Path | str) -> Path:
    """folder/entry for a path named in a data file (`source`: a ground-truth file, say), if it
    lies inside `folder` with symlinks resolved; refused otherwise, naming the file and the entry,
    so a hostile file cannot make vprbench read (and describe) a file elsewhere on the machine."""
    path = folder / entry
    try:
        outside = climbs_out(entry) or not path.resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):  # a symlink loop: it leads nowhere inside either
        outside = True
    if outside:
        raise VPRBenchError(
            f"{source} names {entry!r}, which lies outside {folder} (an absolute path, a '..' that "
            "climbs out, or a symlink leading out). A dataset's files name only files inside it: fix or "
            "replace the file (re-download the dataset)."
        )
    return path


def require(root: Path, relative: str, manifest: DatasetManifest, kind: str = "folder") -> Path:
    """root/relative, or an error naming the missing folder or file and the layout. A manifest
    names paths inside the dataset folder (the file itself may be a symlink the user made)."""
    if climbs_out(relative):
        raise VPRBenchError(f"Dataset {manifest.name!r}: its manifest names {relative!r}, which is not a path "
                            "inside the dataset folder; fix the manifest.")
    path = root / relative
    exists = path.is_dir() if kind == "folder" else regular_file(path, f"Dataset {manifest.name!r}: {kind}")
    if not exists:  # what to do is said by read_layout, which knows the data root
        raise MissingPart(f"Dataset {manifest.name!r}: expected {kind} '{relative}' under {root} "
                          f"(layout {manifest.layout!r}) but it is missing.")
    return path


def from_manifest(manifest: DatasetManifest, root: Path, database, queries, ground_truth) -> Dataset:
    """A Dataset carrying the manifest's provenance."""
    return Dataset(
        name=manifest.name,
        title=manifest.title,
        database=list(database),
        queries=list(queries),
        ground_truth=ground_truth,
        domain=manifest.domain,
        citation=manifest.citation,
        licence=manifest.licence,
        root=root,
        notes=[manifest.notes] if manifest.notes else [],
        radius_unit=manifest.radius_unit or (manifest.unit if manifest.unit != "positives" else ""),
        sequence_order=manifest.sequence_order,
    )


# readers register themselves on import
from . import oxford, own_data, release, utm_names, vpr_bench  # noqa: E402,F401
