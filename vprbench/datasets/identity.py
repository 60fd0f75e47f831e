"""Content identity of image lists: what descriptor stores are keyed by.

An image is identified by its name (relative to the dataset root) and the sha256 of its
bytes. Hashing a million files on every run would read the whole dataset, so each hash is
remembered in a small SQLite table in the cache keyed by (absolute path, size, mtime_ns):
a warm run only stats the files (where the cache cannot be written, every run hashes the
files). A file rewritten in place with the same size within one mtime tick is not noticed
(as with make or git); rename or touch it.
"""
from __future__ import annotations

import hashlib
import os
import sqlite3
from collections.abc import Sequence
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import file_sha256
from ..paths import cache_root

MEMO_NAME = "image-hashes.sqlite"


def image_names(paths: Sequence[Path], root: Path | None) -> list[str]:
    """The names stores and records use: relative to the dataset root, else the file name."""
    return [p.relative_to(root).as_posix() if root and p.is_relative_to(root) else p.name for p in paths]


def _file_sha256(path: str) -> str:
    try:
        return file_sha256(path)
    except OSError as error:
        raise VPRBenchError(f"Cannot read image {path}: {error.strerror or error}.") from None


class _Memo:
    """(path, size, mtime_ns) -> sha256, shared by every process using the cache."""

    def __init__(self, cache_dir=None):
        self.db = None
        path = cache_root(cache_dir) / MEMO_NAME
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.db = sqlite3.connect(path, timeout=60)
            self.db.execute("CREATE TABLE IF NOT EXISTS hashes "
                            "(path TEXT PRIMARY KEY, size INTEGER, mtime_ns INTEGER, sha256 TEXT)")
        except (OSError, sqlite3.Error):  # a read-only cache: hash without remembering (slower, still right)
            self.db = None

    def lookup(self, keys: dict[str, tuple[int, int]]) -> dict[str, str]:
        """The remembered hashes of the paths whose size and mtime are unchanged."""
        if self.db is None:
            return {}
        found, paths = {}, list(keys)
        for start in range(0, len(paths), 500):
            part = paths[start:start + 500]
            query = f"SELECT path, size, mtime_ns, sha256 FROM hashes WHERE path IN ({','.join('?' * len(part))})"
            for path, size, mtime, digest in self.db.execute(query, part):
                if keys[path] == (size, mtime):
                    found[path] = digest
        return found

    def remember(self, rows: list[tuple[str, int, int, str]]) -> None:
        if self.db is None or not rows:
            return
        try:
            with self.db:
                self.db.executemany("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?)", rows)
        except sqlite3.Error:  # read-only or full: the hashes are right, only not remembered
            pass

    def close(self) -> None:
        if self.db is not None:
            self.db.close()


def content_hashes(paths: Sequence[Path], cache_dir=None) -> list[str]:
    """sha256 of each file's bytes ("missing" for a file that is not there), memoised."""
    names = [os.path.abspath(p) for p in paths]
    keys = {}
    for name in names:
        try:
            st = os.stat(name)
        except FileNotFoundError:
            continue
        keys[name] = (st.st_size, st.st_mtime_ns)
    memo = _Memo(cache_dir)
    try:
        known = memo.lookup(keys)
        new = []
        for name, (size, mtime) in keys.items():
            if name not in known:
                known[name] = _file_sha256(name)
                new.append((name, size, mtime, known[name]))
        memo.remember(new)
    finally:
        memo.close()
    return [known.get(name, "missing") for name in names]


def images_key(paths: Sequence[Path], root: Path | None, cache_dir=None) -> str:
    """sha256 over the images' names and contents, in order."""
    h = hashlib.sha256()
    for name, digest in zip(image_names(paths, root), content_hashes(paths, cache_dir)):
        h.update(f"{name}\0{digest}\n".encode())
    return h.hexdigest()
