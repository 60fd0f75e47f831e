"""The descriptor store: warm runs compute nothing, killed runs resume, partial files are never complete."""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.evaluation import evaluate
from vprbench.images import load_image
from vprbench.store import DescriptorStore

# describes images as 8x8 grey thumbnails; logs what it described; can SIGKILL itself mid-run
SCRIPT = textwrap.dedent('''
    import os, signal, sys
    import numpy as np
    import vprbench
    from vprbench.datasets import load_dataset
    from vprbench.evaluation import evaluate
    from vprbench.images import load_image

    class Logged(vprbench.Method):
        batch_size = 10
        def __init__(self, device="cpu"):
            self.calls = 0
        def describe(self, images):
            self.calls += 1
            if self.calls == int(os.environ.get("KILL_AT_BATCH", 0)):
                os.kill(os.getpid(), signal.SIGKILL)
            with open(os.environ["LOG"], "a") as log:
                log.writelines(f"{p.name}\\n" for p in images)
            rows = [np.asarray(load_image(p, "L").resize((8, 8)), np.float32).ravel() for p in images]
            return np.stack([r / np.linalg.norm(r) for r in rows])

    vprbench.register_method("logged", Logged)
    record = evaluate(vprbench.create_method("logged"), load_dataset("corridor", sys.argv[1]))
    print(record["recall"]["1"], record["descriptors_computed"]["database"], record["descriptors_computed"]["queries"])
''')


def run_script(tmp_path, shared_data, cache, kill_at=0):
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "VPRBENCH_CACHE": str(cache), "LOG": str(tmp_path / f"log-{cache.name}-{kill_at}.txt"),
           "KILL_AT_BATCH": str(kill_at)}
    return subprocess.run([sys.executable, str(script), str(shared_data)], env=env, capture_output=True, text=True)


def test_killed_extraction_resumes_where_it_stopped(tmp_path, shared_data):
    cache = tmp_path / "killed"
    killed = run_script(tmp_path, shared_data, cache, kill_at=4)
    assert killed.returncode == -9
    assert not list(cache.rglob("database.h5")), "a killed run must not leave a complete store"
    assert len(list(cache.rglob("database.partial.h5"))) == 1
    first_log = (tmp_path / "log-killed-4.txt").read_text().split()
    assert len(first_log) == 30  # three batches of ten finished before the kill

    resumed = run_script(tmp_path, shared_data, cache)
    assert resumed.returncode == 0, resumed.stderr
    r1, db_now, q_now = resumed.stdout.split()
    assert (int(db_now), int(q_now)) == (111 - 30, 111)
    resumed_log = (tmp_path / "log-killed-0.txt").read_text().split()
    assert not set(resumed_log[:81]) & set(first_log), "finished rows were described again"

    clean = run_script(tmp_path, shared_data, tmp_path / "clean")
    assert clean.stdout.split()[0] == r1
    stores = {run: sorted((tmp_path / run).rglob("database.h5"))[0] for run in ("killed", "clean")}
    import h5py

    with h5py.File(stores["killed"]) as a, h5py.File(stores["clean"]) as b:
        np.testing.assert_array_equal(a["descriptors"][...], b["descriptors"][...])


class Thumb(vprbench.Method):
    batch_size = 50

    def __init__(self, device="cpu"):
        self.described = 0

    def describe(self, images):
        self.described += len(images)
        rows = [np.asarray(load_image(p, "L").resize((8, 8)), np.float32).ravel() for p in images]
        return np.stack([r / np.linalg.norm(r) for r in rows])


def test_warm_store_computes_nothing(shared_data):
    vprbench.register_method("thumb-test", Thumb)
    dataset = load_dataset("corridor", shared_data)
    cold_method = vprbench.create_method("thumb-test")
    cold = evaluate(cold_method, dataset)
    warm_method = vprbench.create_method("thumb-test")
    warm = evaluate(warm_method, dataset)
    assert cold_method.described == 222 and warm_method.described == 0
    assert warm["descriptors_computed"] == {"database": 0, "queries": 0}
    assert warm["recall"] == cold["recall"]


def test_torn_partial_file_is_discarded(tmp_path):
    store = DescriptorStore(tmp_path / "s.h5", tmp_path / "s.partial.h5", ["a", "b"], {})
    store.partial_path.write_bytes(b"not an hdf5 file")
    with pytest.warns(UserWarning, match="Discarding"):
        handle, done = store.open_partial(4)
    assert done.tolist() == [False, False]
    store.write_rows(handle, [0, 1], np.ones((2, 4), np.float32))
    store.finish(handle)
    assert store.complete and store.read().shape == (2, 4)

