"""Per-image data a stage computes once and keeps (local features), beside the descriptor stores.

    features/<name>-<identity hash>/<dataset>-<images key>/<split>.h5
        attrs: feature identity (what computed it), images key (the split's names and contents)
        images/<row>/<array>...   one group per image, written whole with its crc32, marked done last

Keyed like descriptor stores: by what computed the data (the extractor and its options) and the
content of the images, so every retriever and re-ranking run on those images shares one file.
A run holds the folder's lock while it reads and writes (resumable: an image already done is read,
never recomputed); a file written for another extractor or other images is refused by name. What is
read is checked, as descriptor stores are: an image whose arrays no longer match their crc32 is
recomputed (said in a warning), a file HDF5 cannot read (torn by a kill: HDF5 is not crash-safe)
is discarded.
"""
from __future__ import annotations

import json
import os
import warnings
import zlib
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
from ..store.rows_file import close_quietly

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
            held, damaged = 0, []

            def get(row: int) -> dict[str, np.ndarray]:
                nonlocal held
                if row in kept:
                    kept.move_to_end(row)
                    return kept[row]
                found = self._read(handle, row, path)
                if found is False:
                    damaged.append(row)
                if not isinstance(found, dict):
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
                close_quietly(handle)  # after a failed write (a full disk) the close fails too
                if damaged:  # one line per file, not one per image
                    shown = ", ".join(map(str, damaged[:5])) + (", ..." if len(damaged) > 5 else "")
                    warnings.warn(f"Local features of {len(damaged)} image(s) ({shown}) in {path} no longer matched "
                                  "the checksums written with them; they were recomputed.", stacklevel=3)

    def _open(self, path: Path, split: str) -> h5py.File:
        handle = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            handle = _appendable(path)
            fresh = "images" not in handle
            found, images = handle.attrs.get("feature_identity"), handle.attrs.get("images_key")
        except (OSError, RuntimeError, KeyError) as error:
            if isinstance(error, PermissionError) or not path.exists():
                raise cache_error(error, path) from None
            if handle is not None:
                close_quietly(handle)
            try:  # torn by a kill mid-write (HDF5 is not crash-safe): recomputed
                path.unlink()
                handle, fresh = _appendable(path), True
            except OSError as error:
                raise cache_error(error, path) from None
        if fresh:
            handle.attrs["feature_identity"] = self.identity_json
            handle.attrs["images_key"] = self.images_keys[split]
            handle.create_group("images")
            return handle
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
    def _read(handle: h5py.File, row: int, path: Path) -> dict[str, np.ndarray] | None | bool:
        """The image's arrays; None when they are to be computed (absent, left unfinished by a
        killed run, or written before groups carried a crc32), False when they no longer match
        their crc32 (recomputed too). A group HDF5 cannot read discards the file."""
        try:
            group = handle["images"].get(str(row))
            if group is None or not group.attrs.get("done") or "crc32" not in group.attrs:
                return None
            found = {key: group[key][...] for key in group}
            if int(group.attrs["crc32"]) == _checksum(found):
                return found
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as error:
            close_quietly(handle)
            try:
                path.unlink(missing_ok=True)
            except OSError as failure:
                raise cache_error(failure, path) from None
            raise VPRBenchError(f"Local features {path} are damaged (image {row} cannot be read: {error}); the file "
                                "was discarded: run again to recompute it.") from None
        return False

    @staticmethod
    def _write(handle: h5py.File, row: int, arrays: dict[str, np.ndarray], path: Path) -> None:
        try:
            images = handle["images"]
            if str(row) in images:  # left unfinished by a killed run, or damaged
                del images[str(row)]
            group = images.create_group(str(row))
            for key, value in arrays.items():
                group.create_dataset(key, data=value)
            group.attrs["crc32"] = _checksum({key: group[key][...] for key in group})  # of the bytes as stored
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


def _appendable(path: Path) -> h5py.File:
    """`path` opened to read and write (created when absent) without HDF5's sieve buffer: data are
    written when written, so a full disk fails that write with an error. (With the buffer, the
    write failed later, when h5py freed it, where the error can only be printed; HDF5 then crashed
    the process.)"""
    access = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    access.set_libver_bounds(h5py.h5f.LIBVER_EARLIEST, h5py.h5f.LIBVER_LATEST)  # as h5py.File's
    access.set_sieve_buf_size(0)
    name = os.fsencode(path)
    try:
        return h5py.File(h5py.h5f.open(name, h5py.h5f.ACC_RDWR, fapl=access))
    except FileNotFoundError:
        return h5py.File(h5py.h5f.create(name, h5py.h5f.ACC_EXCL, fapl=access))


def _checksum(arrays: dict[str, np.ndarray]) -> int:
    """crc32 of an image's arrays: each one's name, dtype, shape and bytes."""
    crc = 0
    for key in sorted(arrays):
        value = np.ascontiguousarray(arrays[key])
        crc = zlib.crc32(value.tobytes(), zlib.crc32(f"{key}|{value.dtype.str}|{value.shape}|".encode(), crc))
    return crc


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
