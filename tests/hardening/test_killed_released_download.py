"""The authors' released centres (`vprbench vocabulary download`, or a run naming them) fetched by a
real process killed -9 while the file streams in, then fetched again: the cache keeps the whole file
and nothing the kill left (pooch streams each file into a tmp* file beside it). The release is served
by a local HTTP server of the copy in the shared data."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from stalling_server import serving

#: fetch_released('urban') into a cache, the release's URL at the local server
CHILD = """
import sys
from vprbench.methods import anyloc_vocabulary
anyloc_vocabulary.released_url = lambda source: f"http://127.0.0.1:{sys.argv[1]}/c_centers.pt"
print(anyloc_vocabulary.fetch_released("urban", sys.argv[2]))
"""


@pytest.fixture
def served(shared_data):
    with serving(shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban") as server:
        yield server



def test_a_released_vocabulary_download_killed_midway_leaves_nothing_behind(served, tmp_path, monkeypatch):
    """Was: the killed download's half-written tmp* file stayed beside c_centers.pt for good."""
    from vprbench.fsutil import file_sha256
    from vprbench.methods import anyloc_vocabulary
    from vprbench.methods.anyloc_vocabulary import release, released_path

    cache = tmp_path / "cache"
    folder = released_path("urban", cache).parent
    served.stall.set()
    killed = subprocess.Popen([sys.executable, "-c", CHILD, str(served.port), str(cache)], text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ))
    deadline = time.time() + 60
    while not (folder.is_dir() and any(folder.glob("tmp*"))) and time.time() < deadline:
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.communicate(timeout=30)
    assert any(folder.glob("tmp*")) and not released_path("urban", cache).exists()  # what the kill left
    served.stall.clear()
    monkeypatch.setattr(anyloc_vocabulary, "released_url", lambda source: f"http://127.0.0.1:{served.port}/c_centers.pt")
    assert anyloc_vocabulary.fetch_released("urban", cache) == released_path("urban", cache)
    assert file_sha256(released_path("urban", cache)) == release()["sha256"]["urban"]
    assert sorted(p.name for p in folder.iterdir() if not p.name.endswith(".lock")) == ["c_centers.pt"]
