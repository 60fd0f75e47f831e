"""The one describe loop: DataLoader workers, input order, batch independence, clear errors."""
from pathlib import Path

import numpy as np
import pytest

import vprbench
from vprbench.cli.main import main
from vprbench.errors import VPRBenchError
from vprbench.loader import describe_batches, resolve_device
from vprbench.methods import l2_normalise


def collect(method, paths, workers):
    return np.concatenate([rows for _, rows in describe_batches(method, paths, workers=workers)])


@pytest.fixture
def corridor_images(shared_data):
    root = shared_data / "corridor"
    return sorted((root / "ref").glob("*.jpg"))[:23] + sorted((root / "query").glob("*.jpg"))[:14]


@pytest.mark.parametrize("name,options", [("hog", {"resize": (64, 64)}), ("thumb-test", {})])
def test_descriptors_identical_for_any_workers_and_batch_size(corridor_images, name, options):
    reference = vprbench.create_method(name, **options)
    reference.batch_size = 1
    expected = collect(reference, corridor_images, workers=0)
    for workers, batch in ((0, 7), (2, 5), (2, 37)):
        method = vprbench.create_method(name, **options)
        method.batch_size = batch
        np.testing.assert_array_equal(collect(method, corridor_images, workers), expected)


class PathsOnly(vprbench.Method):
    """An older plugin: no load(), describe() reads the paths itself."""

    batch_size = 4

    def __init__(self, device="cpu"):
        pass

    def describe(self, images):
        assert all(hasattr(p, "suffix") for p in images)
        return l2_normalise(np.stack([[len(p.name), p.stat().st_size, 1.0] for p in images]))


def test_plugin_that_only_describes_paths_keeps_working(corridor_images, scratch_methods):
    vprbench.register_method("paths-only-test", PathsOnly)
    method = vprbench.create_method("paths-only-test")
    rows = collect(method, corridor_images, workers=2)
    first = corridor_images[0]
    assert rows.shape == (37, 3)
    np.testing.assert_allclose(rows[0], l2_normalise(np.array([len(first.name), first.stat().st_size, 1.0])))


def test_unreadable_image_in_a_worker_is_one_clear_error(corridor_images, tmp_path):
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"not a jpeg")
    method = vprbench.create_method("hog", resize=(64, 64))
    with pytest.raises(VPRBenchError, match="Cannot read image .*broken.jpg") as caught:
        collect(method, corridor_images[:5] + [broken], workers=2)
    assert "Traceback" not in str(caught.value)


def test_batch_sizes_below_one_are_refused(corridor_images, capsys):
    method = vprbench.create_method("thumb-test")
    for bad in (0, -3):
        method.batch_size = bad
        with pytest.raises(VPRBenchError, match="batch size must be a whole number >= 1"):
            collect(method, corridor_images, workers=0)
    assert main(["evaluate", "--method", "anyloc", "--batch-size", "0", "--dataset", "corridor"]) == 1
    assert "option batch_size takes a whole number >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_code:
        main(["evaluate", "--method", "hog", "--workers", "-1", "--dataset", "corridor"])
    assert exit_code.value.code == 2 and "--workers: must be >= 0, got -1" in capsys.readouterr().err


def test_device_auto_is_cuda_only_where_there_is_one():
    import torch

    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == "cpu"


def test_method_is_checked_before_any_dataset_is_touched(tmp_path, capsys):
    missing = tmp_path / "no-such-data"
    assert main(["evaluate", "--method", "hogg", "--dataset", "pitts30k", "--data-dir", str(missing)]) == 1
    assert "Unknown method 'hogg'" in capsys.readouterr().err
    assert main(["evaluate", "--method", "hog", "-o", "colour=3", "--dataset", "pitts30k", "--data-dir", str(missing)]) == 1
    assert "does not take option(s) colour" in capsys.readouterr().err
    assert not missing.exists()


ORPHAN_RUN = """
import sys, time
from pathlib import Path
from pathlib import Path

import numpy as np
import vprbench
from vprbench.loader import describe_batches

class Slow(vprbench.Method):
    batch_size = 1
    def fingerprint(self):
        return {}
    def load(self, path):  # batches bigger than a pipe's buffer: a worker blocks handing them over
        return np.zeros((3, 480, 640), np.float32)
    def describe(self, items):
        time.sleep(1)
        return np.full((len(items), 4), 0.5, np.float32)

print("started", flush=True)
for _ in describe_batches(Slow(), sorted(Path(sys.argv[1]).glob("*.jpg")), workers=2):
    pass
"""


def test_loader_workers_leave_when_their_run_is_killed(shared_data, tmp_path):
    """kill -9 of a run must not leave its loader workers behind for good (torch's own check never
    runs while a worker waits to hand over a batch)."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "run.py"
    script.write_text(ORPHAN_RUN)
    run = subprocess.Popen([sys.executable, str(script), str(shared_data / "corridor" / "ref")],
                           stdout=subprocess.PIPE, text=True)
    try:
        assert run.stdout.readline().strip() == "started"

        def workers():
            found = []
            for stat in Path("/proc").glob("[0-9]*/stat"):
                try:
                    if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == run.pid:
                        found.append(int(stat.parent.name))
                except (OSError, ValueError, IndexError):
                    pass
            return found

        def running(pid):  # not gone, nor a zombie
            try:
                return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
            except OSError:
                return False

        deadline = time.monotonic() + 20
        while len(workers()) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        children = workers()
        assert len(children) == 2
        time.sleep(3)  # their prefetched batches are waiting in the pipe
        run.send_signal(signal.SIGKILL)
        run.wait()
        deadline = time.monotonic() + 10
        alive = children
        while alive and time.monotonic() < deadline:
            time.sleep(0.5)
            alive = [pid for pid in children if running(pid)]
        for pid in alive:  # leave nothing behind, whatever the outcome
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        assert alive == [], "loader workers outlived their killed run"
    finally:  # nothing left behind if the test fails early
        run.kill()
        run.wait()
        run.stdout.close()


def test_loader_workers_leave_a_killed_run_under_forkserver(shared_data, tmp_path):
    """Under forkserver a worker's parent is the fork server, which outlives the killed run: the
    worker watches the run itself."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "run.py"  # the guard: forkserver imports the script in its server
    script.write_text(ORPHAN_RUN.replace('print("started"', 'if __name__ == "__main__":\n'
                                         '    import multiprocessing; multiprocessing.set_start_method("forkserver")\n'
                                         '    print("started"').replace("\nfor _ in", "\n    for _ in")
                      .replace("\n    pass\n", "\n        pass\n"))
    run = subprocess.Popen([sys.executable, str(script), str(shared_data / "corridor" / "ref")],
                           stdout=subprocess.PIPE, text=True)

    def below(pid):  # every descendant of pid
        children = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with contextlib.suppress(OSError, ValueError, IndexError):
                if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    children.append(int(stat.parent.name))
        return children + [d for c in children for d in below(c)]

    def running(pid):
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    found = []
    try:
        assert run.stdout.readline().strip() == "started"
        deadline = time.monotonic() + 30
        while len(found) < 4 and time.monotonic() < deadline:  # fork server, resource tracker, 2 workers
            time.sleep(0.2)
            found = below(run.pid)
        assert len(found) >= 4
        time.sleep(3)
        run.send_signal(signal.SIGKILL)
        run.wait()
        deadline, alive = time.monotonic() + 10, found
        while alive and time.monotonic() < deadline:
            time.sleep(0.5)
            alive = [pid for pid in found if running(pid)]
        assert alive == [], "loader workers (and their fork server) outlived their killed run"
    finally:
        for pid in found:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        run.kill()
        run.wait()
        run.stdout.close()
