"""Reading the authors' .npy files, and .npz archives from elsewhere, without running code.

VPR-Bench's `ground_truth_new.npy` (rows `[query_index, [positives]]`) and other released
ground-truth and pose files are numpy object arrays, which numpy stores as a pickle:
loading them with numpy, pickles allowed, would run whatever a hostile file names. `read_npy` reads
numeric arrays with numpy (no pickle at all), and object arrays with an unpickler that knows
only numpy's own array, dtype and scalar reconstruction; it then accepts only what these
files hold: ints and floats, lists, tuples or arrays of them, and texts (a pose table may
name its ROS topic); the caller checks the shape it needs. `read_npz` and `npz_headers` check each
member of an .npz (weights, a saved post-processing state) the same way, and bound what its members
unpack to before any is unpacked; objects are never read there.
"""
from __future__ import annotations

import math
import pickle
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format

from ...errors import VPRBenchError
from ...row_sources import format_bytes

try:
    from numpy._core import multiarray
except ImportError:  # numpy 1.x
    from numpy.core import multiarray


def _reconstruct(subtype, shape, dtype):
    if subtype is not np.ndarray or math.prod(shape) > 1:  # numpy writes (ndarray, (0,), ...)
        raise pickle.UnpicklingError(f"it rebuilds {subtype!r} of shape {shape!r}, not numpy's empty array")
    return multiarray._reconstruct(subtype, shape, dtype)


#: everything a pickled numpy object array refers to, under numpy 1.x and 2.x module names
_ALLOWED = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
for _module in ("numpy.core.multiarray", "numpy._core.multiarray"):
    _ALLOWED[_module, "_reconstruct"] = _reconstruct
    _ALLOWED[_module, "scalar"] = multiarray.scalar


class _ArrayUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(
                f"it asks to load {module}.{name}, which a data file never needs (unpickling it could run code)"
            )
        return _ALLOWED[module, name]


#: the most an .npz's members may unpack to, together, unless its caller gives another bound (a PCA
#: state of wide rows may need more: its reader bounds it by its rows): ten times what AnyLoc's
#: default PCA state needs (512 x 49,152 float32: 100 MB; per-query arrays of 27,592 queries x 100
#: candidates: 33 MB). A deflated member of zeros is a thousandth of its size: a 1 MB file could
#: otherwise claim a gigabyte.
NPZ_MAX_BYTES = 1 << 30


def _number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _numbers(value) -> bool:
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "iuf" or (value.dtype == object and all(_number(v) for v in value.ravel()))
    return isinstance(value, (list, tuple)) and all(_number(v) for v in value)


def _check_entries(array: np.ndarray) -> None:
    for index, value in np.ndenumerate(array):
        if not (_number(value) or _numbers(value) or isinstance(value, str)):
            where = ", ".join(map(str, index))
            raise ValueError(f"entry [{where}] is a {type(value).__name__}, not a number, a list of numbers or a text")


def _header(handle) -> tuple[tuple, np.dtype]:
    if handle.read(6) != npy_format.MAGIC_PREFIX:
        raise ValueError("it is not a .npy file (no numpy header)")
    handle.seek(0)
    version = npy_format.read_magic(handle)
    if version == (1, 0):
        shape, _, dtype = npy_format.read_array_header_1_0(handle)
    else:  # 2.0 and 3.0 differ from 1.0 only in the header's length field (and 3.0 in its encoding)
        shape, _, dtype = npy_format.read_array_header_2_0(handle)
    return tuple(shape), dtype


def _sized_header(handle, size: int) -> tuple[tuple, np.dtype]:
    """The header of the array at the start of `handle` (`size` bytes long), refused when it claims
    more data than those bytes hold (numpy would allocate what a few-byte header claims), or a shape
    no array has (numpy refuses it only when reading, which `npz_headers` does not)."""
    shape, dtype = _header(handle)
    # an item of no width (numpy never writes one) counted as a byte, or its count would be unbounded
    itemsize = max(dtype.itemsize, 1)
    if any(d < 0 for d in shape) or math.prod(d for d in shape if d) * itemsize >= 2**63:
        raise ValueError(f"its header announces shape {shape}, which no array has (a negative or too large dimension)")
    if not dtype.hasobject:
        needed, available = math.prod(shape) * itemsize, size - handle.tell()
        if needed > available:
            raise ValueError(f"it is truncated ({available} of {needed} data bytes)")
    return shape, dtype


def _unpickle_array(handle, shape: tuple) -> np.ndarray:
    array = _ArrayUnpickler(handle, encoding="latin1").load()  # latin1: numpy's advice for Python 2 files
    if not isinstance(array, np.ndarray) or array.shape != shape:
        raise ValueError(f"its pickle holds a {type(array).__name__}, not the {shape} array its header announces")
    _check_entries(array)
    return array


def as_indices(values) -> np.ndarray:
    """Image indices as int64: whole numbers only. A cast would silently turn 1.7 into 1 and
    NaN into a huge negative, or overflow with a traceback; these raise ValueError instead."""
    array = np.asarray(values, dtype=object).reshape(-1)
    out = np.empty(len(array), dtype=np.int64)
    for i, value in enumerate(array):
        # a Python int is whole however large (and too large for a float: math.isfinite would overflow)
        whole = _number(value) and (isinstance(value, (int, np.integer)) or math.isfinite(value)
                                    and float(value).is_integer())
        if not whole:
            raise ValueError(f"{value!r} is not an image index (a whole number)")
        if not -2**63 <= int(value) < 2**63:  # a crafted one may have thousands of digits: said by its size
            shown = repr(value) if int(value).bit_length() < 128 else f"a whole number of {int(value).bit_length()} bits"
            raise ValueError(f"{shown} is not an image index (it is beyond the 64-bit integer range)")
        out[i] = int(value)
    return out


def read_npy(path: Path, what: str, expected: str) -> np.ndarray:
    """The array in an .npy file: numbers or texts, or an object array of numbers, lists of
    numbers and texts.

    Anything else, a pickle asking for any other Python object included, is refused with a
    VPRBenchError naming the file, `what` it is and what was `expected`; nothing is run.
    OSError (missing file, permissions) is left to the caller (the CLI names the path).
    """
    path = Path(path)
    with open(path, "rb") as handle:
        try:
            shape, dtype = _sized_header(handle, path.stat().st_size)
            if dtype.hasobject:
                return _unpickle_array(handle, shape)
            if dtype.kind not in "iufUS":  # numbers, or texts (image lists): no pickle involved
                raise ValueError(f"it holds {dtype} values, not numbers or texts")
            handle.seek(0)
            return np.load(handle, allow_pickle=False)
        except (pickle.UnpicklingError, ValueError, TypeError, EOFError, AttributeError, IndexError, KeyError,
                OverflowError, MemoryError, RecursionError, struct.error) as error:
            raise VPRBenchError(f"Cannot read {what} {path}: {error}. Expected {expected}.") from None


def npz_headers(path: Path, what: str, expected: str, kinds: str = "iufUS",
                max_bytes: int = NPZ_MAX_BYTES) -> dict[str, tuple[tuple, np.dtype]]:
    """Each array's (shape, dtype) in an .npz archive, by name, no data read: every member checked
    as `read_npz` checks it, so a reader of the file after this allocates no more than it holds."""
    return _npz(path, what, expected, kinds, read=False, max_bytes=max_bytes)


def read_npz(path: Path, what: str, expected: str, kinds: str = "iufUS",
             max_bytes: int = NPZ_MAX_BYTES) -> dict[str, np.ndarray]:
    """The arrays of an .npz archive, by name. A member that is no .npy array, claims more data than
    it holds, or holds values of a kind not in `kinds` (objects never: numpy stores them as a
    pickle), members that unpack to more than `max_bytes` together, and an archive that is no zip or
    is damaged, are a VPRBenchError naming the file, `what` it is and what was `expected`. OSError
    (missing file, permissions) is left to the caller."""
    return _npz(path, what, expected, kinds, read=True, max_bytes=max_bytes)


def _npz(path: Path, what: str, expected: str, kinds: str, read: bool, max_bytes: int) -> dict:
    try:
        return npz_members(path, kinds, read, max_bytes)
    except ValueError as error:
        raise VPRBenchError(f"Cannot read {what} {path}: {error}. Expected {expected}.") from None


def _beyond(members: list[zipfile.ZipInfo], max_bytes: int) -> tuple[zipfile.ZipInfo, str] | None:
    """The first member with which the sizes the zip directory gives exceed `max_bytes`, and why.
    Checked before any member is unpacked: a member unpacks to no more than its size (zipfile stops
    there) and its header may claim no more (`_sized_header`), so these sizes bound what is allocated."""
    unpacked = 0
    for info in members:
        unpacked += info.file_size
        if unpacked > max_bytes:
            size, together = format_bytes(info.file_size), format_bytes(unpacked)
            size += "" if together == size else f" ({together} with the members before it)"
            return info, (f"it unpacks to {size}, more than the {format_bytes(max_bytes)} such a file may "
                          "hold (a compression bomb, or not such a file)")
    return None


def npz_members(source, kinds: str = "iufUS", read: bool = True, max_bytes: int = NPZ_MAX_BYTES) -> dict:
    """The arrays (`read`) or their (shape, dtype) of an .npz archive at `source` (a path or a file
    object), by name; a ValueError saying why it is unreadable (see `read_npz`). OSError is left."""
    found, name = {}, None
    try:
        with zipfile.ZipFile(source) as archive:
            members = archive.infolist()
            beyond = _beyond(members, max_bytes)
            if beyond is not None:
                name = beyond[0].filename
                raise ValueError(beyond[1])
            for info in members:
                name = info.filename
                if not name.endswith(".npy"):
                    raise ValueError("it is no .npy array")
                with archive.open(info) as handle:
                    shape, dtype = _sized_header(handle, info.file_size)
                    if dtype.kind not in kinds:
                        raise ValueError(f"it holds {dtype} values" + (" (Python objects, which are never loaded)"
                                                                       if dtype.hasobject else ""))
                    if read:
                        handle.seek(0)
                        found[name[:-4]] = npy_format.read_array(handle, allow_pickle=False)
                    else:
                        found[name[:-4]] = shape, dtype
    # a zip's own failures too: a torn or forged archive (BadZipFile, zlib.error), an encrypted or
    # unknown compression (RuntimeError, NotImplementedError)
    except (zipfile.BadZipFile, zlib.error, RuntimeError, NotImplementedError, ValueError, TypeError, EOFError,
            OverflowError, MemoryError, struct.error) as error:
        raise ValueError(f"its member {name}: {error}" if name is not None else
                         f"it is not a complete .npz archive ({error})") from None
    return found
