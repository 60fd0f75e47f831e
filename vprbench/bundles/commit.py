"""An import's files put into a results repository with one atomic step as its commit point.

Under the repository's lock, every file of the import is written into a private folder
`<DIR>/.import.pending/staging-<id>/`, laid out as the repository; renaming that folder to
`commit-<id>` commits the import (one rename). The files are then moved to their places, each
run's record last, and the folder removed. A kill before the rename leaves only the staging
folder, which the next import (or verify) removes unseen; a kill after it leaves the commit
folder, which the next one finishes. Both hold the lock, so no live writer's folder is touched:
nothing else ever writes there. Every name is at least two levels under `.import.pending`, so
readers of `<DIR>/*/*/*.json` never see one.
"""
from __future__ import annotations

import os
import re
import secrets
import shutil
from pathlib import Path

from ..fsutil import _sync_folder, cache_error, remove_stale
from .archive import _CARD, RECORD_NAME

PENDING = ".import.pending"
#: the names a repository keeps (a run's record, arrays and contribution note; a method card)
_KEPT = re.compile(RECORD_NAME.pattern.replace("(json|npz)", "(json|npz|contribution)") + "|" + _CARD.pattern)
#: `atomic_path`'s temporary name for a file NAME: .NAME.<mkstemp's 8 characters>.tmp
_TEMPORARY = re.compile(r"^\.(.+)\.[A-Za-z0-9_]{8}\.tmp$")


def _write(path: Path, data: bytes) -> None:
    """One staged file, on disk before the commit (a step tests kill at)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _rename(source: Path, target: Path) -> None:
    """The commit, or one move after it (a step tests kill at)."""
    os.replace(source, target)


def commit(into: Path, writes: dict[str, bytes]) -> None:
    """Write `writes` (repository-relative names; records as `<p>/<r>/<run>.json`) into `into`
    as one step: all of them, or (after a kill before the commit) none. Call under the lock."""
    if not writes:
        return
    name = f"{os.getpid()}-{secrets.token_hex(4)}"
    staging, committed = into / PENDING / f"staging-{name}", into / PENDING / f"commit-{name}"
    try:
        for member, data in writes.items():
            _write(staging / member, data)
        for folder in {(staging / m).parent for m in writes}:
            _sync_folder(folder)
        _rename(staging, committed)  # the commit point
        _sync_folder(into / PENDING)
    except OSError as error:
        shutil.rmtree(staging, ignore_errors=True)  # not committed: nothing of it stays
        raise cache_error(error, into) from None
    finish(into, committed)


def finish(into: Path, committed: Path) -> None:
    """Move a committed import's files to their places: cards and arrays before the records that
    need them, so a record is there only with both. A file already in place is kept (files are
    only ever added), except a run's contribution note, which is the import's own."""
    # only names a repository keeps, as regular files (the folder's content is not trusted blindly:
    # a pull request could carry one; what lands is re-scored by `results verify` all the same)
    members = sorted(name for p in committed.rglob("*") if p.is_file() and not p.is_symlink()
                     and _KEPT.match(name := p.relative_to(committed).as_posix()))
    # records (<p>/<r>/<run>.json) last; cards (methods/<row>.json) lie one folder down
    members.sort(key=lambda m: m.count("/") == 2 and m.endswith(".json"))
    try:
        for member in members:
            source, target = committed / member, into / member
            if link_in(into, member):  # a move through a linked folder would land outside the repository
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.exists() and not member.endswith(".contribution"):
                source.unlink()
            else:
                _rename(source, target)
        for folder in {(into / m).parent for m in members}:
            _sync_folder(folder)
        shutil.rmtree(committed)
    except OSError as error:
        raise cache_error(error, into) from None


def link_in(into: Path, member: str) -> str | None:
    """The first part of `member` (a repository-relative name) that is a link in `into`, if any."""
    parts = member.split("/")
    for depth in range(1, len(parts) + 1):
        if into.joinpath(*parts[:depth]).is_symlink():
            return "/".join(parts[:depth])
    return None


def _temporaries(into: Path) -> list[Path]:
    """Files an import of an older vprbench (one `atomic_write` per file) left when killed mid-write:
    `.<a repository file's name>.<8 random characters>.tmp`, where that file would be."""
    return [p for p in (*into.glob(".LAYOUT.*.tmp"), *into.glob("*/.*.tmp"), *into.glob("*/*/.*.tmp"))
            if not p.is_symlink() and p.is_file() and (m := _TEMPORARY.match(p.name))
            and (m.group(1) == "LAYOUT" if p.parent == into else
                 _KEPT.match(p.parent.relative_to(into).joinpath(m.group(1)).as_posix()))]


def leftovers(into: Path) -> bool:
    """Whether killed imports left anything here (to set right under the lock: `recover`)."""
    return (into / PENDING).is_dir() or bool(_temporaries(into))


def recover(into: Path) -> int:
    """What imports killed here left, set right (under the lock, so none of it is a live import's):
    uncommitted staging folders and stale temporary files removed, committed imports finished. Returns
    how many were found."""
    pending = into / PENDING
    try:
        temporaries = _temporaries(into)
        remove_stale(temporaries)  # untouched for an hour: not a live writer's (one outside the lock, e.g. an evaluation)
        if pending.is_symlink() or not pending.is_dir():
            return len(temporaries)
        found = sorted(pending.iterdir())
        for folder in found:
            if folder.is_symlink() or not folder.is_dir():
                continue
            if folder.name.startswith("commit-"):
                finish(into, folder)
            elif folder.name.startswith("staging-"):
                shutil.rmtree(folder)
        if not any(pending.iterdir()):
            pending.rmdir()
    except OSError as error:
        raise cache_error(error, pending) from None
    return len(temporaries) + len(found)
