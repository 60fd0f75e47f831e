"""Cells shared by several processes on one cache: each claimed with a lease, evaluated once.

<cache>/sweeps/claims/<cell>.lease names the process working on a cell; a heartbeat thread
refreshes its modification time. A lease older than `lease_s` belonged to a process that
died: another process takes the cell over (the descriptor store resumes its partial rows).
Claiming, taking over and releasing happen under a per-cell file lock (filelock), so two
processes never both hold a cell.
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from pathlib import Path

from ..fsutil import LockTimeout, atomic_write, lock
from ..paths import cache_root


def _lock(path: Path):
    # held for moments: no "waiting for" line each time two processes meet
    return lock(path, timeout=120.0, what=f"the claim {path.stem}", announce=False)


def _write_json(path: Path, data: dict) -> None:
    atomic_write(path, json.dumps(data))


class Claims:
    """This process's claims on cells of one cache."""

    def __init__(self, cache_dir=None, *, lease_s: float = 120.0):
        self.folder = cache_root(cache_dir) / "sweeps" / "claims"
        self.folder.mkdir(parents=True, exist_ok=True)
        self.lease_s = float(lease_s)
        self.worker = f"{socket.gethostname()}:{os.getpid()}"
        self.token = uuid.uuid4().hex
        self.started = time.time()
        self.held: set[str] = set()
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, daemon=True)
        self._beat.start()

    def _paths(self, key: str) -> tuple[Path, Path, Path]:
        return self.folder / f"{key}.lock", self.folder / f"{key}.lease", self.folder / f"{key}.failed"

    def _heartbeat(self) -> None:
        while not self._stop.wait(max(0.2, self.lease_s / 4)):
            for key in list(self.held):
                try:
                    os.utime(self._paths(key)[1])
                except OSError:
                    pass  # taken over or released meanwhile: `still_mine` tells the runner

    def claim(self, key: str, is_complete) -> tuple[str, str]:
        """(state, detail): "complete", "busy" (a live process holds it), "failed" (failed in a process
        that started after this one) or "claimed" (detail names a dead process taken over)."""
        lock, lease, failed = self._paths(key)
        try:
            with _lock(lock):
                if is_complete():
                    return "complete", ""
                if failed.is_file():
                    marker = json.loads(failed.read_text())
                    if marker["time"] >= self.started and marker["worker"] != self.worker:
                        return "failed", f"failed in {marker['worker']}: {marker['reason']}"
                taken_over = ""
                if lease.is_file():
                    owner = json.loads(lease.read_text())
                    age = time.time() - lease.stat().st_mtime
                    if age < self.lease_s:
                        return "busy", owner["worker"]
                    taken_over = f"taken over from {owner['worker']} (no heartbeat for {age:.0f} s)"
                _write_json(lease, {"worker": self.worker, "token": self.token, "since": time.time()})
                self.held.add(key)
                return "claimed", taken_over
        except LockTimeout:
            return "busy", "lock"

    def still_mine(self, key: str) -> bool:
        lease = self._paths(key)[1]
        try:
            return json.loads(lease.read_text())["token"] == self.token
        except (OSError, ValueError, KeyError):
            return False

    def release(self, key: str, failure: str | None = None) -> None:
        lock, lease, failed = self._paths(key)
        with _lock(lock):
            if failure is not None:
                _write_json(failed, {"worker": self.worker, "reason": failure, "time": time.time()})
            elif failed.is_file():
                failed.unlink()
            if self.still_mine(key):
                lease.unlink()
        self.held.discard(key)

    def close(self) -> None:
        self._stop.set()
