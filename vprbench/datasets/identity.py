"""Content identity of image lists: what descriptor stores are keyed by.

An image is identified by its name (relative to the dataset root) and the sha256 of its
bytes: "the same image" means the same bytes, never the same size and modification time.
Hashing a million files on every run would read the whole dataset, so each hash is remembered
in a small SQLite table in the cache, reused only while the file's inode, size, mtime and
ctime are all unchanged. The ctime (inode change time) is set by the kernel on every write or
metadata change and cannot be set back by a user (`touch -d`, `os.utime` and `cp -p` restore
the mtime, not the ctime), so an edit that keeps the size and restores the mtime is still
hashed again. Where the cache cannot be written, every run hashes the files. The loader then
checks, image by image, that the bytes it decodes are the ones so identified (loader.py).
"""
from __future__ import annotations

import hashlib
import os
import sqlite3
import warnings
from collections.abc import Sequence
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import file_sha256, lock
from ..paths import cache_root

MEMO_NAME = "image-hashes.sqlite"


def image_names(paths: Sequence[Path], root: Path | None) -> list[str]:
    """The names stores and records use: relative to the dataset root, else the file name."""
    return [p.relative_to(root).as_posix() if root and p.is_relative_to(root) else p.name for p in paths]


def check_store_names(paths: Sequence[Path], names: Sequence[str]) -> None:
    """Refuse, naming the image, a name a store cannot keep (stores keep names as UTF-8 text): a path given to
    `describe` in another encoding's bytes was a traceback when its store was created, after the images
    before it were described. (A key, `images_key`, takes any name: a folder's stray files are keyed too.)"""
    try:
        "\n".join(names).encode("utf-8")  # one encode for the common case; the image at fault found below
    except UnicodeEncodeError:
        from ..images import utf8_name

        for path, name in zip(paths, names):
            utf8_name(Path(path), name)


def _file_sha256(path: str) -> str:
    try:
        return file_sha256(path)
    except OSError as error:
        raise VPRBenchError(f"Cannot read image {path}: {error.strerror or error}.") from None


def _damaged(error: sqlite3.Error) -> bool:
    """A file that is not (or no longer) a whole SQLite database, rather than one that is locked,
    read-only or on a full disk."""
    return (getattr(error, "sqlite_errorcode", 0) & 0xFF) in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)


#: the memo's table: a path's hash and the stamp (inode, size, mtime, ctime) it was taken at
TABLE = "CREATE TABLE IF NOT EXISTS hashes_v2 (path TEXT PRIMARY KEY, stamp TEXT, sha256 TEXT)"


def _key(path: str):
    """A path as the memo keys it: its text, or its bytes (stored as a BLOB, never equal to a text) when
    it holds bytes that are no UTF-8 (a folder named in another encoding), which SQLite cannot take as text."""
    try:
        path.encode("utf-8")
        return path
    except UnicodeEncodeError:
        return os.fsencode(path)


def stamp(st: os.stat_result) -> str:
    """What must stay unchanged for a remembered hash to be reused (see the module's docstring)."""
    return f"{st.st_ino}:{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}"


class _Memo:
    """path -> (stamp, sha256), shared by every process using the cache.

    The memo is only a cache of hashes: a damaged file (not a database, or malformed pages) is
    renamed to `image-hashes.sqlite.damaged`, with one warning naming it, and rebuilt; a cache
    that cannot be written is not remembered in (every run hashes the images: slower, still right).
    """

    def __init__(self, cache_dir=None):
        self.path = cache_root(cache_dir) / MEMO_NAME
        self.db: sqlite3.Connection | None = None
        self.db = self._open()

    def _open(self) -> sqlite3.Connection | None:
        db = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(self.path, timeout=60)
            db.execute(TABLE)
            return db
        except sqlite3.Error as error:
            if db is not None:
                db.close()
            return self._set_aside(error) if _damaged(error) else None
        except OSError:
            return None

    def _set_aside(self, error: sqlite3.Error) -> sqlite3.Connection | None:
        """Rename the damaged file and start a new one, under a lock so that a process meeting the
        damage after another has rebuilt the memo does not set the new one aside too."""
        if self.db is not None:
            self.db.close()
            self.db = None
        aside = self.path.with_name(self.path.name + ".damaged")
        try:
            with lock(self.path.with_name(self.path.name + ".lock"), timeout=120.0, announce=False,
                      what=f"the image-hash memo {self.path}"):
                if self.path.exists() and not self._whole():
                    os.replace(self.path, aside)
                    for side in ("-journal", "-wal", "-shm"):  # belong to the damaged file
                        self.path.with_name(self.path.name + side).unlink(missing_ok=True)
                    warnings.warn(f"The image-hash memo {self.path} is damaged ({error}); it is set aside as {aside} "
                                  "and rebuilt (images are hashed again once). Delete the set-aside file when you like.",
                                  stacklevel=4)
                db = sqlite3.connect(self.path, timeout=60)
                db.execute(TABLE)
                return db
        except (OSError, sqlite3.Error, VPRBenchError):  # cannot rebuild here: hash without remembering
            return None

    def _whole(self) -> bool:
        """Whether the memo file is (now) an undamaged database."""
        try:
            db = sqlite3.connect(self.path.absolute().as_uri() + "?mode=ro", uri=True, timeout=60)
        except sqlite3.Error:
            return False
        try:
            return db.execute("PRAGMA quick_check").fetchone()[0] == "ok"
        except sqlite3.Error:
            return False
        finally:
            db.close()

    def lookup(self, keys: dict[str, str]) -> dict[str, str]:
        """The remembered hashes of the paths whose stamp is unchanged."""
        if self.db is None:
            return {}
        found, paths = {}, [_key(path) for path in keys]
        try:
            for start in range(0, len(paths), 500):
                part = paths[start:start + 500]
                query = f"SELECT path, stamp, sha256 FROM hashes_v2 WHERE path IN ({','.join('?' * len(part))})"
                for key, found_stamp, digest in self.db.execute(query, part):
                    path = os.fsdecode(key) if isinstance(key, bytes) else key
                    if keys.get(path) == found_stamp and isinstance(digest, str):
                        found[path] = digest
        except sqlite3.Error as error:
            if _damaged(error):
                self.db = self._set_aside(error)
            return {}  # nothing trusted from a file that fails: every image is hashed
        return found

    def remember(self, rows: list[tuple[str, str, str]]) -> None:
        for attempt in range(2):  # a second time in a rebuilt memo, if this one proves damaged
            if self.db is None or not rows:
                return
            try:
                with self.db:
                    self.db.executemany("INSERT OR REPLACE INTO hashes_v2 VALUES (?, ?, ?)",
                                        [(_key(path), taken, digest) for path, taken, digest in rows])
                return
            except sqlite3.Error as error:  # read-only or full: the hashes are right, only not remembered
                if not _damaged(error) or attempt:
                    return
                self.db = self._set_aside(error)

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
        keys[name] = stamp(st)
    memo = _Memo(cache_dir)
    try:
        known = memo.lookup(keys)
        new = []
        for name, taken in keys.items():
            if name not in known:
                known[name] = _file_sha256(name)
                new.append((name, taken, known[name]))
        memo.remember(new)
    finally:
        memo.close()
    return [known.get(name, "missing") for name in names]


def images_key(paths: Sequence[Path], root: Path | None, cache_dir=None, digests: Sequence[str] | None = None,
               names: Sequence[str] | None = None) -> str:
    """sha256 over the images' names (`names`, else made now) and contents (`digests`, else hashed
    now), in order."""
    h = hashlib.sha256()
    digests = content_hashes(paths, cache_dir) if digests is None else digests
    for name, digest in zip(image_names(paths, root) if names is None else names, digests, strict=True):
        # a name in another encoding's bytes (a file beside an option's images) as those bytes: one key per name
        h.update(f"{name}\0{digest}\n".encode("utf-8", "surrogateescape"))
    return h.hexdigest()
