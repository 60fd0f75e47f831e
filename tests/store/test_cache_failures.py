"""Full disks, read-only caches and held locks: one clear error, nothing half-written read as complete."""
import json
import os
import resource
import subprocess
import sys
import time

import pytest

import vprbench
from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from runs import evaluate_method as evaluate
from vprbench.fsutil import CacheError, LockTimeout
from vprbench.store import StoreFolder, method_fingerprint


def test_full_disk_is_one_clear_error_and_the_rerun_completes(shared_data, tmp_path, capsys):
    cache = tmp_path / "cache"
    args = ["evaluate", "--method", "hog", "--resize", "64", "64", "--dataset", "corridor",
            "--data-dir", str(shared_data), "--cache-dir", str(cache), "--json"]

    def small_disk():  # every file this process writes stops at 64 KB; a store needs ~200 KB
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))

    full = subprocess.run([sys.executable, "-m", "vprbench", *args], capture_output=True, text=True,
                          preexec_fn=small_disk, timeout=300)
    assert full.returncode == 1, full.stderr
    message = "".join(full.stderr.split())  # the terminal wraps long paths
    assert "error:Cannotuse" in message and "database.rank0-of-1.partial.h5:Filetoolarge" in message
    assert "Traceback" not in full.stderr
    assert not [p for p in cache.rglob("*.h5") if not p.name.endswith(".partial.h5")]  # nothing complete
    assert not list(cache.rglob("*.tmp"))  # the half-created file went with the error

    assert main(args) == 0  # with room again: computed in full, correct
    record = json.loads(capsys.readouterr().out)
    assert record["descriptors_computed"] == {"database": 111, "queries": 111}


def test_disk_filling_up_between_splits_keeps_the_finished_split(shared_data, tmp_path, capsys):
    """A real small disk (a 400 KB tmpfs; needs permission to mount, so root only): the database
    store fits, the queries store does not. One clear error; with room again only the queries
    are described."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("no permission to mount a small tmpfs")
    try:
        args = ["evaluate", "--method", "hog", "--resize", "64", "64", "--dataset", "corridor",
                "--data-dir", str(shared_data), "--cache-dir", str(disk), "--json"]
        assert main(args) == 1
        message = "".join(capsys.readouterr().err.split())  # the terminal wraps long paths
        assert "queries.rank0-of-1.partial.h5:Nospaceleftondevice;freesomespace" in message
        subprocess.run(["mount", "-o", "remount,size=2m", str(disk)], check=True)
        assert main(args) == 0
        assert json.loads(capsys.readouterr().out)["descriptors_computed"] == {"database": 0, "queries": 111}
    finally:
        subprocess.run(["umount", str(disk)], check=True)


@pytest.fixture
def read_only(tmp_path):
    """read_only(folder) -> the same folder, unwritable: chmod for users, a read-only bind mount for root."""
    undo = []

    def make(folder):
        if os.geteuid() != 0:
            for path in [folder, *folder.rglob("*")]:
                path.chmod(path.stat().st_mode & ~0o222)
                undo.append(lambda path=path: path.chmod(path.stat().st_mode | 0o200))
            return folder
        view = tmp_path / f"read-only-{len(undo)}"
        view.mkdir()
        for command in (["mount", "--bind", str(folder), str(view)], ["mount", "-o", "remount,ro,bind", str(view)]):
            if subprocess.run(command, capture_output=True).returncode != 0:
                pytest.skip("running as root without permission to make a read-only bind mount")
        undo.append(lambda: subprocess.run(["umount", str(view)], check=True))
        return view

    yield make
    for step in reversed(undo):
        step()


def test_read_only_cache_serves_complete_stores_and_refuses_to_write(shared_data, tmp_path, read_only):
    dataset = load_dataset("corridor", shared_data)
    cold = evaluate(vprbench.create_method("fitted-test"), dataset, cache_dir=tmp_path / "warm")
    view = read_only(tmp_path / "warm")
    warm = evaluate(vprbench.create_method("fitted-test"), dataset, cache_dir=view)
    assert warm["descriptors_computed"] == {"database": 0, "queries": 0} and warm["recall"] == cold["recall"]

    (tmp_path / "cold").mkdir()
    empty = read_only(tmp_path / "cold")
    with pytest.raises(CacheError, match=rf"Cannot use {empty}.*: (Read-only file system|Permission denied); "):
        evaluate(vprbench.create_method("fitted-test"), load_dataset("corridor", shared_data), cache_dir=empty)
    assert not list(empty.rglob("*"))


def test_a_held_store_lock_is_waited_for_and_named(shared_data, tmp_path, capfd):
    dataset = load_dataset("corridor", shared_data)
    method = vprbench.create_method("thumb-test")
    method.use_dataset("corridor")
    folder = StoreFolder(method.name, method_fingerprint(method), "corridor", dataset.images_fingerprint(tmp_path), tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom vprbench.fsutil import lock\n"
        f"with lock({str(folder.paths['database'] / '.lock')!r}):\n    print('held', flush=True)\n    time.sleep(60)\n")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        started = time.monotonic()
        with pytest.raises(LockTimeout, match=rf"Timed out after 1 s waiting for descriptor store .* held by pid {holder.pid} on "):
            evaluate(method, dataset, cache_dir=tmp_path, lock_timeout=1)
        assert time.monotonic() - started < 30
        assert f"waiting for descriptor store {folder.paths['database']}: locked by pid {holder.pid}" in capfd.readouterr().err
    finally:
        holder.kill()
        holder.wait()
    record = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path, lock_timeout=5)  # released by its death
    assert record["descriptors_computed"] == {"database": 111, "queries": 111}
