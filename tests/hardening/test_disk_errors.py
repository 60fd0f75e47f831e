"""Operating-system errors become one line naming the path and what to do, exit 1, no traceback.

The disks are real: a read-only cache is a read-only mount (tmpfs or a read-only bind of a
filled cache), a full disk a small tmpfs (we run as root, so permissions alone would not
stop a write). Skipped where mounting is not permitted.
"""
from __future__ import annotations

import json
import re
import os
import shutil
import subprocess
import sys
import threading

import pytest

from vprbench.errors import os_error_message
from vprbench.paths import cache_root

from hostile_files import assert_refused


def mount(*args) -> None:
    done = subprocess.run(["mount", *map(str, args)], capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"cannot mount here ({done.stderr.strip() or done.returncode}); needs root with mount rights")


@pytest.fixture
def mounts():
    """mounts(*mount args) mounts now and unmounts after the test (latest first)."""
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting needs root and the mount command")
    made = []

    def make(*args, target):
        target.mkdir(parents=True, exist_ok=True)
        mount(*args, target)
        made.append(target)
        return target

    yield make
    for target in reversed(made):
        subprocess.run(["umount", "-l", str(target)], check=False)


def evaluate(shared_data, cache) -> list:
    return ["evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", shared_data,
            "--cache-dir", cache, "--json"]


def test_read_only_cache_cold(mounts, tmp_path, shared_data, cli):
    cache = mounts("-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", target=tmp_path / "ro") / "cache"
    code, out, err = cli(*evaluate(shared_data, cache))
    assert_refused(code, err, None, f"Cannot use {cache}: Read-only file system; point --cache-dir at a folder on a writable disk.")


def test_read_only_cache_warm_still_shows_the_result(mounts, tmp_path, shared_data, cli):
    warm = tmp_path / "warm"
    code, out, _ = cli(*evaluate(shared_data, warm))
    first = json.loads(out)
    assert code == 0
    frozen = mounts("--bind", warm, target=tmp_path / "frozen")
    mount("-o", "remount,ro,bind", frozen)
    code, out, err = cli(*evaluate(shared_data, frozen))
    again = json.loads(out)  # computed from the stores and shown, although it cannot be saved
    assert again["recall"] == first["recall"] and again["descriptors_computed"] == {"database": 0, "queries": 0}
    assert code == 1 and "Traceback" not in err
    folder = frozen / "results" / again["protocol"]["hash"] / again["row_key"]  # the run's identity folder
    assert err.strip() == (f"error: Cannot use {folder}: Read-only file system; "
                           "point --cache-dir at a folder on a writable disk. The result was not stored.")


@pytest.mark.parametrize("args, flag", [
    (["describe", "--method", "hog", "IMAGE", "--out", "OUT/d.npy"], "--out"),
    (["candidates", "export", "--method", "hog", "--dataset", "corridor", "--out", "OUT/c.h5"], "--out"),
    (["vocabulary", "fit", "--method", "anyloc", "--backbone", "dinov2_vits14", "--weights", "random", "--layer", "0",
      "--clusters", "4", "--budget", "2000", "--dataset", "corridor", "--output", "OUT/v.pt"], "--output"),
])
def test_an_output_on_a_read_only_disk_is_refused_before_any_work(args, flag, mounts, tmp_path, shared_data, cli):
    """Was: the whole description (or export, or fit) ran, then writing the file failed."""
    read_only = mounts("-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", target=tmp_path / "ro")
    image = shared_data / "corridor" / "query" / "0000000.jpg"
    code, _, err = cli(*[str(image) if a == "IMAGE" else a.replace("OUT", str(read_only)) for a in args],
                       *(["--data-dir", shared_data] if "--dataset" in args else []))
    out = read_only / args[-1].removeprefix("OUT/")
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"argument {flag}: Cannot use {out}: Read-only file system; use a folder on a writable disk" in err
    assert not cache_root().exists(), "the output is checked before anything is cached"


@pytest.fixture
def full_disk(mounts, tmp_path):
    """A 256 KiB tmpfs filled to the last byte."""
    disk = mounts("-t", "tmpfs", "-o", "size=256k", "tmpfs", target=tmp_path / "full")
    with open(disk / "filler", "wb", buffering=0) as filler:
        try:
            while filler.write(b"\0" * 512):
                pass
        except OSError:  # ENOSPC: full
            pass
    return disk


def test_full_disk_when_registering_a_dataset(full_disk, shared_data, cli):
    code, _, err = cli("datasets", "import", "corridor", shared_data / "corridor", "--data-dir", full_disk)
    assert code == 1 and "Traceback" not in err
    assert "No space left on device; free some space, or point --data-dir at a folder on another disk" in err
    assert str(full_disk) in err
    # no half-written registry left behind (only the registry's empty lock file)
    assert sorted(p.name for p in full_disk.iterdir()) in (["filler"], ["datasets.json.lock", "filler"])


def test_full_disk_when_writing_descriptors(full_disk, shared_data, cli):
    images = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:60]
    out = full_disk / "descriptors.npy"
    code, _, err = cli("describe", "--method", "hog", *images, "--out", out)
    # describe goes through the stores (in the cache, on another disk): they are complete and kept
    assert_refused(code, err, None, f"Cannot use {out}: No space left on device; free some space", stores_allowed=True)


def test_lock_timeout_names_the_lock(tmp_path, shared_data, cli, monkeypatch):
    filelock = pytest.importorskip("filelock")
    path = tmp_path / "stores.lock"
    holder = filelock.FileLock(path)
    holder.acquire()
    try:
        def waits(*args, **kwargs):
            with filelock.FileLock(path, timeout=0.05):
                pass

        monkeypatch.setattr("vprbench.evaluation.evaluate", waits)
        code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data)
    finally:
        holder.release()
    assert_refused(code, err, None, f"Timed out waiting for the lock {path}: another vprbench process is working "
                                    "on the same files; wait for it to finish, then rerun.")


def test_hdf5_lock_error_names_the_file(tmp_path):
    """HDF5's lock error carries no file name; the message finds it all the same."""
    import h5py

    path = tmp_path / "database.partial.h5"
    h5py.File(path, "w").close()
    ready = tmp_path / "ready"
    holder = subprocess.Popen([sys.executable, "-c", "import h5py, pathlib, time\n"
                               f"f = h5py.File({str(path)!r}, 'a'); pathlib.Path({str(ready)!r}).touch(); time.sleep(30)"])
    try:
        for _ in range(200):
            if ready.exists():
                break
            threading.Event().wait(0.05)
        with pytest.raises(OSError) as caught:
            h5py.File(path, "a")
    finally:
        holder.kill()
        holder.wait()
    assert caught.value.filename is None  # what h5py gives
    assert os_error_message(caught.value) == (
        f"Cannot use {path}: Resource temporarily unavailable; another process holds it open "
        "(another vprbench run?): wait for it to finish, then rerun.")


@pytest.mark.parametrize("error, expected", [
    (PermissionError(13, "Permission denied", "/data/x"), "Cannot use /data/x: Permission denied; change its permissions, or use a folder this user may write to."),
    (IsADirectoryError(21, "Is a directory", "/data/gt.npy"), "Cannot use /data/gt.npy: Is a directory; it is a folder, not a file: check the path."),
    (OSError(5, "Input/output error"), "Cannot use a file (the system did not say which): Input/output error; check the disk."),
])
def test_message_for_errors_this_machine_cannot_cause(error, expected):
    """Root ignores permissions and the disks are healthy here: these are constructed errors."""
    assert os_error_message(error) == expected


def test_output_into_a_closed_pipe_ends_quietly():
    """`vprbench ... | head` closing early is no error worth a message."""
    process = subprocess.Popen([str(os.path.join(os.path.dirname(sys.executable), "vprbench")), "methods", "list", "--json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the reader is gone before anything is written
    _, err = process.communicate(timeout=120)
    assert process.returncode == 141 and err == b""


def test_full_disk_while_local_features_are_kept_keeps_what_was_written(mounts, tmp_path, shared_data, cli,
                                                                         monkeypatch):
    """hog + sift-ransac on corridor (190 images' SIFT) with the disk filling up part-way. Was: the
    features file, torn by the failed write, was discarded and the rerun computed all 190 again.
    Now what was written whole (segments of 8 images here) is kept; only the rest is computed."""
    import h5py

    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 8)

    def rerank(cache) -> list:
        return [*evaluate(shared_data, cache), "--quiet", "--k", 1, 5, "--rerank", "sift-ransac", "--rerank-k", 5,
                "--rerank-option", "max_features=200", "--inline-arrays"]

    code, out, err = cli(*rerank(tmp_path / "whole"))
    assert code == 0, err
    whole = json.loads(out)
    assert whole["stages"][0]["features_computed"] == 190
    cache = mounts("-t", "tmpfs", "-o", "size=4m", "tmpfs", target=tmp_path / "small") / "cache"
    assert cli(*evaluate(shared_data, cache))[0] == 0  # the descriptor stores: fit
    free = os.statvfs(cache).f_bavail * os.statvfs(cache).f_frsize
    with open(cache.parent / "filler", "wb") as filler:  # 1 MB left: about half of the 2.3 MB of features
        filler.write(b"\0" * (free - 2**20))
    code, _, err = cli(*rerank(cache))
    features = next(cache.glob("features/sift-*/corridor-*"))
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert re.fullmatch(
        f"error: Cannot use {re.escape(str(features))}/(database|queries)\\.\\d+\\.h5: No space left on device; "
        r"free some space, or point --cache-dir at a folder on another disk \(the local features written so far "
        r"are kept\)\.", err.strip()), err
    kept = set()
    for path in features.glob("*.h5"):
        with h5py.File(path, "r") as f:
            kept |= {(path.name.split(".")[0], row) for row in f["images"]}
    assert 40 <= len(kept) < 150
    (cache.parent / "filler").unlink()  # space freed: the rerun computes only the images not written
    code, out, err = cli(*rerank(cache))
    assert code == 0, err
    again = json.loads(out)
    assert again["stages"][0]["features_computed"] == 190 - len(kept)
    assert again["recall"] == whole["recall"] and again["top_predictions"] == whole["top_predictions"]
    assert again["per_query"] == whole["per_query"]


def test_a_full_disk_says_what_the_failed_command_keeps(cli, shared_data, tmp_path, monkeypatch):
    """evaluate keeps its finished descriptors; `results export` and `vocabulary import` keep nothing
    partial. Was: every command said '(finished descriptors are kept)'."""
    import errno

    import torch

    from vprbench.aggregation import Vocabulary

    def full(*_):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    cache, bundle, centres = tmp_path / "cache", tmp_path / "runs.tar.gz", tmp_path / "mine.pt"
    Vocabulary(torch.randn(3, 384)).save(centres)
    run = ["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data, "--cache-dir", cache,
           "--resize", "64", "64", "--k", "1", "--quiet"]
    with monkeypatch.context() as patched:
        patched.setattr(os, "fsync", full)  # every atomic write flushes its file: the disk is full there
        code, _, err = cli(*run)
        assert code == 1 and re.fullmatch(
            f"error: Cannot use {re.escape(str(cache))}/stores/\\S+\\.h5: No space left on device; free some space, "
            r"or point --cache-dir at a folder on another disk \(finished descriptors are kept\)\.\n", err), err
    assert cli(*run)[0] == 0
    with monkeypatch.context() as patched:
        patched.setattr(os, "fsync", full)
        code, _, err = cli("results", "export", "--method", "hog", "--dataset", "corridor", "--to", bundle,
                           "--cache-dir", cache)
        assert (code, err) == (1, f"error: Cannot use {bundle}: No space left on device; free some space, or use a "
                                  "folder on another disk. No bundle was written.\n")
        code, _, err = cli("vocabulary", "import", centres, "--source", "urban", "--backbone", "dinov2_vits14",
                           "--layer", "9", "--facet", "key", "--cache-dir", cache)
        stored = cache / "vocabularies" / "dinov2_vits14-l9-key-c3" / "urban" / "vocabulary.pt"
        assert (code, err) == (1, f"error: Cannot use {stored}: No space left on device; free some space, or point "
                                  "--cache-dir at a folder on another disk.\n")
