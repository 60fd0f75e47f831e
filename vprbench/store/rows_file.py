"""One HDF5 file of descriptor rows: a whole split (a store) or a rank's shard of it.

Layout: `descriptors` (rows x dim, float32 or float16), `checksums` (the crc32 of each row's
stored bytes, written with the row), `done` (one flag per row), `names` (the images,
variable-length UTF-8), `complete` (one byte, set last) and attributes saying what the file
is (`RowsIdentity`). A checksum block is one row: rows are written in batches of any size
and resumed anywhere, and a row is the one block every write covers whole. Every dataset is contiguous and allocated when
the file is created, and the file is created whole under a temporary name and renamed into
place: after that only raw bytes change (rows, then their flags, then the completion byte),
never HDF5's metadata, so a kill at any moment leaves a readable file whose flagged rows
are all on disk. A file is complete only when its content says so: completion byte set,
every row done, names, row range, fit and dtype as expected. That is checked whenever a
file is opened for reading and again when it has changed since; the rows' content is
checked against their checksums as they are read (reader.py).
"""
from __future__ import annotations

import errno
import os
import zlib
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import VPRBenchError
from ..fsutil import atomic_path, cache_error, lock
from ..paths import special_file

FORMAT = "vprbench-rows-3"
#: the format before rows carried checksums: such a file is stale (recomputed), never trusted
UNCHECKED_FORMAT = "vprbench-rows-2"
DTYPES = ("float32", "float16")
#: bytes read or copied at a time when a whole file is read or merged
BLOCK_BYTES = 64 * 2**20


@dataclass(frozen=True)
class RowsIdentity:
    """What a rows file must say about itself to belong where it lies."""

    store: str             # the store folder's key and the split, e.g. "hog-1a2b/corridor-3c4d/database"
    start: int             # first row of the split this file holds
    stop: int
    total: int             # rows in the whole split
    fit_id: str            # identity of the method's fit (vocabulary) the rows were computed with
    dtype: str
    fingerprint: str       # the method fingerprint, JSON (for people reading the file)
    names: list[str] = field(repr=False)  # names of rows start..stop

    def attrs(self) -> dict:
        return {"format": FORMAT, "store": self.store, "start": self.start, "stop": self.stop,
                "total": self.total, "fit_id": self.fit_id, "dtype": self.dtype}

    def write_into(self, f: h5py.File, dim: int) -> None:
        """Names and fingerprint as datasets (attributes are capped at 64 KB), the rest as attributes,
        with the width the method wrote (`dim`): descriptors rewritten later at another width are the
        file's fault, not the method's."""
        f.create_dataset("names", data=self.names, dtype=h5py.string_dtype("utf-8"))
        f.create_dataset("fingerprint", data=self.fingerprint, dtype=h5py.string_dtype("utf-8"))
        f.attrs.update({**self.attrs(), "dim": int(dim)})


@dataclass
class Inspection:
    """What a file on disk is: absent, torn (unreadable), foreign (belongs to another store or
    run), stale (computed with another fit), partial (with the done mask) or complete."""

    status: str
    reason: str = ""
    done: np.ndarray | None = None
    dim: int | None = None


class DamagedRows(VPRBenchError):
    """Rows of a file whose bytes no longer match the checksums written with them."""

    def __init__(self, path: Path, rows: np.ndarray):
        self.path, self.rows = Path(path), np.unique(rows)
        rows = self.rows
        if len(rows) == 1:
            self.detail = f"row {int(rows[0]):,} no longer matches the checksum written with it"
        else:
            self.detail = f"rows {int(rows[0]):,} and {len(rows) - 1:,} more no longer match the checksums written with them"
        super().__init__(f"Descriptor store {path} is damaged: {self.detail}.")


def row_checksums(rows: np.ndarray) -> np.ndarray:
    """crc32 of each row's bytes as stored (little-endian), uint32."""
    rows = np.ascontiguousarray(rows, dtype=rows.dtype.newbyteorder("<"))
    return np.fromiter((zlib.crc32(row) for row in rows), dtype=np.uint32, count=len(rows))


def check_rows(path: Path, start: int, rows: np.ndarray, expected: np.ndarray) -> None:
    """Raise `DamagedRows` unless rows start.. (as stored) have the checksums `expected`."""
    bad = np.flatnonzero(row_checksums(rows) != expected)
    if len(bad):
        raise DamagedRows(path, bad + start)


@contextmanager
def folder_lock(folder: Path, timeout: float | None = None):
    """The lock of a store folder: held by the one process that creates, discards or renames its files."""
    with lock(Path(folder) / ".lock", timeout, what=f"descriptor store {folder}"):
        yield


def _early_contiguous() -> h5py.h5p.PropDCID:
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    return dcpl


def create_rows_file(path: Path, identity: RowsIdentity, dim: int) -> None:
    """Write the empty file whole (all space allocated) and rename it to `path`."""
    if identity.dtype not in DTYPES:
        raise VPRBenchError(f"store dtype must be one of {', '.join(DTYPES)}, got {identity.dtype!r}")
    n = identity.stop - identity.start
    with atomic_path(path) as temporary:
        with hdf5_written(temporary, path) as f:
            reserve(temporary, path, identity, dim)
            f.create_dataset("descriptors", shape=(n, dim), dtype=identity.dtype, dcpl=_early_contiguous(),
                             fill_time="never")
            f.create_dataset("checksums", shape=(n,), dtype="<u4", dcpl=_early_contiguous(), fillvalue=0)
            f.create_dataset("done", shape=(n,), dtype="uint8", dcpl=_early_contiguous(), fillvalue=0)
            f.create_dataset("complete", shape=(), dtype="uint8", dcpl=_early_contiguous(), fillvalue=0)
            identity.write_into(f, dim)


def reserve(path: Path, shown: Path, identity: RowsIdentity, dim: int) -> None:
    """Claim the file's disk space now: a full disk is then one clear error before any
    descriptor is computed, and writing rows later never needs a new block. (Instant on
    ext4, XFS, btrfs; where the filesystem cannot, the C library writes the zeros.)"""
    rows = identity.stop - identity.start
    size = rows * (dim * np.dtype(identity.dtype).itemsize + 5) + sum(len(n.encode()) + 32 for n in identity.names)
    if not hasattr(os, "posix_fallocate"):
        return
    fd = os.open(path, os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, size + 2**16)
    except OSError as error:
        if error.errno not in (errno.EOPNOTSUPP, errno.EINVAL):  # a filesystem that cannot: written as it comes
            raise cache_error(error, shown) from None
    finally:
        os.close(fd)


@contextmanager
def hdf5_written(path: Path, shown: Path):
    """A new HDF5 file, closed however the block ends: a failed write or close (a full disk)
    becomes a `CacheError` naming `shown`, and leaves no file handle behind."""
    try:
        f = h5py.File(path, "w", libver="earliest")
    except (OSError, RuntimeError) as error:
        raise cache_error(error, shown) from None
    try:
        yield f
        f.close()
    except (OSError, RuntimeError) as error:
        close_quietly(f)
        raise cache_error(error, shown) from None
    except BaseException:
        close_quietly(f)
        raise


def close_quietly(f: h5py.File) -> None:
    """Close after a failure; when HDF5 cannot flush (disk full), drop the handle anyway."""
    try:
        f.close()
    except (OSError, RuntimeError):
        try:
            f.id.close()
        except (OSError, RuntimeError, ValueError):
            pass


def inspect_rows_file(path: Path, identity: RowsIdentity) -> Inspection:
    if not path.exists():
        return Inspection("absent")
    if path.is_dir():  # not the cache's to delete (it may hold anything): said once, before any warning
        raise VPRBenchError(f"{path} is a folder where a descriptor store belongs: move or delete it (nothing in it "
                            "was changed), then run again.")
    if special_file(path):  # HDF5 would wait on a pipe for good: discarded as a torn file is
        return Inspection("torn", "it is a named pipe, device or socket, not a file")
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            if attrs.get("format") == UNCHECKED_FORMAT:
                return Inspection("stale", "it was written by an earlier vprbench, without row checksums")
            if attrs.get("format") != FORMAT:
                return Inspection("foreign", f"it is not a vprbench {FORMAT} file (format {attrs.get('format')!r})")
            expected = identity.attrs()
            for key in ("store", "start", "stop", "total", "dtype"):
                if _plain(attrs.get(key)) != expected[key]:
                    return Inspection("foreign", f"it holds {key} {_plain(attrs.get(key))!r}, this store needs {expected[key]!r}")
            n = identity.stop - identity.start
            descriptors = f["descriptors"]
            if (descriptors.ndim != 2 or descriptors.shape[0] != n or len(f["names"]) != n or f["done"].shape != (n,)
                    or f["checksums"].shape != (n,)):
                return Inspection("foreign", f"it holds descriptors of shape {descriptors.shape} and {len(f['names'])} "
                                             f"names, expected {n} rows of each")
            misfit = _layout_misfit(descriptors, identity.dtype, path.stat().st_size)
            written = _plain(attrs.get("dim"))  # None in files written before it was recorded
            if not misfit and written is not None and written != descriptors.shape[1]:
                misfit = f"its descriptors have {descriptors.shape[1]} columns, it was written with {written}"
            if misfit:
                return Inspection("torn", misfit)
            names = f["names"].asstr()[...].tolist()
            if names != identity.names:
                first = next(i for i, (a, b) in enumerate(zip(names, identity.names)) if a != b)
                return Inspection("foreign", f"row {identity.start + first} is {names[first]!r}, expected {identity.names[first]!r}")
            if attrs.get("fit_id") != identity.fit_id:
                return Inspection("stale", f"it was computed with fit {attrs.get('fit_id')!r}, not {identity.fit_id!r}")
            done = f["done"][...].astype(bool)
            dim = int(descriptors.shape[1])
            if int(f["complete"][()]) == 1 and done.all():
                return Inspection("complete", done=done, dim=dim)
            return Inspection("partial", done=done, dim=dim)
    except (OSError, KeyError, ValueError, TypeError) as error:
        if isinstance(error, PermissionError):
            raise cache_error(error, path) from None
        return Inspection("torn", f"it cannot be read ({error})")


def _layout_misfit(descriptors: h5py.Dataset, dtype: str, file_size: int) -> str:
    """Why `descriptors` is not laid out as `create_rows_file` writes it (one contiguous block of
    little-endian `dtype` with at least one column, inside the file), or "": its header is
    trusted for no size, type or place of another kind (a huge width, text, an external file)."""
    rows, dim = descriptors.shape
    expected = np.dtype(dtype).newbyteorder("<")
    if descriptors.dtype != expected:
        return f"its descriptors are stored as {descriptors.dtype}, not {expected}"
    if dim < 1 or descriptors.chunks is not None or not stored_inside(descriptors):
        return f"its descriptors ({rows} x {dim}) are not one block of rows inside the file"
    if descriptors.id.get_storage_size() != rows * dim * expected.itemsize or rows * dim * expected.itemsize > file_size:
        return f"its descriptors ({rows} x {dim}) do not fit in its {file_size:,} bytes"
    return ""


def stored_inside(data: h5py.Dataset) -> bool:
    """Whether the dataset's values lie in its own file: not in an external raw file or another
    HDF5 file (virtual), whose bytes are not those a file's checksum or sha256 covers."""
    return not data.is_virtual and data.id.get_create_plist().get_external_count() == 0


def _plain(value):
    return value.item() if isinstance(value, np.generic) else value


class RowWriter:
    """Rows written into an existing rows file: rows and their checksums first, then their
    flags, each flushed, so a row flagged done is always fully on disk."""

    def __init__(self, path: Path, identity: RowsIdentity):
        self.path, self.identity = path, identity
        try:
            self.file = h5py.File(path, "r+")
        except (OSError, RuntimeError) as error:
            raise cache_error(error, path) from None
        self.descriptors, self.done, self.checksums = self.file["descriptors"], self.file["done"], self.file["checksums"]
        self.dim = int(self.descriptors.shape[1])

    def write(self, rows: np.ndarray, descriptors: np.ndarray) -> None:
        """`rows` are ascending split row numbers inside this file's range."""
        local = np.asarray(rows, dtype=np.int64) - self.identity.start
        if not len(local):
            return
        values = np.asarray(descriptors, dtype=self.identity.dtype)
        first, last = int(local[0]), int(local[-1]) + 1
        try:
            runs = _runs(local)
            if len(runs) > 1 and last - first <= 4 * len(local):
                # scattered rows (a resumed run): rewrite the block around them; rows already
                # done are written back with the bytes they hold
                block = self.descriptors[first:last]
                block[local - first] = values
                self.descriptors[first:last] = block
            else:
                for start, stop in runs:
                    at = int(np.searchsorted(local, start))
                    self.descriptors[start:stop] = values[at:at + stop - start]
            sums = self.checksums[first:last]
            sums[local - first] = row_checksums(values)
            self.checksums[first:last] = sums
            self.file.flush()
            flags = self.done[first:last]
            flags[local - first] = 1
            self.done[first:last] = flags
            self.file.flush()
        except (OSError, RuntimeError) as error:
            raise cache_error(error, self.path) from None

    def finish(self) -> None:
        """Set the completion byte (last), flush to disk, close."""
        try:
            if not self.done[...].all():
                raise VPRBenchError(f"{self.path}: rows are missing; it cannot be marked complete")
            self.file["complete"][()] = 1
            self.file.flush()
            self.file.close()
            with open(self.path, "rb+") as f:
                os.fsync(f.fileno())
        except (OSError, RuntimeError) as error:
            raise cache_error(error, self.path) from None

    def close(self) -> None:
        if self.file.id.valid:
            close_quietly(self.file)


def _runs(local: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive runs [first, last) of ascending row numbers."""
    if not len(local):
        return []
    breaks = np.flatnonzero(np.diff(local) != 1) + 1
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [len(local)]])
    return [(int(local[s]), int(local[e - 1]) + 1) for s, e in zip(starts, ends)]


def merge_rows_files(parts: list[tuple[Path, RowsIdentity]], path: Path, identity: RowsIdentity, dim: int) -> None:
    """Copy complete shards, in row order, into one new complete file at `path` (atomically),
    each row with the checksum its writer gave it, checked as it is copied (a damaged shard
    raises `DamagedRows` naming it)."""
    n = identity.stop - identity.start
    block = max(1, BLOCK_BYTES // max(1, dim * np.dtype(identity.dtype).itemsize))
    with atomic_path(path) as temporary:
        with hdf5_written(temporary, path) as out:
            reserve(temporary, path, identity, dim)
            target = out.create_dataset("descriptors", shape=(n, dim), dtype=identity.dtype,
                                        dcpl=_early_contiguous(), fill_time="never")
            sums = out.create_dataset("checksums", shape=(n,), dtype="<u4", dcpl=_early_contiguous())
            for part_path, part in parts:
                with h5py.File(part_path, "r") as f:
                    source, written = f["descriptors"], f["checksums"]
                    for first in range(0, part.stop - part.start, block):
                        last = min(part.stop - part.start, first + block)
                        rows, expected = source[first:last], written[first:last]
                        check_rows(part_path, part.start + first, rows, expected)
                        target[part.start + first:part.start + last] = rows
                        sums[part.start + first:part.start + last] = expected
            out.create_dataset("done", data=np.ones(n, np.uint8), dcpl=_early_contiguous())
            out.create_dataset("complete", data=np.uint8(1), dcpl=_early_contiguous())
            identity.write_into(out, dim)
