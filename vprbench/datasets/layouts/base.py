"""What every layout reader is built from: its registration (`layout`, LAYOUTS, EXPECTS), the
folders and files it needs inside the dataset (`require`, `inside`, `climbs_out`, `MissingPart`),
and the Dataset it returns (`from_manifest`). The readers import this, never the package, which
imports them to register them.
"""
from __future__ import annotations

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


class MissingPart(VPRBenchError):
    """A folder or file a layout reader needs is missing (`require`); `read_layout` adds what to do,
    `detail` is the message without it (`datasets verify` says it as one problem of its report)."""

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail or message


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
