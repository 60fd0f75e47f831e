"""A bundle archive read into memory member by member, never extracted: a member must be a
regular file whose name is one of the bundle's own (a protocol hash, a row key and a run id, or a
method card; folder entries are passed over), so no path can climb out of a folder; the bytes
read are bounded (an archive bomb stops at the bound); the manifest's sha256 sums must match
every file, and list every file."""
from __future__ import annotations

import gzip
import hashlib
import io
import json
import re
import tarfile
import zlib
from pathlib import Path, PurePosixPath

from ..errors import VPRBenchError
from ..paths import regular_file
from ..text import shortened
from .export import CARDS, FORMAT, FORMAT_VERSION, MANIFEST

#: the most bytes a bundle may unpack to (an MSLS-size run is ~10 MB); `--max-size` raises it
MAX_BYTES = 1 << 30
MAX_MEMBERS = 200_000
#: the most problems of a manifest named (the rest counted): a manifest listing a million names is one line
SHOWN = 5
_HEX = r"[0-9a-f]{16}"
_RUN = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,80}"
#: where a record or its arrays lie: <protocol hash>/<row key>/<run id>.json or .npz (in a bundle and a repository)
RECORD_NAME = re.compile(rf"^({_HEX})/({_HEX})/({_RUN})\.(json|npz)$")
_CARD = re.compile(rf"^{CARDS}/({_HEX})\.json$")


class BundleError(VPRBenchError):
    """The archive as a whole cannot be read as a bundle (no record of it can be trusted)."""


class _Bounded(io.RawIOBase):
    """A reader that fails once more than `limit` bytes came out of it (a bomb stops here)."""

    def __init__(self, inner, limit: int, where: str):
        self.inner, self.left, self.limit, self.where = inner, limit, limit, where

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        data = self.inner.read(min(len(buffer), self.left + 1))
        self.left -= len(data)
        if self.left < 0:
            raise BundleError(self.over())
        buffer[: len(data)] = data
        return len(data)

    def over(self) -> str:
        return (f"{self.where}: it unpacks to more than the bound of {self.limit / 2**20:g} MiB "
                "(an archive bomb, or a bundle too big: raise --max-size).")


def read_members(path: Path, max_bytes: int = MAX_BYTES) -> dict[str, bytes]:
    """Every member of the bundle at `path`, by name, read within `max_bytes`; a BundleError
    naming the archive and the member at fault otherwise."""
    where = str(path)
    regular_file(path, "The bundle")  # a named pipe would hang the read
    try:
        raw = open(path, "rb")
    except OSError as error:
        raise BundleError(f"Cannot read the bundle {path} ({error.strerror or error}).") from None
    with raw:
        magic = raw.read(2)
        raw.seek(0)
        inner = gzip.GzipFile(fileobj=raw) if magic == b"\x1f\x8b" else raw
        stream = _Bounded(inner, max_bytes, where)
        members: dict[str, bytes] = {}
        total = 0  # the sizes members declare, together: what reading them allocates
        try:
            with tarfile.open(fileobj=io.BufferedReader(stream), mode="r|") as archive:
                for count, info in enumerate(archive):
                    if count >= MAX_MEMBERS:  # folder entries too: tarfile keeps every entry it reads
                        raise BundleError(f"{where}: more than {MAX_MEMBERS} members.")
                    name = _member_name(info, where)
                    if name is None:  # a folder entry ('tar czf' writes them): nothing to read or trust
                        continue
                    if name in members:
                        raise BundleError(f"{where}: member {name} appears twice.")
                    if info.size > max_bytes:
                        raise BundleError(f"{where}: member {name} claims {info.size} bytes, over the bound of "
                                          f"{max_bytes / 2**20:g} MiB (an archive bomb, or a bundle too big: "
                                          "raise --max-size).")
                    total += max(info.size, 0)
                    if total > max_bytes:  # the members together, however few bytes of the archive hold them
                        raise BundleError(stream.over())
                    handle = archive.extractfile(info)
                    members[name] = handle.read() if handle else b""
        # zlib.error: a damaged deflate stream met inside a member, past the headers tarfile reads itself
        except (tarfile.TarError, EOFError, OSError, gzip.BadGzipFile, ValueError, zlib.error) as error:
            raise BundleError(f"{where} is not a readable bundle archive ({type(error).__name__}: {error}).") from None
    return members


def _member_name(info: tarfile.TarInfo, where: str) -> str | None:
    """A member's bundle name ('./' dropped), None for a folder entry; else a BundleError."""
    name = info.name
    parts = PurePosixPath(name).parts
    if name.startswith(("/", "\\")) or ".." in parts or "\\" in name or re.match(r"^[A-Za-z]:", name):
        raise BundleError(f"{where}: member {shortened(repr(name))} escapes the folder it would be written to; "
                          "refused.")
    if info.isdir():  # nothing is ever extracted: a folder entry inside the bundle is harmless, and ignored
        return None
    name = "/".join(parts)  # PurePosixPath drops '.' parts and repeated slashes
    if not info.isreg() or info.issparse():  # a sparse member's holes unpack from nothing: a bomb past the bound
        kind = "link" if info.issym() or info.islnk() else "sparse file" if info.isreg() else "special file"
        raise BundleError(f"{where}: member {shortened(repr(name))} is a {kind}, not a regular file; refused.")
    if name != MANIFEST and not (RECORD_NAME.match(name) or _CARD.match(name)):
        raise BundleError(f"{where}: member {shortened(repr(name))} is no file a bundle holds (records, per-query "
                          "arrays, method cards, the manifest); refused.")
    return name


def _json(data: bytes):
    """JSON from a bundle, in UTF-8 without a byte order mark as every reader of a results store or
    repository reads it (json.loads of bytes takes UTF-16 and a BOM too: a record 'ok' here, skipped by
    the site); nesting too deep to parse (a hostile file) is a ValueError like any other."""
    try:
        return json.loads(data.decode("utf-8"))
    except RecursionError:
        raise ValueError("nested too deeply") from None


def check_manifest(members: dict[str, bytes], where: str) -> dict:
    """The manifest, checked: format and version known, every file listed with its sha256 sum."""
    if MANIFEST not in members:
        raise BundleError(f"{where}: it has no {MANIFEST}; it is not a vprbench bundle.")
    try:
        manifest = _json(members[MANIFEST])
        files = manifest["files"]
        if not isinstance(files, dict):
            raise TypeError("files is not a table")
    except (ValueError, KeyError, TypeError) as error:
        raise BundleError(f"{where}: {MANIFEST} is not a bundle manifest ({type(error).__name__}: {error}).") from None
    if manifest.get("format") != FORMAT:
        raise BundleError(f"{where}: {MANIFEST} says format {shortened(repr(manifest.get('format')))}, not {FORMAT}.")
    version = manifest.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:  # JSON true is no version
        raise BundleError(f"{where}: {MANIFEST} says format version {shortened(repr(version))}, which no vprbench writes; it is "
                          "damaged or not a vprbench bundle: export it again.")
    if version > FORMAT_VERSION:
        raise BundleError(f"{where}: bundle format version {version!r} is from a newer vprbench (this one reads up to "
                          f"{FORMAT_VERSION}); upgrade vprbench.")
    problems = []
    for name in sorted(set(members) - {MANIFEST} - set(files)):
        problems.append(f"{where}: {name} is not listed in {MANIFEST}.")
    for name, entry in sorted(files.items()):
        if name not in members:  # any text a manifest gives: a few names, each cut, make a line one can read
            problems.append(f"{where}: {shortened(name)} is listed in {MANIFEST} but missing.")
        elif not isinstance(entry, dict) or hashlib.sha256(members[name]).hexdigest() != entry.get("sha256"):
            problems.append(f"{where}: {name} does not match its sha256 sum in {MANIFEST} (changed after export).")
    if problems:
        more = f" And {len(problems) - SHOWN} more." if len(problems) > SHOWN else ""
        raise BundleError(" ".join(problems[:SHOWN]) + more)
    return manifest
