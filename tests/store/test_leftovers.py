"""What a writer killed after its store's rename left behind goes with the next run, though the
store is complete and served without the lock."""
import subprocess
import sys

import vprbench
from vprbench.datasets import load_dataset
from runs import evaluate_method as evaluate


HOLD = "import fcntl, sys, time; f = open(sys.argv[1], 'a'); fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)"


def _run(shared_data, cache):
    return evaluate(vprbench.create_method("thumb-test"), load_dataset("corridor", shared_data), cache_dir=cache)


def test_shards_and_temporaries_beside_a_complete_store_are_removed(shared_data, tmp_path):
    first = _run(shared_data, tmp_path)
    folder = next((tmp_path / "stores").glob("*/*-database-*"))
    store = (folder / "database.h5").read_bytes()
    # as rank 0 of 2 leaves them when killed between the merge's rename and the tidy
    left = [folder / "database.rank0-of-2.partial.h5", folder / "database.rank1-of-2.partial.h5",
            folder / ".database.h5.x1y2z3.tmp"]
    for path in left:
        path.write_bytes(store)
    other = folder / ".postprocess-0123.npz.abc.tmp"  # not the store's: written by others without the lock
    other.write_bytes(b"x")

    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder / ".lock")], stdout=subprocess.PIPE, text=True)
    try:  # another run holds the lock: that one tidies, this one neither waits nor touches them
        assert holder.stdout.readline() == "held\n"
        held = _run(shared_data, tmp_path)
        assert all(path.exists() for path in left)
    finally:
        holder.kill()
        holder.wait()

    again = _run(shared_data, tmp_path)
    assert [path.name for path in left if path.exists()] == []
    assert other.exists() and (folder / "database.h5").read_bytes() == store
    assert again["descriptors_computed"] == held["descriptors_computed"] == {"database": 0, "queries": 0}
    assert again["recall"] == first["recall"]
