"""How a published section replaces the old one: written into a staging folder beside it, held by a lock
while it is written, swapped in at the end in one step; what killed publishes left is removed by the next.
Of publishes to one folder at once, the site stays the one built from the results read last (`newer_in_place`)."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import CacheError, LockTimeout, atomic_write, exchange, lock
from ..paths import special_file


def alive(staging: Path) -> Path:
    return staging.with_name(staging.name + ".lock")  # held by the publish writing `staging`


def swap(staging: Path, target: Path) -> None:
    """Put the finished folder in place of the old one; the old one is removed only afterwards."""
    if target.exists() and not target.is_dir():
        raise VPRBenchError(f"{target} is a file; move it away so the leaderboard section can be written there.")
    mask = os.umask(0)
    os.umask(mask)
    staging.chmod(0o777 & ~mask)  # mkdtemp makes 0700: a web server reads the site as another user
    # in one step: the old site or the new is in place (a link to a folder is replaced as it was)
    if target.is_dir() and not target.is_symlink() and exchange(staging, target):
        shutil.rmtree(staging, ignore_errors=True)
        return
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}-old-", dir=target.parent))
        target.rename(old / target.name)
    staging.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def remove_stale_sections(folder: Path, section: str, own: Path) -> None:
    """Folders a killed publish of `section` left: old sections (only ever made under the lock, so stale
    when we hold it) and staging folders whose lock no publish holds (a live one does)."""
    for path in (p for p in folder.glob(f".{section}-*-*") if p.is_dir() and p != own):
        with contextlib.suppress(LockTimeout), lock(alive(path), timeout=0, announce=False):  # else: live
            shutil.rmtree(path, ignore_errors=True)
            alive(path).unlink(missing_ok=True)


def _read_at(folder: Path, section: str) -> Path:
    return folder / f".{section}.read-at"  # beside the lock: the section itself is the site (and a git tree)


def newer_in_place(folder: Path, section: str, read_at: int) -> bool:
    """Under the section's lock: whether the section in place was built from results read after `read_at` (ns,
    this host's clock) by another publish. A date ahead of now (a clock set ahead) is not believed: it would stop
    every publish until then."""
    note = _read_at(folder, section)
    try:  # a pipe put in its place would be waited on for good
        found = 0 if special_file(note) else int(note.read_text(encoding="utf-8")[:40])
    except (OSError, ValueError):
        return False
    return (folder / section).is_dir() and read_at < found <= time.time_ns()


def mark_read_at(folder: Path, section: str, read_at: int) -> None:
    """Under the section's lock, once it is swapped in: when the results it was built from were read."""
    with contextlib.suppress(CacheError):  # the site is in place: a note not written only loses this ordering
        atomic_write(_read_at(folder, section), str(read_at))
