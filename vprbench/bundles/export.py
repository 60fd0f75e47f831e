"""`vprbench results export`: the chosen runs of a results store as one bundle.

A bundle is a gzipped tar archive laid out like the results store itself:

    MANIFEST.json                                   format, contributor, date, sha256 of every file
    <protocol hash>/<row key>/<run id>.json         the record, byte for byte as stored
    <protocol hash>/<row key>/<run id>.npz          its per-query arrays (top-K indices, similarities)
    methods/<row key>.json                          the method card of the row

It holds no images and no descriptors: what the verifier needs is the top K of every query,
and the ground truth it already has.
"""
from __future__ import annotations

import hashlib
import io
import json
import tarfile
import warnings
from datetime import datetime, timezone
from pathlib import Path

from .. import __version__
from ..errors import VPRBenchError, os_error_message
from ..evaluation.results import card_bytes, card_of
from ..fsutil import CacheError, atomic_write
from ..paths import special_file
from ..text import one_line, shortened

#: the bundle's format; a bundle of a newer version is refused by older verifiers
FORMAT = "vprbench-bundle"
FORMAT_VERSION = 1
MANIFEST = "MANIFEST.json"
CARDS = "methods"


def select_records(records: list[dict], *, run_ids=(), method: str | None = None, dataset: str | None = None) -> list[dict]:
    """The stored records asked for: by run id, or every run of a method (name or label) on a dataset."""
    if run_ids and (method or dataset):
        raise VPRBenchError("results export takes --run ID, or --method M --dataset D, not both.")
    if run_ids:
        by_id = {r["run_id"]: r for r in records}
        missing = [r for r in run_ids if r not in by_id]
        if missing:
            raise VPRBenchError(f"No stored run {missing[0]!r}; 'vprbench leaderboard' and the results folder list "
                                "the runs there are.")
        return [by_id[r] for r in dict.fromkeys(run_ids)]
    if not (method and dataset):
        raise VPRBenchError("results export needs --run ID, or --method M --dataset D.")
    from ..datasets import own_root

    root = own_root(dataset)  # evaluate took a folder's path: its runs are found by it (and refused as own data)
    chosen = [r for r in records if method in (r["method"], r.get("label"))
              and (dataset == r["dataset"] or (root is not None and r.get("dataset_root") == root))]
    if not chosen:
        raise VPRBenchError(f"No stored run of {method!r} on {dataset!r}; run 'vprbench evaluate --method {method} "
                            f"--dataset {dataset}' first.")
    # a folder of one's own may bear a benchmark's name: its runs are left out (alone, refused as such)
    return [r for r in chosen if r.get("dataset_kind") == "benchmark"] or chosen


#: what a record's dataset kind is, in words, where a bundle cannot carry it
KIND_WORDS = {"own": "a folder of your own", "given": "data given by hand (no dataset on disk)"}


def _record_files(record: dict) -> dict[str, bytes]:
    """The record's file, its per-query arrays and its method card, as the store has them."""
    source = Path(record["_source"])
    kind = record.get("dataset_kind")
    if kind != "benchmark":  # a bundle is for re-scoring, which needs the ground truth vprbench ships
        raise VPRBenchError(
            f"Run {record['run_id']} ({record.get('label') or record['method']} on {record['dataset']!r}) is on "
            f"{KIND_WORDS.get(kind, f'a {kind} dataset')}, whose ground truth vprbench does not ship, so no one could "
            "re-score it from a bundle: bundles carry benchmark runs only; share the record and the dataset folder "
            "instead. Nothing was exported.")
    folder = f"{record['protocol']['hash']}/{record['row_key']}"
    section = record.get("per_query") or {}
    if "file" not in section:
        raise VPRBenchError(f"Run {record['run_id']} ({source}) keeps no per-query arrays, which a bundle needs to be "
                            "checked; rerun that evaluation.")
    card = source.parents[2] / CARDS / f"{record['row_key']}.json"
    arrays = source.parent / str(section["file"])
    for path in (source, arrays, card):
        if special_file(path):  # its read would hang (a pipe) or never end (/dev/zero)
            raise VPRBenchError(f"Run {record['run_id']}: {path} is a named pipe, device or socket, not a file: "
                                "remove it (a card is rebuilt; for a record or its arrays, run the evaluation again). "
                                "Nothing was exported.")
    try:
        files = {f"{folder}/{source.name}": source.read_bytes(), f"{folder}/{section['file']}": arrays.read_bytes()}
        # trusted by its name, a file replaced in the store (another run's arrays copied over these) made a bundle
        # every verifier refuses: checked here, as they check it
        if hashlib.sha256(files[f"{folder}/{section['file']}"]).hexdigest() != section.get("sha256"):
            raise VPRBenchError(f"Run {record['run_id']}: its per-query arrays {arrays} do not match the sha256 its "
                                f"record gives (replaced, edited or damaged): delete it and its record {source.name} (an "
                                "evaluation runs it again), or leave that run out (--run). Nothing was exported.")
        files[f"{CARDS}/{card.name}"] = _card(card, record)
        return files
    except OSError as error:
        raise VPRBenchError(f"Run {record['run_id']}: {os_error_message(error)} Nothing was exported.") from None


def _card(path: Path, record: dict) -> bytes:
    """The row's method card as the store has it. The card is what the record decides (verifiers check exactly
    that) and the method's description, so one missing (an older vprbench's store) is rebuilt, and so is one that
    does not describe the record (copied from another row, or edited), said in a warning: verifiers refuse it."""
    if not path.exists():
        return card_bytes(_stored(record))
    data = path.read_bytes()
    why = card_disagreement(data, record)
    if why is None:
        return data
    warnings.warn(f"Method card {path} does not describe run {record['run_id']} "
                  f"({why}: copied or edited); the bundle holds the card rebuilt from the record. "
                  "Delete that file: the next run of that row writes it again.", stacklevel=4)
    return card_bytes(_stored(record))


def card_disagreement(data: bytes, record: dict) -> str | None:
    """How the card `data` fails to describe `record` ("disagrees with the record on label, ..."), None when
    it describes it."""
    try:
        card = json.loads(data)
    except (ValueError, RecursionError):
        card = None
    if not isinstance(card, dict):
        return "is not a JSON object"
    wrong = [key for key, value in card_of(record).items() if key in card and card[key] != value]
    return f"disagrees with the record on {', '.join(wrong)}" if wrong else None


def _stored(record: dict) -> dict:
    """The record as stored (the fields `read_results` adds, '_source' and the like, left out)."""
    return {k: v for k, v in record.items() if not k.startswith("_")}


#: the longest contributor name a results repository keeps
MAX_CONTRIBUTOR = 200


def bundle_bytes(records: list[dict], contributor: str | None = None) -> bytes:
    """The bundle of `records` (read from a results store) as bytes."""
    plain = isinstance(contributor, str) and contributor.strip() and len(contributor) <= MAX_CONTRIBUTOR
    if contributor is not None and not (plain and one_line(contributor) == contributor):
        # shown beside the runs on every leaderboard page; one that is no UTF-8 text failed the site's writing
        raise VPRBenchError(f"--contributor {shortened(one_line(repr(contributor)))} is not a name: give "
                            f"text of at most {MAX_CONTRIBUTOR} characters, in UTF-8, without control characters.")
    files: dict[str, bytes] = {}
    for record in records:
        files.update(_record_files(record))
    created = datetime.now(timezone.utc)
    manifest = {"format": FORMAT, "version": FORMAT_VERSION, "created": created.isoformat(timespec="seconds"),
                "contributor": contributor or "anonymous", "vprbench": __version__,
                "runs": [r["run_id"] for r in records],
                "files": {name: {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
                          for name, data in sorted(files.items())}}
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", format=tarfile.PAX_FORMAT) as archive:
        for name, data in [(MANIFEST, json.dumps(manifest, indent=1, sort_keys=True).encode()), *sorted(files.items())]:
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = len(data), int(created.timestamp()), 0o644
            archive.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def export_bundle(records: list[dict], to: Path, contributor: str | None = None) -> Path:
    """Write the bundle of `records` to `to` (atomically: a kill leaves no half archive)."""
    data = bundle_bytes(records, contributor)
    try:
        return atomic_write(Path(to), data)
    except CacheError as error:
        raise VPRBenchError(f"{error} No bundle was written.") from None
