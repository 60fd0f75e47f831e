"""Where vprbench keeps what it computes, and the one rule that turns a name into a file name.

Library code is given its folders (`cache_dir`, `data_dir`); only the command line reads the
environment ($VPRBENCH_CACHE, $VPRBENCH_DATA) for their defaults.
"""
from __future__ import annotations

import errno
import os
import re
import stat
from pathlib import Path

CACHE_ENV = "VPRBENCH_CACHE"
DATA_ENV = "VPRBENCH_DATA"


def default_cache() -> Path:
    """The user cache folder (~/.cache/vprbench on Linux)."""
    import pooch

    return Path(pooch.os_cache("vprbench"))


def folder_path(value, option: str) -> Path | None:
    """A folder argument of the Python API (`cache_dir`, `data_dir`, ...) as a Path; None stays None.
    Anything but a non-empty str or path is refused: Path('') would be the current folder."""
    if value is None or isinstance(value, Path):
        return value if value is None else value.expanduser()
    if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
        from .errors import VPRBenchError

        raise VPRBenchError(f"{option} takes a folder path (a str or pathlib.Path), or None for the default; "
                            f"got {type(value).__name__} {value!r}.")
    return Path(value).expanduser()


def cache_root(cache_dir: str | Path | None = None, option: str = "cache_dir") -> Path:
    """`cache_dir`, else the user cache folder; a cache folder that is a file is refused (reading
    it would find nothing, silently). `option` names where it was given, for the message."""
    root = default_cache() if cache_dir is None else folder_path(cache_dir, option)
    if root.exists() and not root.is_dir():
        from .errors import VPRBenchError

        raise VPRBenchError(f"The cache folder {root} ({option}) is a file, not a folder: give the folder "
                            "vprbench keeps its stores and results in.")
    return root


def environment_folder(given: str | None, variable: str, option: str = "") -> str | None:
    """A folder option of the command line: as given, else the environment variable, else None.
    A value of blanks only is refused: it would make a folder named "   " in the current one."""
    if given is None:  # an empty variable counts as unset
        value, source = os.environ.get(variable) or None, f"${variable}"
    else:  # an empty option (an unset shell variable) is refused: it meant the default, and was downloaded into
        value, source = given, option or "the option"
    if value is not None and not value.strip():
        from .errors import VPRBenchError

        raise VPRBenchError(f"{source} is {value!r}, which names no folder: give a folder, or leave it unset.")
    return value


def _link_loop(path, what: str):
    from .errors import VPRBenchError

    return VPRBenchError(f"{what} {path}: a symbolic link in this path leads back to itself; fix or remove the link, "
                         "or give another path.")


def regular_file(path, what: str) -> bool:
    """Whether `path` (links followed) is a regular file, checked before any read: False when nothing
    (or a folder) is there, which callers explain their way; an error naming `what` for anything else:
    a named pipe would hang the read, a device read forever, a link loop say nothing of the link."""
    from .errors import VPRBenchError, require

    require(path, (str, os.PathLike), f"{what}: give a file path (a str or pathlib.Path)")
    mode = _mode(path, what)
    if mode is None:
        return False  # missing, or not reachable: the caller's own message, or its open(), says which
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return stat.S_ISREG(mode)
    raise VPRBenchError(f"{what} {path} is not a regular file (a named pipe, device or socket): give a file.")


def special_file(path) -> bool:
    """Whether `path` (links followed) is a named pipe, device or socket. A cache file replaced by one (or by
    a link to one) hung its reader (a pipe) or had it read without end (/dev/zero): its readers take it
    for a damaged file, as `regular_file` refuses one a user names."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):  # nothing there, or a NUL in the name: the reader's own check says so
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _no_nul(path, what: str):
    """`path`, refused when it holds a NUL character (which no file name can: the system calls raise a ValueError)."""
    if "\0" in os.fsdecode(path):
        from .errors import VPRBenchError

        raise VPRBenchError(f"{what} {os.fsdecode(path)!r} holds a NUL character, which no file name can: "
                            "give its path.")
    return path


def _mode(path, what: str, at=None) -> int | None:
    """The st_mode of `at` (else `path`), links followed; None when nothing is reachable there. A link
    loop is one line naming `path` and `what`, found by the system (ELOOP) on every Python."""
    try:
        return os.stat(_no_nul(path if at is None else at, what)).st_mode
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise _link_loop(path, what) from None
        return None


def resolved(path, what: str) -> Path:
    """Path(path).resolve(), a link loop being one line naming `what` (resolve itself raised a
    RuntimeError for one before Python 3.13, and from 3.13 on returns a path as if nothing were wrong)."""
    from .errors import require

    require(path, (str, os.PathLike), f"{what}: give a path (a str or pathlib.Path)")
    given = Path(_no_nul(path, what)).expanduser()
    _mode(path, what, at=given)
    return given.resolve()


def safe_name(text: str, limit: int = 60) -> str:
    """`text` as a file name that stays where it is put: letters, digits, '.', '_' and '-' only,
    never starting with a dot (no '..', no '/', no hidden files), at most `limit` characters.
    Used for every name from data (dataset, method, protocol) that becomes part of a path;
    callers add a hash where two names must not collide."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(text)).lstrip(".")[:limit]
    return name or "_"


#: characters Windows forbids in a file name (with the control characters)
WINDOWS_FORBIDDEN = re.compile(r'[<>:"/\\|?*\x00-\x1f]')


def portable_name(text: str) -> str:
    """`text` as one folder name every filesystem takes, changed only where one would refuse it:
    Windows' forbidden characters (a timm:ARCH backbone's ':') and separators become '_', trailing dots
    and blanks go, '.' and '..' are no names. Unlike `safe_name` it keeps '@' and the rest, so the
    names of folders already written on Linux stay as they were."""
    name = WINDOWS_FORBIDDEN.sub("_", str(text)).rstrip(". ")
    return name if name.strip(".") else "_"


def shipped_file(folder: str, name, suffix: str, what: str):
    """The file `<folder>/<name><suffix>` of the manifests vprbench ships, found by name only
    (never a path: '../x' would read any file); an unknown name is one line listing the shipped
    ones, e.g. "No reproduction plans for paper 'anylo'. Did you mean: anyloc? Available: anyloc."."""
    from importlib.resources import files

    from .errors import VPRBenchError, closest_names

    place = files("vprbench.manifests") / folder
    names = sorted(f.name.removesuffix(suffix) for f in place.iterdir() if f.name.endswith(suffix))
    if name not in names:
        raise VPRBenchError(f"No {what} {name!r}.{closest_names(name, names)} Available: {', '.join(names)}.")
    return place / f"{name}{suffix}"
