"""Row sources: descriptor matrices read a block of rows at a time, so nothing needs a whole
database in memory.

A row source is anything with `row_count`, `dim`, `dtype`, `folder` (where state fitted on
it may be kept, or None), `read_rows(start, stop)` and `read_rows_at(indices)` (indices
sorted ascending); both reads return a fresh float32 array the caller may modify, whatever
the stored dtype (float16 stores are widened). A source may also lend rows where they
are, read-only, with `view_rows(start, stop)` (None when it cannot): exact search then
computes on them without a copy. A complete descriptor store is one; `ArrayRows` wraps an
in-memory array.
"""
from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from .errors import VPRBenchError
from .text import shortened

#: default memory budget of search and post-processing fits (see parse_memory)
DEFAULT_MEMORY_BUDGET = 1_000_000_000
#: reads larger than this buy nothing (h5py and BLAS are at full speed well below it)
READ_BYTES = 64 * 2**20

# the lengths a descriptor row may have: what the loader checks a method's rows against, what search
# takes for an all-zero row
#: how far from 1 the length of a row compared by cosine may be (float16/bfloat16 arithmetic rounds it)
UNIT_TOLERANCE = 1e-2
#: a row shorter than this is an all-zero row (an image with nothing to describe): it matches nothing
ZERO_LENGTH = 1e-6
#: the longest row whose inner products stay within float32's range (sqrt of its largest value)
MAX_LENGTH = float(np.sqrt(np.finfo(np.float32).max))

_UNITS = {"": 1, "B": 1, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
          "KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TIB": 2**40}


@runtime_checkable
class RowSource(Protocol):
    row_count: int
    dim: int
    dtype: np.dtype
    folder: Path | None

    def read_rows(self, start: int, stop: int) -> np.ndarray: ...

    def read_rows_at(self, indices: np.ndarray) -> np.ndarray: ...


class ArrayRows:
    """An in-memory (N, D) array as a row source (for in-memory callers and tests).
    Reads return copies, as a file-backed store would."""

    def __init__(self, array, folder: str | Path | None = None):
        array = np.asarray(array)
        if array.ndim != 2:
            raise VPRBenchError(f"Descriptors must be an (N, D) matrix, got shape {array.shape}.")
        if not np.issubdtype(array.dtype, np.floating):
            raise VPRBenchError(f"Descriptors must be floating point, got {array.dtype}.")
        self.array = array
        self.row_count, self.dim = int(array.shape[0]), int(array.shape[1])
        self.dtype = array.dtype
        self.folder = Path(folder) if folder is not None else None

    def read_rows(self, start: int, stop: int) -> np.ndarray:
        return np.array(self.array[start:stop], dtype=np.float32)

    def read_rows_at(self, indices) -> np.ndarray:
        # the fancy index is a fresh copy already: np.array would make a second
        return np.asarray(self.array[np.asarray(indices, dtype=np.int64)], dtype=np.float32)

    def view_rows(self, start: int, stop: int) -> np.ndarray | None:
        """Rows start:stop of the array itself, read-only, when it is C-ordered float32."""
        if self.array.dtype != np.float32 or not self.array.flags.c_contiguous:
            return None
        view = self.array[start:stop].view()
        view.flags.writeable = False
        return view


def as_rows(source, name: str = "descriptors") -> RowSource:
    """An array becomes `ArrayRows`; anything else must already be a row source."""
    if isinstance(source, np.ndarray):
        return ArrayRows(source)
    missing = [a for a in ("row_count", "dim", "dtype", "folder", "read_rows", "read_rows_at") if not hasattr(source, a)]
    if missing:
        raise VPRBenchError(f"The {name} must be an array or a row source; {type(source).__name__} lacks {', '.join(missing)}.")
    return source


def read_bytes_per_row(rows: RowSource) -> int:
    """Memory one row costs while it is read: the float32 result, plus the stored dtype's
    buffer when it has to be widened (e.g. float16 stores)."""
    itemsize = np.dtype(rows.dtype).itemsize
    return rows.dim * (4 + (itemsize if np.dtype(rows.dtype) != np.float32 else 0))


def chunks(rows: RowSource, chunk_rows: int) -> Iterator[tuple[int, np.ndarray]]:
    """(start, float32 block) over the whole source, `chunk_rows` rows at a time. A caller that
    budgets for one chunk drops its block before asking for the next."""
    for start in range(0, rows.row_count, chunk_rows):
        stop = min(start + chunk_rows, rows.row_count)
        block = np.asarray(rows.read_rows(start, stop), dtype=np.float32)
        if block.shape != (stop - start, rows.dim):
            raise VPRBenchError(f"Row source returned shape {block.shape} for rows {start}:{stop}; expected "
                                f"({stop - start}, {rows.dim}).")
        yield start, block
        del block  # with the caller's reference gone too, one chunk is alive at a time


#: the largest memory budget taken, in bytes (int64's largest)
MAX_MEMORY = 2**63 - 1


def parse_memory(text, what: str = "Memory size") -> int:
    """'1GB' (10^9), '512MiB' (2^29), '2.5GB', or a number of bytes -> bytes; `what` names it in an error."""
    if isinstance(text, (int, np.integer)):
        value = int(text)
    else:
        match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([A-Za-z]*)\s*", str(text))
        unit = match.group(2).upper() if match else None
        if unit not in _UNITS:
            raise VPRBenchError(f"{what} {text!r} is not understood: use e.g. 1GB, 512MB, 2GiB or a number of bytes.")
        value = float(match.group(1)) * _UNITS[unit]  # inf for 400 digits: int() of it was an OverflowError
        value = int(value) if value <= MAX_MEMORY else MAX_MEMORY + 1
    if value <= 0:
        raise VPRBenchError(f"{what} must be positive, got {text!r}.")
    if value > MAX_MEMORY:  # no machine holds it, and tile sizes are counted in int64
        raise VPRBenchError(f"{what} {shortened(repr(text))} is more than any machine holds (at most "
                            f"{MAX_MEMORY:,} bytes): give e.g. 16GB.")
    return value


def format_bytes(n: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def format_budget(n: int) -> str:
    """`n` bytes rounded up to two digits, as a budget to give (format_bytes may round below `n`)."""
    step = 10 ** max(len(str(int(n))) - 2, 0)
    return format_bytes(-(-int(n) // step) * step)
