"""A cache file replaced by a named pipe, or by a link to a device: a read of it hung (a pipe waits for a
writer that never comes) or never ended (/dev/zero). `pipe_at` makes one; `no_hang` ends a test that hangs."""
from __future__ import annotations

import os
import signal
from contextlib import contextmanager
from pathlib import Path


def pipe_at(path: Path, kind: str = "pipe") -> Path:
    """`path` (its file removed) as a named pipe, or as a link to /dev/zero (kind "zero")."""
    path.unlink(missing_ok=True)
    if kind == "pipe":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")
    return path


class Hung(BaseException):
    """A block that hung (a BaseException: a command's own error handling lets it through)."""


@contextmanager
def no_hang(seconds: int = 20):
    """Fails the block (Hung) when it runs longer than `seconds`: a read of a pipe would otherwise hang pytest."""
    def hung(signum, frame):
        raise Hung(f"still running after {seconds} s: a read of a pipe or device never ended")

    before = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)
