"""Per-image data a stage computes once and keeps (local features), beside the descriptor stores.

    features/<name>-<identity hash>/<dataset>-<images key>/<split>.<n>.h5   segments 1, 2, ...
        attrs: feature identity (what computed it), images key (the split's names and contents)
        attrs rows, row_bytes: the rows it holds and their arrays' bytes, written last (read instead of every group)
        attrs arrays, row_at, row_crc32: where each row's arrays lie in the file and their crc32 (read
            without HDF5: opening a segment per image read cost more than the read; absent: read by group)
        images/<row>/<array>...   one group per image, with its crc32

Keyed like descriptor stores: by what computed the data (the extractor and its options) and the
content of the images, so every retriever and re-ranking run on those images shares one folder.
Images computed are written in segments of SEGMENT_IMAGES (or SEGMENT_BYTES): each segment a new
file written whole and renamed into place (fsutil.atomic_path), never changed afterwards. So a
full disk or a kill mid-write loses only the segment being written (HDF5 is not crash-safe: a file
it was writing when the disk filled is unreadable, which is why files are never appended to); the
rerun reads every segment written and computes the rest. A run holds the folder's lock while it
reads and writes; a segment written for another extractor or other images is refused by name.
What is read is checked, as descriptor stores are: an image whose arrays no longer match their
crc32 is recomputed, a segment HDF5 cannot open is discarded (each said in a warning). The newest
segment holding an image wins. A crc32 is no proof against a file edited or crafted with its checksums
written again: a store given the arrays' `form` recomputes an image that does not fit it (said too).
"""
from __future__ import annotations

import json
import math
import os
import warnings
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import h5py
import numpy as np

from ..errors import VPRBenchError
from ..fsutil import CacheError, atomic_path, cache_error, lock, remove_stale
from ..hashing import canonical_hash, canonical_json
from ..paths import cache_root, safe_name, special_file
from ..text import shortened
from ..store.rows_file import close_quietly

#: bytes of per-image arrays kept in memory per open split (database images recur across queries), at
#: most: a stage keeps a quarter of its memory budget per split (stages' `features`)
KEPT_BYTES = 256 * 2**20
#: images computed are written as one segment once this many (or SEGMENT_BYTES) are waiting, and
#: when the split is closed: a kill loses at most one segment's work, a run adds few files
SEGMENT_IMAGES = 64
SEGMENT_BYTES = 16 * 2**20
#: segments kept open while a split is read (opening one per image read cost ~0.25 ms)
OPEN_SEGMENTS = 32
#: dtype kinds whose stored bytes are the values (read by layout; others, e.g. strings HDF5 keeps in a heap, by group)
PLAIN = "biufc"


class FeatureStore:
    def __init__(self, name: str, identity: dict, label: str, images_keys: dict[str, str], cache_dir=None,
                 lock_timeout: float | None = None, kept_bytes: int = KEPT_BYTES, form: dict | None = None):
        self.name, self.identity_json = name, canonical_json({"name": name, **identity})
        #: array name -> (dtype, trailing shape; None for any length) of each image, the arrays sharing their
        #: first axis (one row per keypoint or patch); None: not checked (a plugin stage's store)
        self.form = form
        self.images_keys, self.lock_timeout, self.kept_bytes = images_keys, lock_timeout, kept_bytes
        #: images computed (not read) through this store: 0 on a run served from the cache
        self.computed = 0
        self.path = (cache_root(cache_dir) / "features" / f"{safe_name(name)}-{canonical_hash(json.loads(self.identity_json))}"
                     / f"{safe_name(label)}-{canonical_hash(images_keys)}")

    @classmethod
    def for_images(cls, name: str, identity: dict, dataset, cache_dir=None, lock_timeout=None,
                   kept_bytes: int = KEPT_BYTES, form: dict | None = None) -> "FeatureStore":
        return cls(name, identity, dataset.name, dataset.images_fingerprint(cache_dir), cache_dir, lock_timeout,
                   kept_bytes, form)

    def files(self, split: str) -> list[Path]:
        """The split's segments, oldest first (`<split>.h5`, one file appended to by earlier versions, first)."""
        numbered = [(int(p.name.split(".")[1]), p) for p in self.path.glob(f"{split}.*.h5")
                    if p.name.split(".")[1].isdigit()]
        earlier = self.path / f"{split}.h5"
        return ([earlier] if earlier.exists() else []) + [p for _, p in sorted(numbered)]

    @contextmanager
    def opened(self, split: str, compute: Callable[[int], dict[str, np.ndarray]]) -> Iterator[Callable[[int], dict]]:
        """`get(row)` for the split's images: read when stored, else `compute(row)` (name -> array),
        written with the next segment (a killed run resumes from the last one). Holds the folder's lock."""
        with lock(self.path / ".lock", self.lock_timeout, what=f"local features {self.path}"):
            remove_stale(self.path.glob(f".{split}.*.tmp"), age_s=0)  # a killed writer's (we hold the lock)
            where, layouts = self._index(split)
            kept: OrderedDict[int, dict] = OrderedDict()
            waiting: dict[int, dict] = {}  # computed, not yet written
            held, damaged, misfits, failed = 0, {}, {}, False
            readers: OrderedDict[Path, h5py.File] = OrderedDict()  # segments kept open to read

            def write() -> None:
                nonlocal failed
                failed = True  # until written: a write that failed is not tried again on the way out
                where.update(dict.fromkeys(waiting, self._write(split, waiting)))
                waiting.clear()
                failed = False

            def get(row: int) -> dict[str, np.ndarray]:
                nonlocal held
                if row in kept:
                    kept.move_to_end(row)
                    return kept[row]
                found = waiting.get(row)
                if found is None and row in where:
                    path = where[row]
                    found = _read_at(path, layouts[path], row) if path in layouts else self._read(readers, path, row)
                    if found is False:
                        damaged.setdefault(where.pop(row), []).append(row)
                    elif self.form is not None and (misfit := _misfit(found, self.form)):
                        # its checksum matches, yet the stage would fail on it (a traceback) or read nonsense
                        misfits.setdefault(where.pop(row), [misfit, []])[1].append(row)
                        found = None
                if not isinstance(found, dict):
                    found = {key: np.asarray(value) for key, value in compute(row).items()}
                    waiting[row] = found
                    self.computed += 1
                    if len(waiting) >= SEGMENT_IMAGES or _size(waiting.values()) >= SEGMENT_BYTES:
                        write()
                kept[row] = found
                held += _size([found])
                while held > self.kept_bytes and len(kept) > 1:
                    held -= _size([kept.popitem(last=False)[1]])
                return found

            try:
                yield get
            except BaseException:
                if waiting and not failed:  # an interrupt, an image that failed: keep what was computed
                    with suppress(VPRBenchError):
                        write()
                raise
            else:
                if waiting:
                    write()
            finally:
                for handle in readers.values():
                    close_quietly(handle)
                for path, rows in damaged.items():  # one line per file, not one per image
                    shown = ", ".join(map(str, rows[:5])) + (", ..." if len(rows) > 5 else "")
                    warnings.warn(f"Local features of {len(rows)} image(s) ({shown}) in {path} no longer matched "
                                  "the checksums written with them; they were recomputed.", stacklevel=3)
                for path, (misfit, rows) in misfits.items():
                    shown = ", ".join(map(str, rows[:5])) + (", ..." if len(rows) > 5 else "")
                    warnings.warn(f"Local features of {len(rows)} image(s) ({shown}) in {path} are not what "
                                  f"{self.name!r} computes ({misfit}); they were recomputed.", stacklevel=3)

    def _index(self, split: str) -> tuple[dict[int, Path], dict[Path, "Layout"]]:
        """row -> the newest segment holding it, and the layout of each segment that has one. A
        segment HDF5 cannot open (damaged; or the file earlier versions appended to, torn by a kill
        or a full disk) is discarded, said in a warning: its images are computed again."""
        where: dict[int, Path] = {}
        layouts: dict[Path, Layout] = {}
        for path in self.files(split):
            try:
                if special_file(path):  # HDF5 would wait on a pipe for good
                    raise ValueError("it is a named pipe, device or socket, not a file")
                with h5py.File(path, "r") as f:
                    found, images, rows = (f.attrs.get(key) for key in ("feature_identity", "images_key", "rows"))
                    if rows is None:  # a segment of an earlier version: every group's attributes (~7 ms a file)
                        rows = [int(name) for name, group in f["images"].items()
                                if group.attrs.get("done") and "crc32" in group.attrs]
                    elif "row_at" in f.attrs:
                        layouts[path] = Layout(rows, f.attrs["arrays"], f.attrs["row_at"], f.attrs["row_crc32"])
                    rows = [int(row) for row in rows]
            except (OSError, RuntimeError, KeyError, ValueError, TypeError) as error:
                if isinstance(error, PermissionError):
                    raise cache_error(error, path) from None
                try:
                    path.unlink()
                except OSError as failure:
                    raise cache_error(failure, path) from None
                warnings.warn(f"Local features {path} are damaged ({shortened(str(error))}); the file was discarded "
                              "and its images are computed again.", stacklevel=4)
                continue
            self._check(path, found, images, split)
            where.update(dict.fromkeys(rows, path))
        return where, layouts

    def _check(self, path: Path, found, images, split: str) -> None:
        # an attribute edited into an array compared element by element (a traceback): text only
        found, images = (value if isinstance(value, str) else None for value in (found, images))
        if found == self.identity_json and images == self.images_keys[split]:
            return
        ours = self.name
        if found != self.identity_json:
            theirs, ours = _differing(found, self.identity_json)
            what = f"another extractor ({theirs})"
        else:
            what = "other images"
        raise VPRBenchError(f"Local features {path} were computed by {what}, not {ours} as this run computes "
                            "them: delete that file (it is recomputed).")

    @staticmethod
    def _read(readers: OrderedDict, path: Path, row: int) -> dict[str, np.ndarray] | bool:
        """The image's arrays (indexed: done, with a crc32), False when they no longer match their
        crc32 (recomputed). A group HDF5 cannot read discards the segment. `readers`: the segments
        open to read, the least recently used closed past OPEN_SEGMENTS."""
        try:
            if path not in readers:
                readers[path] = h5py.File(path, "r")
                while len(readers) > OPEN_SEGMENTS:
                    close_quietly(readers.popitem(last=False)[1])
            readers.move_to_end(path)
            group = readers[path]["images"][str(row)]
            found = {key: group[key][...] for key in group}
            crc = int(group.attrs["crc32"])
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as error:
            if path in readers:
                close_quietly(readers.pop(path))
            raise _discarded(path, row, error) from None
        return found if crc == _checksum(found) else False

    def _write(self, split: str, images: dict[int, dict[str, np.ndarray]]) -> Path:
        """`images` as a new segment, written whole, then renamed into place; its path."""
        last = self.files(split)[-1:]
        number = int(last[0].name.split(".")[1]) + 1 if last and last[0].name.count(".") == 2 else 1
        path = self.path / f"{split}.{number}.h5"
        try:
            with atomic_path(path) as temporary:
                handle = _created(temporary)
                try:
                    handle.attrs["feature_identity"] = self.identity_json
                    handle.attrs["images_key"] = self.images_keys[split]
                    written = []  # (datasets, crc32) per row
                    for row, arrays in images.items():
                        group = handle.create_group(f"images/{row}")
                        stored = {key: group.create_dataset(key, data=value) for key, value in arrays.items()}
                        crc = _checksum({key: value[...] for key, value in stored.items()})  # as stored
                        group.attrs["crc32"], group.attrs["done"] = crc, 1
                        written.append((stored, crc))
                    # last, so they list only groups written whole; SEGMENT_IMAGES rows at most (64 kB attribute limit)
                    handle.attrs.update(Layout.of(written))
                    handle.attrs["row_bytes"] = np.array([_size([arrays]) for arrays in images.values()], np.int64)
                    handle.attrs["rows"] = np.fromiter(images, np.int64, len(images))
                    handle.close()
                finally:
                    close_quietly(handle)  # after a failed write (a full disk) the close fails too
        except (OSError, RuntimeError, CacheError) as error:  # a full disk: the segments before this one are kept
            raise cache_error(error, path, kept="the local features written so far") from None
        return path

    def bytes_per_image(self, split: str = "database") -> float:
        """Bytes of the arrays stored per image of `split` (what the stage keeps), 0 when none. Without the lock a
        run holds for its whole stage (this waited for it): segments never change once in place; one gone is skipped."""
        sizes: dict[int, int] = {}
        for path in (p for p in self.files(split) if not special_file(p)):  # a pipe would hang HDF5
            try:
                with h5py.File(path, "r") as f:
                    rows, row_bytes = f.attrs.get("rows"), f.attrs.get("row_bytes")
                    if rows is not None and row_bytes is not None:
                        sizes.update(zip(map(int, rows), map(int, row_bytes)))
                    else:  # an earlier version's segment: every group and array (~70 ms a file)
                        sizes.update((int(name), sum(d.nbytes for d in g.values()))
                                     for name, g in f["images"].items() if g.attrs.get("done"))
            except (OSError, RuntimeError, KeyError, ValueError, TypeError):
                continue
        return sum(sizes.values()) / len(sizes) if sizes else 0.0


class Layout:
    """Where a segment's rows lie in its file: each array's offset and first-axis length per row,
    the arrays' names, dtypes and trailing shapes (the same for every row), each row's crc32."""

    def __init__(self, rows, arrays, row_at, row_crc32):
        self.position = {int(row): i for i, row in enumerate(rows)}
        self.arrays = [(str(key), np.dtype(str(dtype)), _dimensions(rest)) for key, dtype, rest in json.loads(arrays)]
        self.at, self.crc = _integers(row_at), _integers(row_crc32)
        if self.at.shape != (len(self.position), len(self.arrays), 2) or self.crc.shape != (len(self.position),):
            raise ValueError(f"a layout of shape {self.at.shape} for {len(self.position)} rows")
        if any(dtype.kind not in PLAIN for _, dtype, _ in self.arrays):
            raise ValueError(f"a layout of arrays of {[str(dtype) for _, dtype, _ in self.arrays]}")

    @staticmethod
    def of(written: list[tuple[dict[str, h5py.Dataset], int]]) -> dict:
        """The attributes of a segment of rows `written` (each one's datasets and crc32); none when
        its arrays are not all stored whole in place with the same names, dtypes and trailing
        shapes (then read by group)."""
        specs = [[(key, d.dtype.str, d.shape[1:]) for key, d in sorted(stored.items())] for stored, _ in written]
        if any(spec != specs[0] for spec in specs) or any(d.dtype.kind not in PLAIN for d in written[0][0].values()):
            return {}
        at = []
        for stored, _ in written:
            arrays = [stored[key] for key, _, _ in specs[0]]
            offsets = [a.id.get_offset() for a in arrays]
            if any(a.ndim == 0 or offset is None and a.size for offset, a in zip(offsets, arrays)):  # chunked, compact
                return {}
            at.append([(-1 if offset is None else offset, a.shape[0]) for offset, a in zip(offsets, arrays)])
        return {"arrays": json.dumps(specs[0]), "row_at": np.array(at, np.int64).reshape(len(written), len(specs[0]), 2),
                "row_crc32": np.array([crc for _, crc in written], np.int64)}


def _dimensions(rest) -> tuple[int, ...]:
    """A layout's trailing shape; anything but whole numbers in range (an infinity, a float) is a
    ValueError: the segment is discarded."""
    if not isinstance(rest, list) or any(type(n) is not int or not 0 <= n < 2**32 for n in rest):
        raise ValueError(f"a layout's trailing shape {str(rest)[:80]}")
    return tuple(rest)


def _integers(values) -> np.ndarray:
    """A layout's offsets or crc32s as int64; not integers (a float would be cast silently, NaN with a
    warning) is a ValueError."""
    found = np.asarray(values)
    if found.dtype.kind not in "iu":
        raise ValueError(f"a layout of {found.dtype} values")
    return found.astype(np.int64)


def _read_at(path: Path, layout: Layout, row: int) -> dict[str, np.ndarray] | bool:
    """The image's arrays read at their offsets (one plain file read each, no HDF5), False when
    they no longer match their crc32 (recomputed). A layout past the file's end discards the segment."""
    i = layout.position[row]
    try:
        with open(path, "rb") as f:
            end, found = os.fstat(f.fileno()).st_size, {}
            for (key, dtype, rest), (offset, length) in zip(layout.arrays, layout.at[i].tolist()):
                size = length * dtype.itemsize * math.prod(rest)  # exact: np.prod wraps past 2**63
                if length < 0 or size and not 0 <= offset <= end - size:
                    raise ValueError(f"{key} at {offset} ({size} bytes) lies outside the file ({end} bytes)")
                found[key] = value = np.empty((length, *rest), dtype)
                if size:
                    f.seek(offset)
                    if f.readinto(value) != size:
                        raise ValueError(f"{key} at {offset} was cut short")
    except (OSError, ValueError) as error:
        raise _discarded(path, row, error) from None
    return found if int(layout.crc[i]) == _checksum(found) else False


def _discarded(path: Path, row: int, error: Exception) -> VPRBenchError:
    """The damaged segment `path` deleted (its images are computed again on the next run); the error saying so."""
    try:
        path.unlink(missing_ok=True)
    except OSError as failure:
        return cache_error(failure, path)
    return VPRBenchError(f"Local features {path} are damaged (image {row} cannot be read: {error}); the file "
                         "was discarded: run again to recompute it.")


def _misfit(arrays: dict[str, np.ndarray], form: dict) -> str | None:
    """What in an image's stored arrays does not fit `form` (FeatureStore's), None when they fit."""
    if set(arrays) != set(form):
        return shortened(f"arrays {sorted(arrays)!r}, not {sorted(form)!r}", 160)  # names from the file, quoted
    for key, (dtype, rest) in form.items():
        value = np.asarray(arrays[key])  # a scalar string dataset reads as bytes
        if value.dtype != np.dtype(dtype) or value.ndim != 1 + len(rest) \
                or any(want is not None and n != want for n, want in zip(value.shape[1:], rest)):
            wanted = ", ".join(["n", *("any" if n is None else str(n) for n in rest)])
            return f"{key} {value.dtype} {value.shape}, not {dtype} ({wanted})"
        if value.dtype.kind in "fc" and not np.isfinite(value).all():
            return f"{key} holds values that are not finite"
    lengths = {arrays[key].shape[0] for key in form}
    return f"arrays of {sorted(lengths)} rows, not one row per feature" if len(lengths) > 1 else None


def _size(images) -> int:
    return sum(a.nbytes for arrays in images for a in arrays.values())


def _created(path: Path) -> h5py.File:
    """A new file at `path` (replacing what is there) without HDF5's sieve buffer: data are
    written when written, so a full disk fails that write with an error. (With the buffer, the
    write failed later, when h5py freed it, where the error can only be printed; HDF5 then crashed
    the process.)"""
    access = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    access.set_libver_bounds(h5py.h5f.LIBVER_EARLIEST, h5py.h5f.LIBVER_LATEST)  # as h5py.File's
    access.set_sieve_buf_size(0)
    return h5py.File(h5py.h5f.create(os.fsencode(path), h5py.h5f.ACC_TRUNC, fapl=access))


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
