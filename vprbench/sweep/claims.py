"""Cells shared by several processes on one cache: each claimed with a lease, evaluated once.

<cache>/sweeps/claims/<cell>.lease names the process working on a cell; a heartbeat thread
refreshes its modification time every HEARTBEAT_S, a quarter of the shortest lease allowed, so
processes with different leases never judge each other's live claims dead. A lease whose date
has not changed for `lease_s` belonged to a process that died: another process takes the cell over (the descriptor
store resumes its partial rows). The lease's age is its date against this host's clock; a date
ahead of now (another host's clock set ahead, a file touched by hand) cannot make a cell wait
for that long: such a lease counts as stale once this process has seen its date unchanged for
one lease period (time.monotonic, which nobody can set).
Claiming, taking over and releasing happen under a per-cell file lock (filelock), so two
processes never both hold a cell. While it holds a cell, a process also holds an flock on
<cell>.alive, which the system releases when the process dies: a lease of this host whose flock
is free belonged to a process killed (kill -9, out of memory), and its cell is taken over at
once rather than after `lease_s` (only on this host: another host's flock may not reach here).
A claim file that cannot be read (empty, not JSON, wrong fields) is set aside as <name>.damaged
with a warning naming it, and the cell is claimed anew.
"""
from __future__ import annotations

import json
import math
import os
import reprlib
import socket
import threading
import time
import uuid
import warnings
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import LockTimeout, atomic_write, cache_error, lock, remove_stale, temporaries_of
from ..paths import cache_root, special_file

#: the shortest lease: four heartbeats, so a live process on a busy machine is not judged dead
MIN_LEASE_S = 1.0
HEARTBEAT_S = MIN_LEASE_S / 4
#: the fields of each claim file and their types; anything else is a damaged file
_FIELDS = {"lease": {"worker": str, "token": str}, "failed": {"worker": str, "reason": str, "time": float}}


def checked_lease(lease_s) -> float:
    """`lease_s` as seconds, or a VPRBenchError: a NaN or infinite lease would let any process
    take a live claim (or none ever take a dead one)."""
    try:
        value = math.nan if isinstance(lease_s, bool) else float(lease_s)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value >= MIN_LEASE_S):
        raise VPRBenchError(f"The lease must be a finite number of seconds, at least {MIN_LEASE_S:g} (how long a "
                            f"claim outlives its process's last heartbeat); got {lease_s!r}.")
    return value


def _lock(path: Path):
    # held for moments: no "waiting for" line each time two processes meet
    return lock(path, timeout=120.0, what=f"the claim {path.stem}", announce=False)


def _write_json(path: Path, data: dict) -> None:
    """Under the cell's lock: temporaries found then are killed writers' (else kept for good)."""
    atomic_write(path, json.dumps(data))
    remove_stale(temporaries_of(path), age_s=0)


def _read_claim(path: Path) -> dict | None:
    """The claim file's fields, or None when there is none. A damaged file is set aside (renamed
    to <name>.damaged) with a warning naming it, so it neither stops the sweep nor blocks the
    cell until someone finds and deletes it."""
    fields = _FIELDS[path.suffix[1:]]
    special = special_file(path)  # a pipe would hang the sweep, /dev/zero fill its memory: set aside unread
    try:
        raw = b"" if special else path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as error:
        raise cache_error(error, path) from None
    try:
        data = json.loads(raw)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        for name, kind in fields.items():
            value = data.get(name)
            if kind is float and not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
                raise ValueError(f"its {name!r} is {reprlib.repr(value)}, not a finite number")
            if kind is str and not isinstance(value, str):
                raise ValueError(f"its {name!r} is {reprlib.repr(value)}, not a text")
        return data
    except (ValueError, RecursionError) as error:  # JSON and UTF-8 errors are ValueErrors
        if special:
            reason = "it is a named pipe, device or socket, not a file"
        elif not raw.strip():
            reason = "it is empty"
        elif isinstance(error, json.JSONDecodeError):
            reason = f"it is not JSON: {error.msg.lower()} at byte {error.pos}"
        else:
            reason = str(error)
    aside = path.with_name(path.name + ".damaged")
    try:
        os.replace(path, aside)
    except OSError as error:
        raise cache_error(error, path) from None
    warnings.warn(f"The claim file {path} cannot be read ({reason}); it is set aside as {aside} and the cell is "
                  "claimed anew. Delete the set-aside file when you like.", stacklevel=3)
    return None


class Claims:
    """This process's claims on cells of one cache."""

    def __init__(self, cache_dir=None, *, lease_s: float = 120.0):
        self.lease_s = checked_lease(lease_s)
        self.folder = cache_root(cache_dir) / "sweeps" / "claims"
        self.folder.mkdir(parents=True, exist_ok=True)
        self.worker = f"{socket.gethostname()}:{os.getpid()}"
        self.token = uuid.uuid4().hex
        self.started = time.time()
        self.held: set[str] = set()
        #: cell -> the open <cell>.alive this process holds an flock on while it holds the cell
        self._alive: dict[str, object] = {}
        #: cell -> (date of its lease when first seen, time.monotonic() then): judges leases dated ahead
        self._seen: dict[str, tuple[int, float]] = {}
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, daemon=True)
        self._beat.start()

    def _paths(self, key: str) -> tuple[Path, Path, Path]:
        return self.folder / f"{key}.lock", self.folder / f"{key}.lease", self.folder / f"{key}.failed"

    def _flock(self, key: str):
        """The open <cell>.alive, flocked by this process; None where it is held (a process past its
        lease, still running) or the system has no flock."""
        try:
            import fcntl

            path = self.folder / f"{key}.alive"
            if special_file(path):  # a pipe or device put in its place: opening a pipe waits for a reader for good
                path.unlink(missing_ok=True)  # (a link: the link alone)
            alive = open(path, "ab")
        except (ImportError, OSError):
            return None
        try:
            fcntl.flock(alive, fcntl.LOCK_EX | fcntl.LOCK_NB)  # per open file: two Claims of one process exclude too
            return alive
        except OSError:
            alive.close()
            return None

    def _died(self, key: str, owner: dict) -> bool:
        """Whether the lease's holder, a process of this host that held <cell>.alive, has died."""
        if owner.get("alive") is not True or owner["worker"].rpartition(":")[0] != socket.gethostname():
            return False
        probe = self._flock(key)
        if probe is not None:
            probe.close()
        return probe is not None

    def forget(self, key: str) -> None:
        """No longer hold `key` (released, or taken over by another process meanwhile)."""
        self.held.discard(key)
        alive = self._alive.pop(key, None)
        if alive is not None:
            alive.close()  # closing releases the flock

    def _heartbeat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            for key in list(self.held):
                try:
                    os.utime(self._paths(key)[1])
                except OSError:
                    pass  # taken over or released meanwhile: `still_mine` tells the runner

    def _stale(self, key: str, lease: Path) -> str:
        """Why the lease is stale ("" while its holder may be alive)."""
        stat = lease.stat()
        age = time.time() - stat.st_mtime
        if age >= self.lease_s:
            return f"no heartbeat for {age:.0f} s"
        seen = self._seen.get(key)
        if seen is None or seen[0] != stat.st_mtime_ns:  # new, or refreshed by a heartbeat
            if age < -1 and seen is None:
                warnings.warn(f"The claim {lease} is dated {-age:.0f} s ahead of this host's clock (a clock set ahead, or "
                              f"a file touched by hand); it counts as stale if its date stays unchanged for "
                              f"{self.lease_s:g} s.", stacklevel=3)
            self._seen[key] = (stat.st_mtime_ns, time.monotonic())
            return ""
        unchanged = time.monotonic() - seen[1]
        return f"its date, ahead of this host's clock, unchanged for {unchanged:.0f} s" if unchanged >= self.lease_s else ""

    def claim(self, key: str, is_complete) -> tuple[str, str]:
        """(state, detail): "complete", "busy" (a live process holds it), "failed" (failed in a process
        that started after this one) or "claimed" (detail names a dead process taken over)."""
        lock, lease, failed = self._paths(key)
        try:
            with _lock(lock):
                if is_complete():
                    return "complete", ""
                marker = _read_claim(failed)
                if marker is not None and marker["time"] >= self.started and marker["worker"] != self.worker:
                    return "failed", f"failed in {marker['worker']}: {marker['reason']}"
                taken_over = ""
                owner = _read_claim(lease)
                if owner is not None:
                    stale = "its process has ended" if self._died(key, owner) else self._stale(key, lease)
                    if not stale:
                        return "busy", owner["worker"]
                    taken_over = f"taken over from {owner['worker']} ({stale})"
                alive = self._flock(key)
                _write_json(lease, {"worker": self.worker, "token": self.token, "since": time.time(),
                                    "alive": alive is not None})
                self._seen.pop(key, None)
                self.held.add(key)
                if alive is not None:
                    self._alive[key] = alive
                return "claimed", taken_over
        except LockTimeout:
            return "busy", "lock"

    def still_mine(self, key: str) -> bool:
        lease = self._paths(key)[1]
        try:  # a pipe or device put in its place is no lease of this process's (reading it would wait for good)
            return lease.is_file() and json.loads(lease.read_text(encoding="utf-8"))["token"] == self.token
        except (OSError, ValueError, KeyError, TypeError):
            return False

    def keep_if_mine(self, key: str, keep) -> bool:
        """Call `keep()` (store the cell's result) if this process still holds `key`, under the cell's lock: a
        process stalled past its lease cannot store a result beside the one of the process that took it over."""
        with _lock(self._paths(key)[0]):
            if not self.still_mine(key):
                return False
            keep()
            return True

    def release(self, key: str, failure: str | None = None) -> None:
        lock, lease, failed = self._paths(key)
        with _lock(lock):
            if failure is not None:
                _write_json(failed, {"worker": self.worker, "reason": failure, "time": time.time()})
            elif failed.is_file():
                failed.unlink()
            if self.still_mine(key):
                lease.unlink()
            if key in self._alive:  # removed under the cell's lock, as every open of it: no one flocks a gone file
                (self.folder / f"{key}.alive").unlink(missing_ok=True)
            self.forget(key)

    def close(self) -> None:
        self._stop.set()
