"""The authors' released centres (`vprbench vocabulary download`, or a run naming them) fetched by a
real process killed -9 while the file streams in, then fetched again: the cache keeps the whole file
and nothing the kill left (pooch streams each file into a tmp* file beside it). The release is served
by a local HTTP server of the copy in the shared data."""
from __future__ import annotations

import functools
import http.server
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

#: fetch_released('urban') into a cache, the release's URL at the local server
CHILD = """
import sys
from vprbench.methods import anyloc_vocabulary
anyloc_vocabulary.released_url = lambda source: f"http://127.0.0.1:{sys.argv[1]}/c_centers.pt"
print(anyloc_vocabulary.fetch_released("urban", sys.argv[2]))
"""


class Handler(http.server.SimpleHTTPRequestHandler):
    """The file; while `stall` is set, its first half only, then nothing until it is cleared."""
    stall = threading.Event()

    def log_message(self, *args):
        pass

    def do_GET(self):
        if not self.stall.is_set():
            return super().do_GET()
        body = Path(self.translate_path(self.path)).read_bytes()
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body[: len(body) // 2])
        self.wfile.flush()
        while self.stall.is_set():
            time.sleep(0.05)
        self.close_connection = True


class Server(http.server.ThreadingHTTPServer):
    def handle_error(self, request, client_address):
        pass  # a client killed mid-file (the point of the test) is no server error to print


@pytest.fixture
def port(shared_data):
    folder = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban"
    server = Server(("127.0.0.1", 0), functools.partial(Handler, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server.server_port
    Handler.stall.clear()
    server.shutdown()


def test_a_released_vocabulary_download_killed_midway_leaves_nothing_behind(port, tmp_path, monkeypatch):
    """Was: the killed download's half-written tmp* file stayed beside c_centers.pt for good."""
    from vprbench.fsutil import file_sha256
    from vprbench.methods import anyloc_vocabulary
    from vprbench.methods.anyloc_vocabulary import release, released_path

    cache = tmp_path / "cache"
    folder = released_path("urban", cache).parent
    Handler.stall.set()
    killed = subprocess.Popen([sys.executable, "-c", CHILD, str(port), str(cache)], text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ))
    deadline = time.time() + 60
    while not (folder.is_dir() and any(folder.glob("tmp*"))) and time.time() < deadline:
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.communicate(timeout=30)
    assert any(folder.glob("tmp*")) and not released_path("urban", cache).exists()  # what the kill left
    Handler.stall.clear()
    monkeypatch.setattr(anyloc_vocabulary, "released_url", lambda source: f"http://127.0.0.1:{port}/c_centers.pt")
    assert anyloc_vocabulary.fetch_released("urban", cache) == released_path("urban", cache)
    assert file_sha256(released_path("urban", cache)) == release()["sha256"]["urban"]
    assert sorted(p.name for p in folder.iterdir() if not p.name.endswith(".lock")) == ["c_centers.pt"]
