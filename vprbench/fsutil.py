"""The one atomic-write helper and the one inter-process lock of vprbench.

- `atomic_path(path)` / `atomic_write(path, data)`: the file is written under a temporary
  name in the same folder and `os.replace`d over `path`, so a reader (or a kill at any
  moment) sees the old content or the new, never half of one; `atomic_write` also removes the
  temporaries killed writers of `path` left, once an hour old.
- `exchange(a, b)`: two folders swapped in one step where the system can (a published site).
- `lock(path, timeout)`: an exclusive `filelock` lock shared by every process on the
  machine (and by hosts sharing the folder, where the filesystem supports `flock`). A
  process that has to wait says, in one line, who holds the lock; a timeout is a
  `LockTimeout` naming the lock and its holder.
- `file_sha256(path)`: the content hash that identifies images and weight files.
- `cache_error(error, path)`: an `OSError` (or HDF5's `RuntimeError`) turned into a
  `CacheError` (a `VPRBenchError`) that names the path and says what to do.
- `warn_once(path, text)`: a file left where it lies (a record in the wrong folder) named once
  per process, however many look-ups meet it.
"""
from __future__ import annotations

import errno
import glob
import hashlib
import math
import os
import re
import socket
import sys
import tempfile
import time
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import VPRBenchError, os_error_message
from .text import literal, one_line


class CacheError(VPRBenchError):
    """A file under the cache (or an output path) could not be read or written."""

    #: the operating system's error number it came from (ENOSPC: a full disk), when it came from one
    errno: int | None = None


class LockTimeout(CacheError):
    """Waited longer than the given timeout for a lock."""


def cache_error(error: Exception, path: str | os.PathLike | None = None, **said) -> CacheError:
    """One clear message (errors.os_error_message: the path, what went wrong, what to do; `said`: its
    wording, e.g. what a full disk keeps) for an `OSError`, for HDF5's `RuntimeError`, which carries
    the errno only in its text, or for a CacheError to be said again. `path` names the file when the
    error itself does not."""
    if isinstance(error, CacheError) or not isinstance(error, OSError):
        number = getattr(error, "errno", None) or _errno_in(error) or errno.EIO
        error = OSError(number, os.strerror(number))
    return _failed(error, None if error.filename is not None else path, **said)


def _errno_in(error: Exception) -> int | None:
    """The errno HDF5 writes into its errors' text only."""
    found = re.search(r"errno = (\d+)", str(error))
    return int(found.group(1)) if found else None


def _failed(error: OSError, path, **said) -> CacheError:
    failure = CacheError(os_error_message(error, path, **said))
    failure.errno = error.errno or _errno_in(error)
    return failure


def _sync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # not every platform opens folders; the rename itself is still atomic
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside `path` to write to; it replaces `path` when the block succeeds
    and is removed when it fails. The data are flushed to disk before the rename."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as error:  # name the folder that refuses files, not a temporary name
        too_long = error.errno == errno.ENAMETOOLONG  # then the fault is the file's own name
        raise _failed(error, path if too_long else path.parent) from None
    os.close(fd)
    temporary = Path(name)
    try:
        yield temporary
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(temporary, 0o666 & ~mask)  # mkstemp makes 0600; give the file the usual mode
        with open(temporary, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(temporary, path)
        _sync_folder(path.parent)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise _failed(error, path) from None  # the target, not the temporary name
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write `data` (str as UTF-8) to `path` atomically. Temporaries of `path` that killed writers left
    (untouched for an hour: a live writer's are younger) are removed then, as nothing else would."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
    remove_stale(temporaries_of(Path(path)))
    return Path(path)


def exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (Linux renameat2 RENAME_EXCHANGE), so a reader or a kill
    sees one or the other in place, never neither; False where the system or filesystem cannot
    (the caller then renames twice)."""
    import ctypes

    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError, TypeError):  # not Linux, or a C library older than glibc 2.28
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_cwd, rename_exchange = -100, 2
    if renameat2(at_cwd, os.fsencode(a), at_cwd, os.fsencode(b), rename_exchange) == 0:
        return True
    number = ctypes.get_errno()
    if number in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(number, os.strerror(number), str(b))


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes (read in blocks; OSError for the caller to name)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def is_temporary(path: Path) -> bool:
    """A leftover of `atomic_path` (a writer killed before its rename)."""
    return path.name.startswith(".") and path.name.endswith(".tmp")


def temporaries_of(path: Path) -> list[Path]:
    """The temporary files `atomic_path` writers of `path` made beside it (a live one's, or a killed one's)."""
    return list(path.parent.glob(f".{glob.escape(path.name)}.*.tmp"))


def remove_stale(paths: Iterable[Path], age_s: float = 3600) -> None:
    """Remove these leftovers of killed writers if untouched for `age_s` (a live writer's files
    are younger); best effort: one that cannot be removed stays, harmless to readers."""
    now = time.time()
    for path in paths:
        try:
            if now - path.stat().st_mtime > age_s:
                path.unlink()
        except OSError:
            pass


def write_in_turn(path: Path, write, what: str) -> Path:
    """`write(path)` (a writer through `atomic_path`) under a lock beside `path`: writers of one file take
    turns, so the temporaries found then are killed writers', removed whatever their age (else kept for good)."""
    with lock(path.with_name(f".{path.name}.lock"), timeout=120, announce=False, what=what):
        write(path)
        remove_stale(temporaries_of(path), age_s=0)
    return path


def write_once(path: Path, data: bytes | str) -> None:
    """`path` written if it is not there yet (a file no one writes twice); killed writers' temporaries beside
    it removed once untouched for an hour (a live writer's are younger), as nothing would look again."""
    if not path.is_file():
        atomic_write(path, data)
    else:
        remove_stale(temporaries_of(path))


#: files named by `warn_once`, by path, size and modification time
_SAID: set[tuple] = set()


def _stamp(path) -> tuple:
    try:
        found = os.stat(path)
    except OSError:
        return (os.fspath(path),)
    return os.fspath(path), found.st_size, found.st_mtime_ns


def said_of(path) -> bool:
    """Whether `warn_once` named the file as it is now."""
    return _stamp(path) in _SAID


def warn_once(path, text: str, stacklevel: int = 2, category: type[Warning] = UserWarning) -> None:
    """Warn `text` of the file at `path` once per process (a command, a session), however many look-ups
    meet it: it is said where it is met, not once per look-up. Changed or replaced, it is said again."""
    stamp = _stamp(path)
    if stamp not in _SAID:
        _SAID.add(stamp)
        warnings.warn(text, category, stacklevel=stacklevel + 1)


# ------------------------------------------------------------------ locks
def _holder_path(path: Path) -> Path:
    return path.with_name(path.name + ".holder")


def _describe_holder(path: Path) -> str:
    holder = _holder_path(path)
    if not holder.is_file():  # nothing there, or a pipe or device put there: reading it would wait for good
        return "another process"
    try:
        return literal(holder.read_text(encoding="utf-8", errors="replace").strip()) or "another process"
    except OSError:
        return "another process"


def check_lock_timeout(timeout, what: str = "a lock") -> None:
    """None (wait as long as it takes) or a finite number of seconds >= 0: filelock waits forever
    for a negative timeout, and a NaN one never runs out."""
    if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
                                or not math.isfinite(timeout) or timeout < 0):
        raise VPRBenchError(f"A lock timeout (--lock-timeout) is a finite number of seconds >= 0, the longest to wait "
                            f"for {what}; got {timeout!r}.")


@contextmanager
def lock(path: str | os.PathLike, timeout: float | None = None, *, what: str | None = None,
         announce: bool = True) -> Iterator[None]:
    """Hold the exclusive lock `path` (a lock file, created if needed) for the block.

    timeout: seconds to wait (None waits as long as it takes; unless `announce` is False, for
    locks held only for moments, the wait is announced once on stderr with the holder's pid,
    host and command). Re-entrant within a process.
    """
    from filelock import FileLock, Timeout

    path = Path(path)
    what = what or str(path)
    check_lock_timeout(timeout, what)
    for file in (path, _holder_path(path)):
        if file.is_symlink():  # taking the lock would empty, or write the holder note into, the file it points to
            raise CacheError(f"The lock file {file} is a link; remove it (vprbench makes its own), then run again.")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        held = FileLock(path, is_singleton=True)
        if not held.acquire(blocking=False, timeout=0):  # pragma: no cover - filelock raises instead
            raise Timeout(str(path))
    except Timeout:
        if announce:
            # one line: `what` names a folder the user gave, which may hold a newline or an escape sequence
            print(f"waiting for {one_line(what)}: locked by {_describe_holder(path)}", file=sys.stderr, flush=True)
        try:
            held.acquire(timeout=-1 if timeout is None else timeout)
        except Timeout:
            raise LockTimeout(
                f"Timed out after {timeout:g} s waiting for {what} (lock {path}), held by "
                f"{_describe_holder(path)}. Let that run finish, or stop it; a lock whose holder "
                "has died is released by the system."
            ) from None
    except OSError as error:
        raise cache_error(error, path) from None
    try:
        if held.lock_counter == 1:
            since = time.strftime("%Y-%m-%d %H:%M:%S")
            command = " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))[:200]
            try:  # a note for people, written in place (a torn note after a kill is harmless)
                # an argument of bytes that are not UTF-8 (a path on Linux) is written as escapes, not refused
                _holder_path(path).write_text(f"pid {os.getpid()} on {socket.gethostname()} since {since} ({command})\n",
                                              encoding="utf-8", errors="backslashreplace")
            except OSError:
                pass
        yield
    finally:
        if held.lock_counter == 1:
            _holder_path(path).unlink(missing_ok=True)
        held.release()
