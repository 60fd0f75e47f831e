"""A local HTTP server of a folder's files that can stall a file halfway: a download caught mid-file."""
from __future__ import annotations

import contextlib
import functools
import http.server
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Serving:
    port: int
    #: while set, the stalled file sends its first half, then nothing until it is cleared
    stall: threading.Event


class _Server(http.server.ThreadingHTTPServer):
    def handle_error(self, request, client_address):
        pass  # a client killed mid-file (the point of such a test) is no server error to print


@contextlib.contextmanager
def serving(folder: Path, stalled: str | None = None) -> Iterator[Serving]:
    """The files of `folder` on a free port of 127.0.0.1; `stalled` is the file that stalls (None: any)."""
    stall = threading.Event()

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if not stall.is_set() or stalled not in (None, self.path.lstrip("/")):
                return super().do_GET()
            body = Path(self.translate_path(self.path)).read_bytes()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            while stall.is_set():
                time.sleep(0.05)
            self.close_connection = True

    server = _Server(("127.0.0.1", 0), functools.partial(Handler, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield Serving(server.server_port, stall)
    finally:
        stall.clear()
        server.shutdown()
