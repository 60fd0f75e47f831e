"""User-facing errors: the CLI prints their message and exits non-zero, without a traceback."""
from __future__ import annotations

import errno as codes
import io
import os
import re
import tomllib
from contextlib import contextmanager

from .text import shortened


class VPRBenchError(Exception):
    """A problem with the user's input or environment; the message says what and how to fix it."""


class MethodNeed(VPRBenchError):
    """What a method lacks to be made, said with the command making it, which names the method and the run's
    folders: `said(method, locations)` ({"data-dir": ..., "cache-dir": ...}). create_method, which knows
    both (the factory does not), says it again for the method as created."""

    def __init__(self, said, method: str):
        super().__init__(said(method, {}))
        self.said = said


class ShardWarning(UserWarning):
    """A warning about what one torchrun rank met in its own share (an image it read, a file it removed):
    said by that rank. Every other warning is met alike by every rank, and said by the node's first."""


class ProblemList(VPRBenchError):
    """Several problems found at once, one a line: the command line keeps its line breaks (every
    other message is one line, a line break from data in it written out as '\\n')."""


def closest_names(name: str, choices, n: int = 3) -> str:
    """' Did you mean: a, b?' for the names closest to `name`, or '' when none is close."""
    import difflib

    if not isinstance(name, str):  # a name of the wrong type (None, a number, a list) is simply unknown
        return ""
    close = difflib.get_close_matches(name, [c for c in choices if isinstance(c, str)], n=n, cutoff=0.5)
    return f" Did you mean: {', '.join(close)}?" if close else ""


def require(value, kind, what: str) -> None:
    """A VPRBenchError unless `value` is a `kind`: for the Python API's arguments, checked on entry
    so a wrong type is one line naming the argument (`what` says which, and what to pass), not an
    AttributeError from deep inside."""
    if not isinstance(value, kind):
        import reprlib

        raise VPRBenchError(f"{what}; got {type(value).__name__} {reprlib.repr(value)}.")


# ---------------------------------------------------------------- network errors
def network_reason(error: BaseException) -> str:
    """Why a download failed, in a few words: an HTTP status, else the innermost operating-system
    reason ('Connection refused'), else the error's first line. The clients wrap it in layers
    (requests > urllib3 > socket) whose text repeats the host, port and path at length."""
    from collections import deque

    found, pending, seen = None, deque([error]), set()
    while pending:
        current = pending.popleft()
        if current is None or id(current) in seen or not isinstance(current, BaseException):
            continue
        seen.add(id(current))
        status = _attribute(_attribute(current, "response"), "status_code") or _attribute(current, "code")
        if isinstance(status, int) and 400 <= status < 600:
            return f"HTTP {status}"
        if isinstance(current, TimeoutError) or "timed out" in _text(current).lower():
            found = found or "timed out"
        if isinstance(current, OSError) and isinstance(current.strerror, str) and current.strerror:
            found = current.strerror  # the innermost wins: it is the one the others wrap
        pending += [current.__cause__, current.__context__, _attribute(current, "reason"), *current.args]
    text = _text(error).strip()
    found = found or (text.splitlines()[0] if text else type(error).__name__)
    return shortened(found, 160)


def _text(error: BaseException) -> str:
    """str(error), or '' when it cannot be had: the reason is asked for while reporting a failure,
    which a faulty __str__ (or an args tuple holding the error itself) must not replace."""
    try:
        return str(error)
    except Exception:  # RecursionError too
        return ""


def _attribute(value, name: str):
    try:
        return getattr(value, name, None)
    except Exception:  # a property that raises (a response object half made)
        return None


def url_host(url: str) -> str:
    """The host (and port) of `url`, which names where a download went without its long path."""
    from urllib.parse import urlsplit

    return urlsplit(url).netloc or url


# ---------------------------------------------------------------- operating-system errors
#: errno -> what to do; {move} becomes "point --cache-dir at" (or --data-dir) when the path lies under one
_WHAT_TO_DO = {
    codes.EROFS: "{move} a folder on a writable disk",
    codes.ENOSPC: "free some space, or {move} a folder on another disk{kept}",
    codes.EDQUOT: "free some space, or {move} a folder on another disk{kept}",
    codes.EFBIG: "the file size limit (ulimit -f) or the filesystem's largest file is reached: raise the limit, or "
                 "{move} a folder on another disk",
    codes.EACCES: "change its permissions, or {move} a folder this user may write to",
    codes.EPERM: "{move} another folder",
    codes.ENOENT: "check the path",
    codes.ENOTDIR: "a part of the path is a file, not a folder: check the path",
    codes.EISDIR: "it is a folder, not a file: check the path",
    codes.EAGAIN: "another process holds it open (another vprbench run?): wait for it to finish, then rerun",
    codes.EMFILE: "raise the limit (ulimit -n) or run fewer jobs at once",
    codes.EIO: "check the disk",
    codes.ENAMETOOLONG: "use a shorter name",
    codes.ELOOP: "a symbolic link in this path leads back to itself: fix or remove the link, or give another path",
}


def _path_of(error: OSError) -> str | None:
    """The file an OSError is about: its filename; a path named in its message (HDF5 puts one
    there); else, from the innermost frame outwards, the file object being read or written
    (a failed write() names no file) or the name HDF5 was opening (its lock errors name none)."""
    if getattr(error, "lock_file", None):  # filelock.Timeout
        return str(error.lock_file)
    if error.filename is not None:
        return os.fsdecode(error.filename)
    found = re.search(r"name = '([^']+)'", str(error))
    if found:
        return found.group(1)
    frames, trace = [], error.__traceback__
    while trace is not None:
        frames.append(trace.tb_frame)
        trace = trace.tb_next
    for frame in reversed(frames):
        for value in frame.f_locals.values():
            if isinstance(value, io.IOBase) and isinstance(getattr(value, "name", None), (str, bytes)):
                return os.fsdecode(value.name)
        if "h5py" in frame.f_code.co_filename and isinstance(frame.f_locals.get("name"), (str, bytes, os.PathLike)):
            return os.fsdecode(frame.f_locals["name"])
    return None


#: the folders the command line runs with, by the option that sets them (for the advice only)
ROOTS: dict[str, str] = {}


def name_roots(**roots) -> None:
    """Tell error messages which folder each option (cache_dir=..., data_dir=...) points at."""
    ROOTS.update({f"--{k.replace('_', '-')}": os.path.abspath(v) for k, v in roots.items() if v is not None})


def _move(path: str | None) -> str:
    """'point --cache-dir at' or 'point --data-dir at' when the path lies under that root, else 'use'."""
    if path is not None:
        target = os.path.abspath(path)
        for option, root in ROOTS.items():
            if target == root or target.startswith(root + os.sep):
                return f"point {option} at"
    return "use"


#: what a run stopped part-way keeps (the next run resumes from it)
DESCRIBED = "finished descriptors"
#: what the running command keeps, said on a full disk; None: nothing partial worth naming. A command
#: line command says it (`keeping`); the API's long work is describing.
KEPT: dict[str, str | None] = {"what": DESCRIBED}


@contextmanager
def keeping(what: str | None):
    """Within it, a full disk's advice says that `what` are kept (None: says nothing of it)."""
    before, KEPT["what"] = KEPT["what"], what
    try:
        yield
    finally:
        KEPT["what"] = before


def os_error_message(error: OSError, path: str | os.PathLike | None = None, kept: str | None = None) -> str:
    """One sentence for an operating-system error: the path (`path`, else the one the error is
    about), what went wrong, what to do (on a full disk: that `kept`, else what the command keeps,
    are kept)."""
    path = os.fspath(path) if path is not None else _path_of(error)
    where = f" {path}" if path else " a file (the system did not say which)"
    if getattr(error, "lock_file", None) or isinstance(error, TimeoutError):
        return (f"Timed out waiting for the lock{where}: another vprbench process is working on the same "
                "files; wait for it to finish, then rerun.")
    number = codes.EAGAIN if error.errno == codes.EWOULDBLOCK else error.errno
    if number == codes.EEXIST and path and os.path.lexists(path) and not os.path.isdir(path):
        number = codes.ENOTDIR  # making a folder where a file stands: the file is the problem, not a clash
    reason = os.strerror(number) if number else (str(error) or type(error).__name__)
    advice = _WHAT_TO_DO.get(number)
    kept = kept or KEPT["what"]
    said = f" ({kept} are kept)" if kept else ""
    return f"Cannot use{where}: {reason}" + (f"; {advice.format(move=_move(path), kept=said)}." if advice else ".")


# ---------------------------------------------------------------- TOML errors
def toml_data(text: str, what: str) -> dict:
    """A user's TOML text (a plan, a dataset.toml) parsed; invalid, or nested too deeply to parse,
    it is a VPRBenchError naming `what` (e.g. "Plan p.toml"), never a traceback."""
    try:  # a byte order mark (Windows editors write one) is no TOML: tomllib calls it an invalid statement
        return tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as error:
        raise VPRBenchError(f"{what} is not valid TOML: {error}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise VPRBenchError(f"{what} nests arrays or tables too deeply to be read; check its brackets.") from None
