"""The results store: one record per run, found by identity.

    <cache>/results/<protocol hash>/<row key>/<run id>.json    the record (typed, validated on read)
                                              <run id>.npz     its per-query arrays (numpy, no pickle)
    <cache>/results/methods/<row key>.json                     the method card: what the row's method is

A spec's records are a directory listing away (`find_result`), never a scan of every record.
Every file is written to a temporary name and renamed, so concurrent writers, kills and full
disks never leave a partial or mixed record. Records of vprbench 0.2 (flat files in
<cache>/results/) are moved, unchanged, into their identity folder the first time the store is
read, and upgraded in memory on every read (`record.upgrade`).
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError, os_error_message, require
from ..fsutil import CacheError, atomic_write, is_temporary, lock, remove_stale, said_of, warn_once, write_once
from ..paths import cache_root, special_file
from .record import OPTIONAL_FIELDS, PER_QUERY_FIELDS, per_query_arrays_in, validated

CARDS = "methods"
#: how this folder is laid out (a newer vprbench that lays it out otherwise bumps the version)
LAYOUT = {"layout": "vprbench-results", "version": 1}
LAYOUT_FILE = "LAYOUT"  # JSON; not *.json, which would be a record
_HEX = re.compile(r"^[0-9a-f]{16}$")


def results_dir(cache_dir=None) -> Path:
    """<cache>/results. Given the results folder itself (it holds LAYOUT), reading would find
    nothing and writing would nest a second store: both are refused, naming the cache folder."""
    root = cache_root(cache_dir)
    if (root / LAYOUT_FILE).is_file() and not (root / "results").exists():
        raise VPRBenchError(f"{root} is a results folder, not a cache folder: pass the cache folder that holds it, "
                            f"{root.parent}.")
    return root / "results"


def run_folder(protocol_hash: str, row_key: str, cache_dir=None) -> Path:
    """Where the runs of one row on one protocol live (both names are hex digests, never data)."""
    for name in (protocol_hash, row_key):
        if not _HEX.match(str(name)):
            raise VPRBenchError(f"{name!r} is not a protocol hash or row key (16 hex digits).")
    return results_dir(cache_dir) / protocol_hash / row_key


# ---------------------------------------------------------------- writing
def check_layout(root: Path) -> None:
    """A results folder laid out by another vprbench (its LAYOUT file) is refused, never rewritten."""
    path = root / LAYOUT_FILE
    if not path.is_file():
        return
    try:
        found = json.loads(path.read_text(encoding="utf-8"))
        layout, version = found["layout"], int(found["version"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise VPRBenchError(f"{path} is not a vprbench results layout file ({type(error).__name__}); fix it, or use "
                            "another --cache-dir. Nothing was changed.") from None
    if layout != LAYOUT["layout"] or version > LAYOUT["version"]:
        raise VPRBenchError(f"The results folder {root} was written by another vprbench ({layout} version {version}; "
                            f"this one reads {LAYOUT['layout']} up to {LAYOUT['version']}): upgrade vprbench, or use "
                            "another --cache-dir. Nothing was changed.")


def save_result(record: dict, cache_dir=None) -> Path:
    """Store one record (per-query arrays in an .npz beside it) in its identity folder, and the
    method card of its row; returns the JSON path. Safe with any number of concurrent writers."""
    require(record, dict, "save_result takes a result record (the dict evaluate returns)")
    record = {k: v for k, v in record.items() if not k.startswith("_")}
    checked = validated(record, f"the record of run {record.get('run_id')!r}")
    folder = run_folder(checked["protocol"]["hash"], checked["row_key"], cache_dir)
    stem = checked["run_id"]
    check_layout(results_dir(cache_dir))
    try:
        write_once(results_dir(cache_dir) / LAYOUT_FILE, json.dumps(LAYOUT))
        section = record.get("per_query")
        if section and "file" not in section:
            arrays = _per_query_arrays(section)
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            data = buffer.getvalue()
            atomic_write(folder / f"{stem}.npz", data)
            record["per_query"] = {"file": f"{stem}.npz", "sha256": hashlib.sha256(data).hexdigest(),
                                   "k": section["k"], "queries": len(section["first_positive_rank"]),
                                   "fields": list(arrays)}
        _write_card(record, cache_dir)  # before the record: a record is there only with its card (export needs it)
        atomic_write(folder / f"{stem}.json", json.dumps(record, sort_keys=True, indent=1).encode())
        # what writers killed here left: temporary files, and arrays whose record never came
        remove_stale(p for p in folder.iterdir()
                     if is_temporary(p) or (p.suffix == ".npz" and not p.with_suffix(".json").exists()))
    except OSError as error:
        raise VPRBenchError(f"{os_error_message(error, folder)} The result was not stored.") from None
    except CacheError as error:
        raise VPRBenchError(f"{error} The result was not stored.") from None
    return folder / f"{stem}.json"


def _write_card(record: dict, cache_dir) -> None:
    """What the row's method is, kept apart from its results (written once per row)."""
    write_once(results_dir(cache_dir) / CARDS / f"{record['row_key']}.json", card_bytes(record))


def card_bytes(record: dict) -> bytes:
    """The method card of the record's row, as `save_result` writes it: what the record decides,
    and the installed method's description (so a card lost or never written is rebuilt the same)."""
    from ..methods.registry import available_methods

    entry = available_methods().get(record["method"])
    card = {**card_of(record), "description": entry.description if entry else "",
            "source": entry.source if entry else "unknown"}
    return json.dumps(card, sort_keys=True, indent=1).encode()


def card_of(record: dict) -> dict:
    """The part of a row's method card that its record decides (a contributed card is checked against it)."""
    spec = record["spec"]
    return {"row_key": record["row_key"], "method": record["method"], "label": record.get("label"),
            "options": spec["options"], "given": spec["given"], "files": spec["files"], "search": spec["search"],
            "stages": spec["stages"], "store_dtype": spec["store_dtype"],
            "weights": (record.get("provenance") or {}).get("weights")}


def _per_query_arrays(section: dict) -> dict[str, np.ndarray]:
    return {
        "database_indices": np.asarray(section["database_indices"], dtype=np.int32).reshape(-1, section["k"]),
        "similarities": np.asarray(section["similarities"], dtype=np.float32).reshape(-1, section["k"]),
        "first_positive_rank": np.asarray(section["first_positive_rank"], dtype=np.int32),
        "positives": np.asarray(section["positives"], dtype=np.int32),
        **{name: np.asarray(section[name], dtype=np.int32) for name in OPTIONAL_FIELDS if name in section},
    }


# ---------------------------------------------------------------- reading
def read_record(path: Path) -> dict:
    """One record file, upgraded and validated; a VPRBenchError naming the file otherwise."""
    if special_file(path):  # a pipe would hang every listing of the store, /dev/zero fill the memory
        raise VPRBenchError(f"{path} is not a readable JSON record (it is a named pipe, device or socket).")
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise VPRBenchError(f"{path} is not a readable JSON record ({type(error).__name__}).") from None
    record = validated(data, str(path))
    record["_source"] = os.path.abspath(path)  # absolute: messages name it whole, pages cut it (escape.public)
    return record


def records_in(folder: Path, skipped: list | None = None) -> list[dict]:
    found = []
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            found.append(read_record(path))
        except VPRBenchError as error:
            warnings.warn(f"{error} Skipped (nothing was deleted).", stacklevel=3)
            if skipped is not None:
                skipped.append(path)
    return found


def oldest_first(records: list[dict]) -> list[dict]:
    return sorted(records, key=lambda r: (str(r.get("created", "")), str(r.get("run_id", ""))))


def read_results(cache_dir=None, skipped: list | None = None) -> list[dict]:
    """Every stored record, oldest first. A file that is not a whole record this version reads is
    named in a warning and skipped (never deleted), its path appended to `skipped` when given."""
    require(skipped, (list, type(None)), "read_results' skipped takes a list to append skipped files to, or None")
    migrate_legacy(cache_dir)
    root = results_dir(cache_dir)
    check_layout(root)
    legacy = cache_root(cache_dir) / "results.jsonl"
    if legacy.is_file():
        warnings.warn(f"{legacy} holds vprbench 0.1 records, which carry no protocol or weights provenance and are "
                      "no longer read; rerun those evaluations (the file is left as it is).", stacklevel=2)
    records = []
    for folder in sorted(root.glob("*/*")) if root.is_dir() else []:
        if folder.is_dir() and folder.parent.name != CARDS:
            records += records_in(folder, skipped)
    return oldest_first(records)


def per_query(record: dict) -> dict[str, np.ndarray] | None:
    """The record's per-query arrays (from the record itself or its .npz), or None when the
    record has none or its file is missing or damaged (with a warning)."""
    require(record, dict, "per_query takes a result record (from read_results, find_result or evaluate)")
    section = record.get("per_query")
    if not section:
        return None
    if not isinstance(section, dict):  # a record not validated (read by hand) may hold anything here
        warnings.warn(f"The per-query section of run {record.get('run_id')} is {type(section).__name__}, not a table; "
                      "its statistics and figures are skipped.", stacklevel=2)
        return None
    if "file" not in section:
        try:
            return _in_range(record, _per_query_arrays(section))
        except (ValueError, TypeError, KeyError) as error:
            warnings.warn(f"The per-query data of run {record.get('run_id')} is unusable ({error}); its statistics "
                          "and figures are skipped.", stacklevel=2)
            return None
    source = record.get("_source")
    name = str(section["file"])
    if not source:  # the .npz lies beside the record file, which only a record read from the store knows
        warnings.warn(f"Run {record.get('run_id')}'s per-query data is in {name} beside its record, but this record "
                      "was not read from the store: read it with read_results or find_result.", stacklevel=2)
        return None
    path = Path(source).parent / name
    try:
        if Path(name).name != name or not name.endswith(".npz"):
            raise ValueError(f"its file {name!r} is not a file name beside the record")
        if special_file(path):
            raise ValueError("it is a named pipe, device or socket, not a file")
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != section.get("sha256"):
            raise ValueError("its content does not match the record's sha256")
        # the sha256 proves the file is the one its record names, not that it is an .npz: a record and
        # file made together may hold any bytes, or an array header claiming terabytes
        arrays = per_query_arrays_in(data)
        _in_range(record, arrays)
    except (OSError, ValueError, KeyError, AttributeError, TypeError) as error:
        warnings.warn(f"Per-query data {path} of run {record.get('run_id')} is unreadable ({error}); "
                      "its statistics and figures are skipped.", stacklevel=2)
        return None
    return arrays


def check_kinds(arrays: dict[str, np.ndarray]) -> None:
    """The arrays hold what every reader computes with: (queries, K) whole-number indices, as
    many finite similarities, one whole number per query in each other array; a ValueError
    naming the first misfit otherwise (an .npz from elsewhere may hold strings, NaN or any shape,
    which would fail deep in a metric instead of here)."""
    indices, similarities = arrays["database_indices"], arrays["similarities"]
    if indices.ndim != 2 or indices.dtype.kind not in "iu":
        raise ValueError(f"its top-K indices are {indices.dtype} {indices.shape}, not (queries, K) whole numbers")
    if similarities.shape != indices.shape or similarities.dtype.kind not in "iuf" or \
            not np.isfinite(similarities).all():
        raise ValueError(f"its similarities are {similarities.dtype} {similarities.shape}, not {indices.shape} "
                         "finite numbers (one per top-K index)")
    for name in (*PER_QUERY_FIELDS[2:], *OPTIONAL_FIELDS):
        found = arrays.get(name)
        if found is not None and (found.dtype.kind not in "iu" or found.shape != indices.shape[:1]):
            raise ValueError(f"its {name} array is {found.dtype} {found.shape}, not one whole number per query "
                             f"({indices.shape[0]})")


def _in_range(record: dict, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays, if they fit the record: (queries, K) top lists of database indices in range,
    first-positive ranks within 0..K; a ValueError naming the first misfit otherwise (an index
    past the database would reach an image list at publish)."""
    counts = record.get("counts") or {}
    queries, database = counts.get("queries"), counts.get("database")
    indices, first = arrays["database_indices"], arrays["first_positive_rank"]
    if indices.ndim != 2 or indices.shape[0] != queries or arrays["similarities"].shape != indices.shape or \
            first.shape != (queries,) or arrays["positives"].shape != (queries,):
        raise ValueError(f"its arrays have shapes {indices.shape}, {arrays['similarities'].shape}, {first.shape}, "
                         f"not those of the record's {queries} queries")
    check_kinds(arrays)
    if indices.size and (indices.min() < 0 or not isinstance(database, int) or indices.max() >= database):
        bad = int(np.flatnonzero((indices < 0).any(axis=1) | (indices >= (database or 0)).any(axis=1))[0])
        raise ValueError(f"query {bad} lists a database index outside the record's {database} database images")
    if first.size and (first.min() < 0 or first.max() > indices.shape[1]):
        raise ValueError(f"a first-positive rank lies outside 0..{indices.shape[1]}")
    return arrays


# ---------------------------------------------------------------- records of vprbench 0.2
def migrate_legacy(cache_dir=None) -> int:
    """Move 0.2's flat records (results/*.json and their .npz) into their identity folders,
    unchanged; returns how many moved. A file that cannot be upgraded stays where it is (named
    in a warning)."""
    root = results_dir(cache_dir)
    # one already named stays where it is: not read (nor said) again by every look-up of a command
    flat = [path for path in sorted(root.glob("*.json")) if not said_of(path)] if root.is_dir() else []
    if not flat:
        return 0
    moved = 0
    with lock(root / ".migrate.lock", timeout=120, what=f"the results store {root}", announce=False):
        for path in flat:
            if not path.is_file():  # moved by another process meanwhile
                continue
            try:
                record = validated(json.loads(path.read_text(encoding="utf-8")), str(path))
            except (OSError, ValueError, VPRBenchError) as error:
                warn_once(path, f"{path} stays where it is: {error}", stacklevel=3)
                continue
            folder = run_folder(record["protocol"]["hash"], record["row_key"], cache_dir)
            folder.mkdir(parents=True, exist_ok=True)
            section = record.get("per_query") or {}
            npz = section.get("file")
            if npz and Path(npz).name == npz and (root / npz).is_file():
                os.replace(root / npz, folder / npz)
            os.replace(path, folder / path.name)
            moved += 1
    return moved
