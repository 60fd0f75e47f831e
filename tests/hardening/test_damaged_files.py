"""Damaged files vprbench reads fail with one line naming them, or, for a cache file that is
only a cache, are set aside and rebuilt: an empty, text, truncated or crafted ground-truth .mat
(one of which crashes scipy's reader outright), a damaged image-hash memo, and empty or garbage
claim files of a sweep. Each test first shows the damage is real: the plain parser fails on it
with an exception (or a crash) that names nothing."""
from __future__ import annotations

import json
import re
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.io import loadmat, savemat

from vprbench.datasets.identity import MEMO_NAME
from vprbench.evaluation import read_results
from vprbench.evaluation.results import results_dir
from vprbench.paths import cache_root
from vprbench.sweep.plan import read_plan

from hostile_files import assert_refused, oxford_copy


# ---------------------------------------------------------------- ground-truth .mat
def crafted_mat(path: Path) -> None:
    """A 200-byte .mat whose numeric element claims data type 8 (none): scipy's v5 reader indexes
    its table of types with it unchecked and dereferences a null pointer."""
    savemat(path, {"dbStruct": np.array([1.0])})
    data = bytearray(path.read_bytes())
    data[data.rfind(bytes([9, 0, 0, 0, 8, 0, 0, 0]))] = 8  # miDOUBLE -> 8
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["empty", "text", "truncated", "crafted-crash"])
def test_damaged_ground_truth_mat_is_named(damage, tmp_path, cli):
    root = oxford_copy(tmp_path / "data", ["a.png"] * 40, ["b.png"] * 40)
    mat = root / "oxdatapart.mat"
    if damage == "empty":
        mat.write_bytes(b"")
    elif damage == "text":
        mat.write_text("dbStruct = {'a.png', [0 0]}\n")
    elif damage == "truncated":
        mat.write_bytes(mat.read_bytes()[:700])
    else:
        crafted_mat(mat)
    # the damage is real: scipy's reader fails on the file, naming nothing, or kills the process
    probe = subprocess.run([sys.executable, "-c", f"from scipy.io import loadmat; loadmat({str(mat)!r})"],
                           capture_output=True, text=True)
    if damage == "crafted-crash":
        assert probe.returncode == -signal.SIGSEGV, probe
    else:
        assert probe.returncode == 1 and "Traceback" in probe.stderr and "Error" in probe.stderr.splitlines()[-1]
    code, _, err = cli("datasets", "info", "oxford", "--data-dir", tmp_path / "data")
    assert_refused(code, err, None, f"Cannot read {mat}: ", "replace it (re-download the dataset)")
    if damage == "crafted-crash":
        assert "the MATLAB reader crashed on it (SIGSEGV)" in err


def test_mat_without_a_dbstruct_says_what_it_holds(tmp_path, cli):
    root = oxford_copy(tmp_path / "data", ["a.png"], ["b.png"])
    savemat(root / "oxdatapart.mat", {"positions": np.zeros((2, 2))})
    assert "dbStruct" not in loadmat(root / "oxdatapart.mat")
    code, _, err = cli("datasets", "info", "oxford", "--data-dir", tmp_path / "data")
    assert_refused(code, err, None, "it holds no variable 'dbStruct' (it holds ['positions'])")


# ---------------------------------------------------------------- the image-hash memo
HOG = ["evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", "corridor"]


def damage_pages(path: Path) -> None:
    """Overwrite every page of an SQLite file but the first (the header) with garbage."""
    data = bytearray(path.read_bytes())
    for start in range(4096, len(data), 4096):
        data[start:start + 64] = b"\xa5" * 64
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["not-a-database", "malformed-pages"])
def test_damaged_image_hash_memo_is_set_aside_and_rebuilt(damage, shared_data, cli):
    assert cli(*HOG, "--data-dir", shared_data)[0] == 0
    memo = cache_root() / MEMO_NAME
    (first,) = read_results()
    shutil.rmtree(results_dir())
    if damage == "not-a-database":
        memo.write_bytes(b"SQLite format 2\0" + os.urandom(3000))
    else:
        damage_pages(memo)
    with pytest.raises(sqlite3.DatabaseError):  # the damage is real: reading the hashes fails
        with sqlite3.connect(memo) as db:
            db.execute("SELECT * FROM hashes_v2").fetchall()
    with pytest.warns(UserWarning, match=rf"The image-hash memo {memo} is damaged \(.*\); it is set aside as "
                                         rf"{memo}.damaged and rebuilt"):
        code, _, err = cli(*HOG, "--data-dir", shared_data)
    assert code == 0 and "Traceback" not in err, err
    (second,) = read_results()
    assert second["dataset_fingerprints"] == first["dataset_fingerprints"] and second["recall"] == first["recall"]
    assert (cache_root() / (MEMO_NAME + ".damaged")).is_file()
    with sqlite3.connect(memo) as db:  # rebuilt: every image remembered again
        assert db.execute("PRAGMA quick_check").fetchone() == ("ok",)
        assert db.execute("SELECT count(*) FROM hashes_v2").fetchone() == (222,)


# ---------------------------------------------------------------- claim files of a sweep
@pytest.fixture
def plan(tmp_path) -> Path:
    path = tmp_path / "plan.toml"
    path.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')
    return path


def claim_file(plan: Path, suffix: str) -> Path:
    (cell,) = read_plan(plan).cells
    folder = cache_root() / "sweeps" / "claims"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{cell.key}{suffix}"


CLAIMS = {
    "empty-lease": (".lease", b""),
    "garbage-lease": (".lease", b"\x00\xff{not json"),
    "lease-without-token": (".lease", json.dumps({"worker": "host:1"}).encode()),
    "garbage-failed": (".failed", b"<<<<<<<"),
    "failed-with-a-text-time": (".failed", json.dumps({"worker": "host:1", "reason": "x", "time": "soon"}).encode()),
    "failed-as-a-list": (".failed", b"[1, 2, 3]"),
}


@pytest.mark.parametrize("case", list(CLAIMS))
def test_damaged_claim_files_are_set_aside(case, plan, shared_data, cli):
    suffix, content = CLAIMS[case]
    path = claim_file(plan, suffix)
    path.write_bytes(content)
    with pytest.raises((ValueError, KeyError, TypeError)):  # the damage is real: the plain reading fails
        data = json.loads(content)
        data["token"] if suffix == ".lease" else data["time"] >= 0.0  # noqa: B015
    with pytest.warns(UserWarning, match=rf"The claim file {path} cannot be read \(.+\); it is set aside as "
                                         rf"{path}.damaged and the cell is claimed anew"):
        code, out, err = cli("run", plan, "--data-dir", shared_data)
    assert code == 0 and "Traceback" not in err, err
    assert "1 ran" in out and len(read_results()) == 1
    assert path.with_name(path.name + ".damaged").read_bytes() == content and not path.exists()


def test_the_mat_readers_child_imports_nothing_from_the_working_folder(tmp_path, monkeypatch):
    """The child that reads a .mat ran `python -c`, which puts the working folder first on its import path:
    a `scipy` there (a dataset folder one works in) ran in it. Now it runs with -P."""
    from vprbench.datasets import load_dataset

    oxford_copy(tmp_path / "data", ["a.png"], ["b.png"])
    planted = tmp_path / "work" / "scipy"
    planted.mkdir(parents=True)
    (planted / "__init__.py").write_text(f"open({str(tmp_path / 'ran')!r}, 'w').close()\n")
    monkeypatch.chdir(tmp_path / "work")
    dataset = load_dataset("oxford", tmp_path / "data")
    assert (len(dataset.database), len(dataset.queries)) == (1, 1)
    assert not (tmp_path / "ran").exists(), "code in the working folder ran in the .mat reader's process"


# ---------------------------------------------------------------- descriptor store layout
def _relaid(f, **dataset) -> None:
    """Replace the store's descriptors by `dataset`, each row's checksum recomputed to match."""
    import zlib

    del f["descriptors"]
    f.create_dataset("descriptors", **dataset)
    if "data" in dataset:
        rows = np.ascontiguousarray(dataset["data"])
        del f["checksums"]
        f.create_dataset("checksums", data=np.array([zlib.crc32(row) for row in rows], dtype=np.uint32))


LAYOUTS = {
    # a header claiming 2**40 columns (chunked, nothing allocated): read as a 4 TiB row
    "huge-width": lambda f, n, rows: _relaid(f, shape=(n, 2**40), dtype="f4", chunks=(1, 1024)),
    # text where rows belong: HDF5 cannot convert it, and its error names no file
    "text": lambda f, n, rows: _relaid(f, data=np.array([b"x"] * n, dtype="S1").reshape(n, 1)),
    # no column at all: the run blamed the method for describing in 0 dimensions
    "no-columns": lambda f, n, rows: _relaid(f, data=np.zeros((n, 0), np.float32)),
    # fewer columns than the method wrote: was "Method 'hog' described the database in 10 and the queries in ..."
    "fewer-columns": lambda f, n, rows: _relaid(f, data=np.ascontiguousarray(rows[:, :10])),
    # rows read from another file on the machine
    "external": lambda f, n, rows: _relaid(f, shape=rows.shape, dtype="f4", external=[("/etc/hostname", 0, 2**20)]),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_store_not_laid_out_as_vprbench_writes_it_is_recomputed(layout, corridor_copy, cli):
    """The store's header is trusted for no width, type or place vprbench never writes: such a
    store is discarded (named) and recomputed, not read as a huge row, text or another file."""
    import h5py

    command = ["evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", corridor_copy.parent]
    assert cli(*command)[0] == 0
    first = read_results()[0]["recall"]
    shutil.rmtree(results_dir())
    store = next(cache_root().rglob("database.h5"))
    with h5py.File(store, "r+") as f:
        rows = f["descriptors"][...]
        LAYOUTS[layout](f, len(rows), rows)
    with pytest.warns(UserWarning, match=rf"Discarding {re.escape(str(store))}: its descriptors .*; it is recomputed"):
        code, _, err = cli(*command)
    assert code == 0 and "Traceback" not in err, err
    assert read_results()[0]["recall"] == first
