"""Layout readers: how a dataset lies on disk -> `Dataset`. Datasets sharing a layout share its reader."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import Dataset

Reader = Callable[[Path, DatasetManifest], Dataset]
LAYOUTS: dict[str, Reader] = {}


def layout(name: str):
    def register(reader: Reader) -> Reader:
        LAYOUTS[name] = reader
        return reader

    return register


def read_layout(root: Path, manifest: DatasetManifest) -> Dataset:
    if manifest.layout not in LAYOUTS:
        raise VPRBenchError(f"Dataset {manifest.name!r}: unknown layout {manifest.layout!r} (known: {sorted(LAYOUTS)})")
    return LAYOUTS[manifest.layout](root, manifest)


def require(root: Path, relative: str, manifest: DatasetManifest, kind: str = "folder") -> Path:
    """root/relative, or an error naming the missing folder or file and the layout."""
    path = root / relative
    exists = path.is_dir() if kind == "folder" else path.is_file()
    if not exists:
        raise VPRBenchError(
            f"Dataset {manifest.name!r}: expected {kind} '{relative}' under {root} "
            f"(layout {manifest.layout!r}) but it is missing. Run 'vprbench datasets verify {manifest.name}' "
            f"or see 'vprbench datasets info {manifest.name}' for how to get the data."
        )
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
    )


# readers register themselves on import
from . import own_data, vpr_bench  # noqa: E402,F401
