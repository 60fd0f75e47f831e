"""Dataset manifests: one TOML file per dataset under manifests/datasets/."""
from __future__ import annotations

import copy
import functools
import tomllib
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path

from ..errors import VPRBenchError, closest_names
from ..paths import folder_path

#: the values of `sequence_order`: how a traverse's capture order is known (see datasets/traverse.py)
ORDERS = ("", "listing", "file-name-frame")


@dataclass(frozen=True)
class DatasetManifest:
    name: str
    title: str
    layout: str
    directory: str
    domain: str
    unit: str
    radius: float | None = None
    #: the radius's unit when `unit` is "positives" (lists made by the provider): "metres" or "frames"
    radius_unit: str = ""
    database_count: int | None = None
    query_count: int | None = None
    citation: str = ""
    licence: str = ""
    source: str = ""
    #: how to get the data: pooch base_url + file registry, or instructions for a person
    download: dict = field(default_factory=dict)
    instructions: str = ""
    #: layout-specific settings (folder names, ground-truth file, strides...)
    options: dict = field(default_factory=dict)
    notes: str = ""
    #: the default evaluation protocol (name, description, source; see datasets/protocol.py)
    protocol: dict = field(default_factory=dict)
    #: named variants of the protocol (swapped splits, another tolerance, a query subset...)
    protocols: list = field(default_factory=list)
    #: how the capture order of a traverse is known, for sequence matching: "listing",
    #: "file-name-frame", or "" (not a traverse; see datasets/traverse.py)
    sequence_order: str = ""

    @classmethod
    def from_toml(cls, text: str, origin: str) -> "DatasetManifest":
        data = tomllib.loads(text)
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(data) - known
        if unknown:
            raise VPRBenchError(f"Manifest {origin}: unknown field(s) {sorted(unknown)}")
        if data.get("sequence_order", "") not in ORDERS:
            raise VPRBenchError(f"Manifest {origin}: sequence_order must be one of {ORDERS}, got {data['sequence_order']!r}")
        try:
            return cls(**data)
        except TypeError as error:
            raise VPRBenchError(f"Manifest {origin}: {error}") from None


def _manifest_dir():
    return files("vprbench.manifests") / "datasets"


def dataset_manifests() -> dict[str, DatasetManifest]:
    manifests = {}
    for entry in sorted(_manifest_dir().iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            text = entry.read_text(encoding="utf-8")
            manifest = copy.deepcopy(_parsed(text, entry.name))  # a copy: callers may change theirs
            manifests[manifest.name] = manifest
    return manifests


@functools.lru_cache(maxsize=256)
def _parsed(text: str, origin: str) -> DatasetManifest:
    """A manifest's text parsed once per process (publishing a board asks for every manifest per record)."""
    return DatasetManifest.from_toml(text, origin)


def dataset_manifest(name: str) -> DatasetManifest:
    manifests = dataset_manifests()
    if name not in manifests:
        if is_path(name):  # else told to 'pass a folder path for your own data', the very thing given
            raise VPRBenchError(f"{name} is a folder of your own; here a benchmark's name is needed: run "
                                "'vprbench datasets list' to see them.")
        raise VPRBenchError(
            f"Unknown dataset {name!r}.{closest_names(name, manifests)} "
            "Run 'vprbench datasets list' to see all datasets, or pass a folder path for your own data."
        )
    return manifests[name]


def is_path(name: str) -> bool:
    """A folder of the user's own: a path-like name, or an existing folder that is no manifest's name."""
    if not name.strip():
        return False  # Path('') is the current folder; an empty name is an unknown dataset
    if "/" in name or name.startswith((".", "~")):
        return True
    return name not in dataset_manifests() and Path(name).is_dir()


def default_data_root() -> Path:
    """<user cache>/vprbench/data: where datasets are downloaded when no data root is given."""
    import pooch

    return Path(pooch.os_cache("vprbench")) / "data"


def data_root(data_dir: str | Path | None = None) -> Path:
    """`data_dir`, else the default data root (the command line reads $VPRBENCH_DATA for it); a data
    root that is a file is refused (nothing could be found in it, or downloaded into it)."""
    root = default_data_root() if data_dir is None else folder_path(data_dir, "data_dir")
    if root.exists() and not root.is_dir():
        raise VPRBenchError(f"The data root {root} is a file, not a folder: give --data-dir the folder that holds "
                            "the datasets (or will hold them, with --download).")
    return root


def is_default_data_root(data_dir: str | Path | None = None) -> bool:
    """True unless a data root was named (--data-dir or $VPRBENCH_DATA): only the default one is
    downloaded into without being asked."""
    return data_dir is None
