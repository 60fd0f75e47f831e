"""Datasets: manifests + layout readers -> `Dataset` (images, ground truth, provenance)."""
from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import VPRBenchError
from .download import download, how_to_get
from .layouts import read_layout
from .layouts.own_data import own_manifest
from .manifest import DatasetManifest, data_root, dataset_manifest, dataset_manifests
from .model import Dataset, GroundTruth

__all__ = [
    "Dataset", "DatasetManifest", "GroundTruth", "data_root", "dataset_manifest",
    "dataset_manifests", "load_dataset", "dataset_location",
]


def is_path(name: str) -> bool:
    return "/" in name or name.startswith(".") or Path(name).is_dir()


def dataset_location(manifest: DatasetManifest, data_dir=None) -> Path:
    return data_root(data_dir) / manifest.directory


def load_dataset(name: str, data_dir=None, *, fetch: bool = True, strict: bool = False) -> Dataset:
    """A dataset by manifest name, or a folder of the user's own (see layouts/own_data.py)."""
    if is_path(name):
        root = Path(name).expanduser()
        if not root.is_dir():
            raise VPRBenchError(f"Dataset folder {root} does not exist.")
        return read_layout(root, own_manifest(root))
    manifest = dataset_manifest(name)
    root = dataset_location(manifest, data_dir)
    if not root.exists():
        if fetch and manifest.download:
            download(manifest, root)
        else:
            raise VPRBenchError(f"Dataset {name!r} is not at {root}. {how_to_get(manifest, root)}")
    dataset = read_layout(root, manifest)
    check_counts(dataset, manifest, strict)
    return dataset


def check_counts(dataset: Dataset, manifest: DatasetManifest, strict: bool) -> None:
    for split, expected, found in (
        ("database", manifest.database_count, len(dataset.database)),
        ("query", manifest.query_count, len(dataset.queries)),
    ):
        if expected is not None and expected != found:
            message = f"Dataset {manifest.name!r}: {found} {split} images at {dataset.root}, the manifest expects {expected}."
            if strict:
                raise VPRBenchError(message + " (--strict)")
            warnings.warn(message, stacklevel=3)
