"""Datasets: manifests + layout readers -> `Dataset` (images, ground truth, provenance)."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import VPRBenchError, require
from ..paths import folder_path, resolved
from .download import download
from .layouts import read_layout
from .layouts.own_data import own_manifest
from .locations import dataset_location, how_to_get, read_registry
from .manifest import (DatasetManifest, data_root, dataset_manifest, dataset_manifests, is_default_data_root,
                       is_path)
from .model import Dataset, GroundTruth
from .protocol import apply_protocol, find_protocol, own_protocol, protocols
from .storage import check_counts, import_dataset, missing_dataset_message, nearest_existing
from .verify import VerifyReport, verify_dataset

__all__ = [
    "Dataset", "DatasetManifest", "GroundTruth", "VerifyReport", "data_root", "dataset_location",
    "dataset_manifest", "dataset_manifests", "download_dataset", "import_dataset", "is_on_disk",
    "load_dataset", "protocols", "read_copy", "read_registry", "verify_dataset",
]


def own_root(name: str) -> str | None:
    """The folder a dataset argument names as records keep it (`dataset_root`, resolved), None for a
    benchmark's name: the path given to evaluate finds its runs again in export and compare."""
    return str(resolved(name, "Dataset folder")) if is_path(name) else None  # a link loop, a NUL: one line


def is_on_disk(name: str, data_dir=None) -> bool:
    """Whether the dataset's folder (default or imported) exists; for `datasets list`."""
    return dataset_location(dataset_manifest(name), data_dir).is_dir()


def load_dataset(name: str, data_dir=None, *, fetch: bool | None = None, strict: bool = False,
                 protocol: str | None = None, cache_dir=None) -> Dataset:
    """A dataset by manifest name, or a folder of the user's own (see layouts/own_data.py),
    under one of its protocols (None: the default; see datasets/protocol.py).

    A missing dataset with a direct source is downloaded when `fetch` is True; with None (the
    default) only into the default data root, never into a data root the user named
    (--data-dir, $VPRBENCH_DATA) nor to an imported copy's place; with False never.
    `cache_dir` is where image identities are remembered (a folder's own protocol names them).
    """
    from ..methods.checks import flag

    if isinstance(name, os.PathLike):  # a Path names a folder as its text does
        name = os.fspath(name)
    require(name, str, "load_dataset takes a dataset's name (see 'vprbench datasets list') or the path of a folder "
                       "of your own")
    fetch = flag("load_dataset", "fetch", fetch, "only into the default data root")  # 'no' would be truthy: a download
    strict = flag("load_dataset", "strict", strict)
    cache_dir = folder_path(cache_dir, "cache_dir")  # else a wrong one is found out only for a folder of one's own
    if is_path(name):
        root = Path(name).expanduser()
        if root.exists() and not root.is_dir():
            raise VPRBenchError(f"Dataset folder {root} is a file, not a folder: give the folder holding database/ and "
                                "queries/.")
        if not root.is_dir():
            raise VPRBenchError(f"Dataset folder {root} does not exist (closest existing folder: {nearest_existing(root)}).")
        if protocol not in (None, "default", "own"):
            raise VPRBenchError(f"A folder of your own has one protocol, 'own' (its positions and radius); got {protocol!r}.")
        dataset = read_layout(root, own_manifest(root))
        dataset.kind, dataset.protocol = "own", own_protocol(dataset, cache_dir)
        return dataset
    manifest = dataset_manifest(name)
    chosen = find_protocol(manifest, protocol)  # an unknown protocol fails before any reading
    root = dataset_location(manifest, data_dir)
    if not root.exists():
        if fetch is None:
            fetch = is_default_data_root(data_dir) and name not in read_registry(data_dir)
        if not (fetch and manifest.download):
            raise VPRBenchError(missing_dataset_message(manifest, root, data_dir))
        download(manifest, root, data_dir=data_dir)
    return read_copy(root, manifest, chosen.name, strict, data_dir)


def read_copy(root: Path, manifest, protocol: str | None = None, strict: bool = False, data_dir=None) -> Dataset:
    """The benchmark's copy in the folder `root`, read and its counts checked, under one of its protocols: the
    one in a data root (load_dataset), or the one a run's record names (the leaderboard's re-scoring)."""
    dataset = read_layout(root, manifest, data_dir)
    check_counts(dataset, manifest, strict, data_dir)
    return apply_protocol(dataset, find_protocol(manifest, protocol))


def download_dataset(name: str, data_dir=None, strict: bool = True) -> Dataset:
    """`vprbench datasets download NAME`: fetch (when a direct source exists), then read and check it."""
    manifest = dataset_manifest(name)
    if not manifest.download:
        raise VPRBenchError(f"Dataset {name!r} has no direct download. {how_to_get(manifest, data_dir)}")
    return load_dataset(name, data_dir, fetch=True, strict=strict)
