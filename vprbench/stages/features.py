"""Per-image data a stage computes once and keeps (local features), beside the descriptor stores.

    features/<name>-<identity hash>/<dataset>-<images key>/<split>.h5
        attrs: feature identity (what computed it), images key (the split's names and contents)
        images/<row>/<array>...   one group per image, written whole, marked done last

Keyed like descriptor stores: by what computed the data (the extractor and its options) and the
content of the images, so every retriever and re-ranking run on those images shares one file.
A run holds the folder's lock while it reads and writes (resumable: an image already done is read,
never recomputed); a file written for another extractor or other images is refused by name.
"""
from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from ..errors import VPRBenchError
from ..fsutil import cache_error, lock
from ..hashing import canonical_hash, canonical_json
from ..paths import cache_root, safe_name

#: bytes of per-image arrays kept in memory per open split (database images recur across queries)
KEPT_BYTES = 256 * 2**20


class FeatureStore:
    def __init__(self, name: str, identity: dict, label: str, images_keys: dict[str, str], cache_dir=None,
                 lock_timeout: float | None = None):
        self.name, self.identity_json = name, canonical_json({"name": name, **identity})
        self.images_keys, self.lock_timeout = images_keys, lock_timeout
        #: images computed (not read) through this store: 0 on a run served from the cache
        self.computed = 0
        self.path = (cache_root(cache_dir) / "features" / f"{safe_name(name)}-{canonical_hash(json.loads(self.identity_json))}"
                     / f"{safe_name(label)}-{canonical_hash(images_keys)}")

    @classmethod
    def for_images(cls, name: str, identity: dict, dataset, cache_dir=None, lock_timeout=None) -> "FeatureStore":
        return cls(name, identity, dataset.name, dataset.images_fingerprint(cache_dir), cache_dir, lock_timeout)

    def file(self, split: str) -> Path:
        return self.path / f"{split}.h5"

    @contextmanager
    def opened(self, split: str, compute: Callable[[int], dict[str, np.ndarray]]) -> Iterator[Callable[[int], dict]]:
        """`get(row)` for the split's images: read when stored, else `compute(row)` (name -> array),
        written and flushed at once (a killed run resumes from there). Holds the folder's lock."""
        path = self.file(split)
        with lock(self.path / ".lock", self.lock_timeout, what=f"local features {self.path}"):
            handle = self._open(path, split)
            kept: OrderedDict[int, dict] = OrderedDict()
            held = 0

            def get(row: int) -> dict[str, np.ndarray]:
                nonlocal held
                if row in kept:
                    kept.move_to_end(row)
                    return kept[row]
                group = handle["images"].get(str(row))
                if group is not None and group.attrs.get("done"):
                    found = {key: group[key][...] for key in group}
                else:
                    found = {key: np.asarray(value) for key, value in compute(row).items()}
                    self._write(handle, row, found, path)
                    self.computed += 1
                kept[row] = found
                held += sum(a.nbytes for a in found.values())
                while held > KEPT_BYTES and len(kept) > 1:
                    held -= sum(a.nbytes for a in kept.popitem(last=False)[1].values())
                return found

            try:
                yield get
            finally:
                handle.close()

    def _open(self, path: Path, split: str) -> h5py.File:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            handle = h5py.File(path, "a")
        except OSError as error:
            if isinstance(error, PermissionError) or not path.exists():
                raise cache_error(error, path) from None
            path.unlink()  # torn by a kill mid-write (HDF5 is not crash-safe): recomputed
            handle = h5py.File(path, "a")
        if "images" not in handle:
            handle.attrs["feature_identity"] = self.identity_json
            handle.attrs["images_key"] = self.images_keys[split]
            handle.create_group("images")
            return handle
        found, images = handle.attrs.get("feature_identity"), handle.attrs.get("images_key")
        if found != self.identity_json or images != self.images_keys[split]:
            handle.close()
            ours = self.name
            if found != self.identity_json:
                theirs, ours = _differing(found, self.identity_json)
                what = f"another extractor ({theirs})"
            else:
                what = "other images"
            raise VPRBenchError(f"Local features {path} were computed by {what}, not {ours} as this run computes "
                                "them: delete that file (it is recomputed).")
        return handle

    @staticmethod
    def _write(handle: h5py.File, row: int, arrays: dict[str, np.ndarray], path: Path) -> None:
        try:
            images = handle["images"]
            if str(row) in images:  # left unfinished by a killed run
                del images[str(row)]
            group = images.create_group(str(row))
            for key, value in arrays.items():
                group.create_dataset(key, data=value)
            group.attrs["done"] = 1
            handle.flush()
        except (OSError, RuntimeError) as error:
            raise cache_error(error, path) from None

    def bytes_per_image(self, split: str = "database") -> float:
        """Bytes of the arrays stored per image of `split` (what the stage keeps), 0 when none."""
        try:
            with lock(self.path / ".lock", self.lock_timeout, announce=False), h5py.File(self.file(split), "r") as f:
                groups = [g for g in f["images"].values() if g.attrs.get("done")]
                total = sum(d.nbytes for g in groups for d in g.values())
        except (OSError, KeyError):
            return 0.0
        return total / len(groups) if groups else 0.0


def _differing(found, ours: str) -> tuple[str, str]:
    """('sift with max_features=500', 'sift with max_features=2000'): each identity's name and the
    entries where the two differ (shown escaped by repr; the file's attribute is data, not trusted)."""
    mine = json.loads(ours)
    try:
        theirs = json.loads(found)
        theirs = theirs if isinstance(theirs, dict) else {}
    except (TypeError, ValueError):
        theirs = {}
    keys = sorted(k for k in set(mine) | set(theirs) if k != "name" and mine.get(k) != theirs.get(k))

    def shown(identity: dict) -> str:
        name = identity.get("name", "unknown")
        detail = ", ".join(f"{k}={identity.get(k)!r}" for k in keys[:4]) + (", ..." if len(keys) > 4 else "")
        return f"{name!r} with {detail}" if detail else repr(name)
    return shown(theirs), shown(mine)
