"""`vprbench datasets download` run twice at once into one data root, and killed -9 while a file
streams in: real processes fetching the real Corridor files from a local HTTP server (pooch, sha256
checks and all, without the internet)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stalling_server import serving
from vprbench.datasets.download import read_registry

#: `vprbench ARGS...` with Corridor's source at the local server; with a meeting folder, each process
#: that has fetched its first file waits (2 s at most) for the other to be fetching too, so two
#: downloads that do not take turns overlap for certain
CHILD = """
import dataclasses, sys, time
from pathlib import Path
import pooch
from vprbench.datasets import manifest as manifests
from vprbench.cli.main import main

port, meeting, me, other = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
real = manifests.dataset_manifests()
local = {**real["corridor"].download, "base_url": f"http://127.0.0.1:{port}/"}
served = {**real, "corridor": dataclasses.replace(real["corridor"], download=local)}
manifests.dataset_manifests = lambda: served
if meeting != "-":
    fetch, fetched = pooch.Pooch.fetch, []

    def met(self, *args, **kwargs):
        found = fetch(self, *args, **kwargs)
        if not fetched:
            (Path(meeting) / me).touch()
            deadline = time.time() + 2
            while not (Path(meeting) / other).exists() and time.time() < deadline:
                time.sleep(0.01)
        fetched.append(found)
        return found

    pooch.Pooch.fetch = met
sys.exit(main(sys.argv[5:]))
"""

STALLED = "query/0000005.jpg"


@pytest.fixture
def served(shared_data):
    with serving(shared_data / "corridor", stalled=STALLED) as server:
        yield server



def start(port: int, data: Path, meeting: str = "-", me: str = "-", other: str = "-") -> subprocess.Popen:
    command = [sys.executable, "-c", CHILD, str(port), meeting, me, other, "datasets", "download", "corridor",
               "--data-dir", str(data)]
    return subprocess.Popen(command, env={**os.environ, "VPRBENCH_CACHE": str(data.parent / "cache")}, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def assert_whole(root: Path) -> None:
    """Exactly the files of Corridor's registry, each with its sha256."""
    from vprbench.fsutil import file_sha256

    registry = read_registry("corridor.sha256")
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()) == sorted(registry)
    assert all(file_sha256(root / name) == sha for name, sha in registry.items())


def test_two_downloads_at_once_take_turns_and_keep_one_whole_copy(served, tmp_path):
    """Was: both fetched into corridor.partial; the first renamed it to corridor while the second still
    wrote there, so the second failed ('No such file or directory ... Check the network'), or removed the
    first's whole copy and renamed its own few files in its place (a broken dataset kept for good)."""
    data, meeting = tmp_path / "data", tmp_path / "meeting"
    meeting.mkdir()
    runs = [start(served.port, data, str(meeting), me, other) for me, other in (("a", "b"), ("b", "a"))]
    outputs = [run.communicate(timeout=120) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], outputs
    assert all("Traceback" not in err for _, err in outputs), outputs
    assert sum("waiting for the download of 'corridor'" in err for _, err in outputs) == 1, outputs
    assert all("111 database and 111 query images" in out for out, _ in outputs), outputs
    assert_whole(data / "corridor")
    assert not (data / "corridor.partial").exists()


def test_a_download_killed_while_a_file_streams_in_leaves_nothing_in_the_dataset(served, tmp_path):
    """kill -9 while pooch streams a file into its tmp* file beside it. Was: the rerun renamed that
    half-written temporary into the dataset folder, for good."""
    data = tmp_path / "data"
    served.stall.set()
    run = start(served.port, data)
    deadline = time.time() + 60
    while not any((data / "corridor.partial" / "query").glob("tmp*")) and time.time() < deadline:
        time.sleep(0.02)
    run.send_signal(signal.SIGKILL)
    run.communicate(timeout=30)
    assert any((data / "corridor.partial" / "query").glob("tmp*"))  # what the kill left
    served.stall.clear()
    rerun = start(served.port, data)
    out, err = rerun.communicate(timeout=120)
    assert rerun.returncode == 0 and "Traceback" not in err, err
    assert_whole(data / "corridor")
