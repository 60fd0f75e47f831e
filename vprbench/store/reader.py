"""A complete descriptor store read as a row source, every row checked against its checksum.

Search computes on a store's rows where they are (`view_rows`: the file's pages, mapped
read-only): a complete store is never written in place (stores are replaced by renaming and
discarded by unlinking), so mapped rows stay the rows that were checked.

Each row's crc32 is checked the first time this reader reads it (again after the file has
changed on disk); `verify()` checks them all at once (an evaluation does before it
searches). A row that fails is never returned: the file is discarded under its folder's
lock (if it is still the file that failed) and `DamagedRows` says so, naming the store.
"""
from __future__ import annotations

import mmap
import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import VPRBenchError
from ..fsutil import cache_error
from ..paths import special_file
from .rows_file import BLOCK_BYTES, DamagedRows, RowsIdentity, check_rows, folder_lock, inspect_rows_file, _plain


class DescriptorStore:
    """A complete store, read as a "row source": `row_count`, `dim`, `dtype`, `folder`,
    `read_rows(start, stop)`, `read_rows_into(start, stop, out)` and `read_rows_at(indices)`
    give float32 rows."""

    def __init__(self, path: Path, identity: RowsIdentity):
        self.path, self.identity = Path(path), identity
        self.folder = self.path.parent
        self._signature = None
        self._placed = (None, None)  # (signature, byte offset of the descriptors or None)
        self._check_file()

    @classmethod
    def recorded(cls, path: Path, store: str) -> "DescriptorStore | None":
        """The complete store at `path` as its own content describes it (for readers that do
        not know the images, e.g. the leaderboard), or None when it is absent or incomplete."""
        if special_file(path):  # HDF5 would wait on a pipe for good
            return None
        try:
            with h5py.File(path, "r") as f:
                attrs = {k: _plain(v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
                names = f["names"].asstr()[...].tolist()
                fingerprint = f["fingerprint"].asstr()[()]
            identity = RowsIdentity(store=store, start=attrs["start"], stop=attrs["stop"], total=attrs["total"],
                                    fit_id=attrs["fit_id"], dtype=attrs["dtype"], fingerprint=fingerprint, names=names)
            return cls(path, identity)
        except (OSError, KeyError, ValueError, TypeError, VPRBenchError):
            return None

    def _check_file(self) -> None:
        """The file is complete and the one last checked, or is checked again (its rows too)."""
        try:
            stat = os.stat(self.path)
        except OSError as error:
            raise VPRBenchError(f"Descriptor store {self.path} has gone ({error.strerror}); run again to recompute it.") from None
        signature = (stat.st_ino, stat.st_size, stat.st_mtime_ns)
        if signature == self._signature:
            return
        found = inspect_rows_file(self.path, self.identity)
        if found.status != "complete":
            raise VPRBenchError(f"Descriptor store {self.path} is not complete: "
                                f"{found.reason or found.status}. Run the evaluation again to recompute it.")
        self.row_count = self.identity.stop - self.identity.start
        self.dim = found.dim
        self.dtype = np.dtype(self.identity.dtype)
        self._checked = np.zeros(self.row_count, dtype=bool)  # rows whose checksum this reader has checked
        self._signature = signature

    @property
    def names(self) -> list[str]:
        return list(self.identity.names)

    def content_key(self) -> str:
        """16 hex digits naming the rows' content (a hash of their stored checksums): what is
        fitted on these rows (a post-processor) is keyed by it, not by the folder it lies in."""
        import hashlib

        try:
            with h5py.File(self.path, "r") as f:
                checksums = np.ascontiguousarray(f["checksums"][...])
        except (OSError, KeyError) as error:
            raise cache_error(error, self.path) from None
        return hashlib.sha256(checksums.tobytes()).hexdigest()[:16]

    # ------------------------------------------------------------ checksums
    def _check(self, f: h5py.File, first: int, raw: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Check rows first.. (or `rows`, ascending, from `first`) as stored in `raw` against their checksums."""
        rows = np.arange(first, first + len(raw)) if rows is None else rows
        todo = ~self._checked[rows]
        if not todo.any():
            return
        expected = f["checksums"][first:int(rows[-1]) + 1][rows - first]
        try:
            if todo.all():
                check_rows(self.path, 0, raw, expected)
            else:
                check_rows(self.path, 0, raw[todo], expected[todo])
        except DamagedRows as error:
            self._discard(rows[todo][error.rows])
        self._checked[rows[todo]] = True

    def _discard(self, rows: np.ndarray) -> None:
        """Remove the damaged file (unless another run has already replaced it), then raise."""
        damage = DamagedRows(self.path, rows)
        with folder_lock(self.folder):
            try:
                stat = os.stat(self.path)
                if (stat.st_ino, stat.st_size, stat.st_mtime_ns) == self._signature:
                    self.path.unlink()
            except FileNotFoundError:
                pass
            except OSError as error:
                raise cache_error(error, self.path) from None
        self._signature = None
        damage.args = (f"Descriptor store {self.path} is damaged: {damage.detail}; it was discarded: run again to "
                       "recompute it.",)
        raise damage

    def verify(self) -> None:
        """Check every row against its checksum (reading the whole file once)."""
        self._check_file()
        block = max(1, BLOCK_BYTES // max(1, self.dim * self.dtype.itemsize))
        raw = np.empty((min(block, self.row_count), self.dim), dtype=self.dtype)
        with self._open() as f:
            data = f["descriptors"]
            for start in range(0, self.row_count, block):
                stop = min(start + block, self.row_count)
                if not self._checked[start:stop].all():
                    data.read_direct(raw, np.s_[start:stop], np.s_[:stop - start])
                    self._check(f, start, raw[:stop - start])

    # ------------------------------------------------------------ reads
    def read_rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        self._check_file()
        stop = self.row_count if stop is None else stop
        out = np.empty((max(0, stop - start), self.dim), dtype=np.float32)
        self.read_rows_into(start, stop, out)
        return out

    def read_rows_into(self, start: int, stop: int, out: np.ndarray) -> None:
        """Rows start:stop straight into `out` (float32, C-contiguous, stop - start rows)."""
        self._check_file()
        if not 0 <= start <= stop <= self.row_count:
            raise ValueError(f"rows {start}:{stop} outside 0:{self.row_count}")
        if out.shape != (stop - start, self.dim) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous float32 array of shape {(stop - start, self.dim)}")
        if stop == start:
            return
        with self._open() as f:
            raw = out if self.dtype == np.float32 else np.empty(out.shape, dtype=self.dtype)  # checked as stored
            f["descriptors"].read_direct(raw, np.s_[start:stop])
            self._check(f, start, raw)
        if raw is not out:
            out[...] = raw

    def view_rows(self, start: int, stop: int) -> np.ndarray | None:
        """Rows start:stop as a read-only view of the file's own pages (the system's file cache:
        no copy, no new memory), checked like a read; None when the descriptors are not one
        block of float32 inside the file, or the file was replaced since it was checked."""
        self._check_file()
        if not 0 <= start <= stop <= self.row_count:
            raise ValueError(f"rows {start}:{stop} outside 0:{self.row_count}")
        offset = self._offset()
        if offset is None or stop == start:
            return None
        first = offset + start * 4 * self.dim
        base = first - first % mmap.ALLOCATIONGRANULARITY
        try:
            with open(self.path, "rb") as file:
                stat = os.fstat(file.fileno())
                if (stat.st_ino, stat.st_size, stat.st_mtime_ns) != self._signature:
                    return None
                pages = _mapped(file.fileno(), first - base + (stop - start) * 4 * self.dim, base)
        except (OSError, ValueError):
            return None  # e.g. no address space: the rows are read instead
        rows = np.frombuffer(pages, np.float32, (stop - start) * self.dim, first - base).reshape(stop - start, self.dim)
        if not self._checked[start:stop].all():
            with self._open() as f:
                self._check(f, start, rows)
        return rows

    def _offset(self) -> int | None:
        """Where the descriptors start in the file, when they are one block of little-endian
        float32 inside it (not chunked, external or virtual)."""
        if self._placed[0] != self._signature:
            with self._open() as f:
                data = f["descriptors"]
                offset = data.id.get_offset()
                plain = (data.dtype == np.dtype("<f4") and data.chunks is None and not data.is_virtual
                         and data.id.get_create_plist().get_external_count() == 0)
                size = self.row_count * self.dim * 4
                inside = offset is not None and data.id.get_storage_size() == size and offset + size <= self._signature[1]
            self._placed = (self._signature, int(offset) if plain and inside else None)
        return self._placed[1]

    def read_rows_at(self, indices) -> np.ndarray:
        """Rows at ascending `indices` (repeats allowed), in that order."""
        self._check_file()
        indices = np.asarray(indices, dtype=np.int64)
        if len(indices) and (np.any(np.diff(indices) < 0) or indices[0] < 0 or indices[-1] >= self.row_count):
            raise ValueError("indices must be ascending and inside the store")
        raw = np.empty((len(indices), self.dim), dtype=self.dtype)
        block = max(1, BLOCK_BYTES // max(1, self.dim * self.dtype.itemsize))
        with self._open() as f:
            data = f["descriptors"]
            i = 0
            while i < len(indices):
                # rows close together are read as one slice; far apart ones one by one
                j = int(np.searchsorted(indices, indices[i] + block, side="left"))
                first, last = int(indices[i]), int(indices[j - 1]) + 1
                if (j - i) * 4 >= last - first:
                    raw[i:j] = data[first:last][indices[i:j] - first]
                else:
                    for k in range(i, j):
                        raw[k] = data[int(indices[k])]
                self._check(f, first, raw[i:j], indices[i:j])
                i = j
        return raw.astype(np.float32, copy=False)

    def read(self) -> np.ndarray:
        return self.read_rows(0, self.row_count)

    def _open(self) -> h5py.File:
        try:
            return h5py.File(self.path, "r")
        except OSError as error:
            raise cache_error(error, self.path) from None


def _mapped(fd: int, length: int, offset: int) -> mmap.mmap:
    if hasattr(mmap, "MAP_POPULATE"):  # Linux: pages mapped now, by the reading thread, not at the first product
        return mmap.mmap(fd, length, flags=mmap.MAP_SHARED | mmap.MAP_POPULATE, prot=mmap.PROT_READ, offset=offset)
    return mmap.mmap(fd, length, access=mmap.ACCESS_READ, offset=offset)
