"""HDF5 descriptor stores: one file per (method fingerprint, dataset, split).

A store is written as `<split>.partial.h5` and renamed to `<split>.h5` only once every row
is written, so a crash can never leave a file that is later read as complete; rows
finished before an interruption are kept, and extraction resumes after them.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from .paths import cache_root


def fingerprint_key(fingerprint: dict) -> str:
    return hashlib.sha256(json.dumps(fingerprint, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class DescriptorStore:
    path: Path            # the complete file
    partial_path: Path    # the file being written
    image_names: list[str]
    fingerprint: dict

    @classmethod
    def for_split(cls, method_name: str, fingerprint: dict, dataset_name: str, dataset_key: str,
                  split: str, image_names: list[str], cache_dir=None) -> "DescriptorStore":
        folder = cache_root(cache_dir) / "stores" / f"{method_name}-{fingerprint_key(fingerprint)}" / f"{dataset_name}-{dataset_key}"
        return cls(folder / f"{split}.h5", folder / f"{split}.partial.h5", image_names, fingerprint)

    # -- reading ---------------------------------------------------------------
    @property
    def complete(self) -> bool:
        return self.path.is_file()

    def read(self) -> np.ndarray:
        with h5py.File(self.path, "r") as f:
            return f["descriptors"][...]

    def read_fit_state(self) -> dict[str, np.ndarray] | None:
        for path in (self.path, self.partial_path):
            if path.is_file():
                try:
                    with h5py.File(path, "r") as f:
                        if "fit_state" in f:
                            return {k: v[...] for k, v in f["fit_state"].items()}
                except OSError:
                    continue
        return None

    # -- writing ---------------------------------------------------------------
    def open_partial(self, dim: int) -> tuple[h5py.File, np.ndarray]:
        """The partial file (created or reopened) and the mask of rows already written."""
        self.partial_path.parent.mkdir(parents=True, exist_ok=True)
        n = len(self.image_names)
        try:
            f = h5py.File(self.partial_path, "a")
        except OSError:  # torn by a crash: start again
            warnings.warn(f"Discarding unreadable partial store {self.partial_path}; extraction restarts.", stacklevel=2)
            self.partial_path.unlink()
            f = h5py.File(self.partial_path, "w")
        if "descriptors" in f:
            if f["descriptors"].shape == (n, dim) and list(f.attrs.get("images", [])) == self.image_names:
                return f, f["done"][...].astype(bool)
            del f["descriptors"], f["done"]
        f.create_dataset("descriptors", shape=(n, dim), dtype="float32", chunks=(max(1, min(n, 256)), dim))
        f.create_dataset("done", shape=(n,), dtype="bool", fillvalue=False)
        f.attrs["images"] = self.image_names
        f.attrs["fingerprint"] = json.dumps(self.fingerprint, sort_keys=True, default=str)
        f.flush()
        return f, np.zeros(n, dtype=bool)

    def partial_dim(self) -> int | None:
        if not self.partial_path.exists():
            return None
        try:
            with h5py.File(self.partial_path, "r") as f:
                return int(f["descriptors"].shape[1])
        except (OSError, KeyError):
            return None

    def save_fit_state(self, state: dict[str, np.ndarray]) -> None:
        """Kept beside the partial rows so a resumed run uses the same vocabulary."""
        self.partial_path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(self.partial_path, "a") as f:
            if "fit_state" in f:
                del f["fit_state"]
            group = f.create_group("fit_state")
            for key, value in state.items():
                group.create_dataset(key, data=np.asarray(value))

    @staticmethod
    def write_rows(f: h5py.File, rows: np.ndarray, descriptors: np.ndarray) -> None:
        # rows before flags, both flushed: a row marked done is always fully on disk
        f["descriptors"][rows] = descriptors
        f.flush()
        f["done"][rows] = True
        f.flush()

    def finish(self, f: h5py.File) -> None:
        f.close()
        self.partial_path.replace(self.path)
