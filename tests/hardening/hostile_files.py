"""The bad-input suite's tools: hostile pickles whose payload would leave a marker file behind,
and the one check that the CLI refused cleanly."""
from __future__ import annotations

import os
import pickle
import subprocess
from pathlib import Path

import numpy as np

from vprbench.evaluation import read_results
from vprbench.paths import cache_root


class Payload:
    """Unpickling this calls `call(*args)` (os.system, exec, subprocess.call...)."""

    def __init__(self, call, *args):
        self.call, self.args = call, args

    def __reduce__(self):
        return self.call, self.args


def gadget_pickles(marker: Path) -> dict[str, bytes]:
    """Pickles that create `marker` when unpickled (test_gadgets_are_real checks it), through
    every route a pickle can call code: REDUCE at protocols 0-5 (GLOBAL and STACK_GLOBAL),
    INST, OBJ, and callables other than os.system."""
    command = f"touch {marker}"
    raw = command.encode()
    return {
        "reduce-system-protocol2": pickle.dumps(Payload(os.system, command), protocol=2),
        "reduce-system-protocol5": pickle.dumps(Payload(os.system, command), protocol=5),
        "global-reduce-protocol0": b"cos\nsystem\n(V" + raw + b"\ntR.",
        "inst-protocol0": b"(V" + raw + b"\nios\nsystem\n.",
        "obj-protocol1": b"(cos\nsystem\nV" + raw + b"\no.",
        "exec-stack-global": pickle.dumps(Payload(exec, f"import os; os.system({command!r})"), protocol=4),
        "subprocess-call": pickle.dumps(Payload(subprocess.call, ["touch", str(marker)]), protocol=3),
    }


def npy_with_pickle(path: Path, payload: bytes, shape=(3, 2)) -> Path:
    """An .npy whose header announces an object array and whose body is `payload`."""
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "|O", "fortran_order": False, "shape": shape})
        handle.write(payload)
    return path


def rows_with_payload(marker: Path, n: int = 3) -> np.ndarray:
    """A VPR-Bench row array [index, [positives]] with the payload hidden in one row."""
    rows = np.empty((n, 2), dtype=object)
    for i in range(n):
        rows[i, 0], rows[i, 1] = i, [i]
    rows[n - 1, 1] = Payload(os.system, f"touch {marker}")
    return rows


def assert_refused(code: int, err: str, marker: Path | None, *fragments, stores_allowed: bool = False) -> None:
    """Exit 1, one clear message holding `fragments`, no traceback, the payload never ran,
    nothing stored (no descriptor store, no result)."""
    assert code == 1, err
    message = err.strip()  # (a progress bar that was running leaves an empty line)
    assert "Traceback" not in err and message.startswith("error: "), err
    assert "\n" not in message, f"one message on one line, got: {err}"
    for fragment in fragments:
        assert str(fragment) in err, err
    if marker is not None:
        assert not marker.exists(), "the payload ran"
    assert not read_results(), "a refused run recorded a result"
    if not stores_allowed:
        assert not list(cache_root().rglob("*.h5")), "a refused run wrote a descriptor store"


def tiny_images(folder: Path, names) -> None:
    """Small real images (8x8 grey JPEG/PNG) under the given names."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        Image.new("RGB", (8, 8), (90, 90, 90)).save(folder / name)


def oxford_copy(data_root: Path, database: list[str], queries: list[str]) -> Path:
    """<data_root>/Oxford_Robotcar: a NetVLAD dbStruct .mat (the release's 1x8 cell array) naming
    `database` and `queries` under oxDataPart/, which holds a.png and b.png."""
    from scipy.io import savemat

    root = data_root / "Oxford_Robotcar"
    tiny_images(root / "oxDataPart", ["a.png", "b.png"])
    cell = np.empty((1, 8), dtype=object)
    names = []
    for listed in (database, queries):
        column = np.empty((len(listed), 1), dtype=object)
        for i, name in enumerate(listed):
            column[i, 0] = name
        names.append(column)
    values = (names[0], np.zeros((len(database), 2)), names[1], np.zeros((len(queries), 2)), len(database),
              len(queries), 25, 625)
    for k, value in enumerate(values):
        cell[0, k] = value
    savemat(root / "oxdatapart.mat", {"dbStruct": cell})
    return root


def big_png(path: Path, width: int, height: int, bit_depth: int = 16) -> Path:
    """A valid grey PNG of width x height black pixels: a few hundred KB however large (zlib
    squeezes the zero rows about 1000:1)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row = bytes(1 + width * bit_depth // 8)  # filter byte 0, then the row's samples
    packer = zlib.compressobj(9)
    body = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    header = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", body) + chunk(b"IEND", b""))
    return path
