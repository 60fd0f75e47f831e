"""Files in VPR-Bench's precomputed-matches format, written as Python 2 wrote them.

Python 3's pickle at protocol 2 writes bytes through `_codecs.encode` and texts as unicode;
Python 2 wrote both as its `str` (SHORT_BINSTRING / BINSTRING) and named numpy's modules
`numpy.core.multiarray`. `Python2Pickler` does exactly that, so the files here are what
VPR-Bench's Python 2 code saved with `np.save` (numpy needs `encoding='latin1'` to read them).
"""
from __future__ import annotations

import io
import pickle
import struct
from pathlib import Path

import numpy as np

FILE = "precomputed_data_corrected.npy"


class Python2Pickler(pickle._Pickler):
    """Protocol 2 as Python 2 wrote it: byte strings and texts as `str`, numpy under its 1.x module names."""

    dispatch = dict(pickle._Pickler.dispatch)

    def __init__(self, file, hostile: bool = False):
        super().__init__(file, protocol=2)
        self.hostile = hostile  # let a gadget's callable (os.system) through, for the refusal tests

    def save_binstring(self, obj, data: bytes):
        if len(data) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(data)]) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(data)) + data)
        self.memoize(obj)

    def save_bytes(self, obj):
        self.save_binstring(obj, obj)

    def save_str(self, obj):
        self.save_binstring(obj, obj.encode("latin1"))

    dispatch[bytes] = save_bytes
    dispatch[str] = save_str

    def save_global(self, obj, name=None):
        name = name or obj.__name__
        module = "numpy.core.multiarray" if obj.__module__.endswith("multiarray") else obj.__module__
        if module not in ("numpy", "numpy.core.multiarray") and not self.hostile:
            raise pickle.PicklingError(f"{module}.{name} is not in VPR-Bench's files")
        self.write(pickle.GLOBAL + f"{module}\n{name}\n".encode())
        self.memoize(obj)


def python2_pickle(value, hostile: bool = False) -> bytes:
    body = io.BytesIO()
    Python2Pickler(body, hostile).dump(value)
    return body.getvalue()


def python2_npy(path: Path, array: np.ndarray, hostile: bool = False) -> Path:
    """`np.save(path, array)` as Python 2's numpy wrote an object array."""
    body = python2_pickle(array, hostile)
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "|O", "fortran_order": False, "shape": array.shape})
        handle.write(body)
    return path


def precomputed(similarity: np.ndarray, *, order=None, encoding_s=0.0123, matching_s=0.0045) -> np.ndarray:
    """The 6-part object array VPR-Bench saves, from a query x database similarity matrix."""
    similarity = np.asarray(similarity, dtype=np.float64)
    queries = np.arange(len(similarity), dtype=np.int64) if order is None else np.asarray(order, dtype=np.int64)
    rows = similarity[queries]
    matched = rows.argmax(axis=1).astype(np.int64)
    parts = np.empty(6, dtype=object)
    parts[0], parts[1], parts[2], parts[3] = queries, matched, rows[np.arange(len(rows)), matched], rows
    parts[4], parts[5] = float(encoding_s), float(matching_s)
    return parts


def write_method(root: Path, method: str, parts: np.ndarray) -> Path:
    folder = root / method
    folder.mkdir(parents=True, exist_ok=True)
    return python2_npy(folder / FILE, parts)


def thumbnail_similarity(query_images, database_images, size=(8, 6)) -> np.ndarray:
    """A real, trivial VPR method: cosine similarity of tiny normalised grey thumbnails."""
    from PIL import Image

    def describe(paths):
        rows = []
        for path in paths:
            pixels = np.asarray(Image.open(path).convert("L").resize(size), dtype=np.float64).ravel()
            pixels -= pixels.mean()
            rows.append(pixels / (np.linalg.norm(pixels) or 1.0))
        return np.stack(rows)

    return describe(query_images) @ describe(database_images).T
