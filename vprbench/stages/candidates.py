"""Frozen candidates: a retrieval run's top K per query in one HDF5 file, so re-rankers can be
compared on exactly the same candidates.

    indices  int64 (queries, K)    database rows, best first
    scores   float32 (queries, K)  the retriever's similarities
    all_zero uint8 (queries,)      1 for a query whose descriptor is all zero (a failure at every K,
                                   search.AllZero); with the attribute all_zero_database (files of
                                   an earlier vprbench have neither: such queries are then not known)
    attrs    format, version, protocol hash and id, the images' key (their names, order and contents),
             the retriever's spec (JSON) and its identity, the search's info, K

A re-ranking run started from a file (`--candidates FILE`) refuses one exported under another
protocol, on other images (another copy of the dataset: files changed or in another order) or by
another retriever (method, options, weights, a named vocabulary's content, search, store), and names
the file and its sha256 in its record.
"""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from ..errors import VPRBenchError
from ..text import shortened
from ..fsutil import atomic_path, file_sha256, remove_stale, temporaries_of
from ..hashing import canonical_hash, canonical_json
from ..paths import regular_file
from ..search.exact import AllZero, SearchResult
from ..search.row_checks import zero_rows
from .base import repeated_row, unordered_row

FORMAT = "vprbench-candidates"
VERSION = 1
#: the parts of a retriever's spec, beside its method and options, that change its candidates, as a message names them
RETRIEVER_PARTS = {"search": "search", "store_dtype": "store", "files": "files", "found": "cached files",
                   "version": "spec version"}


def retriever_identity(spec) -> dict:
    """What decides the candidates: the spec's retrieval (method, files, search, store, and what its options named
    in the cache: an AnyLoc vocabulary 'urban' fitted in another cache is another retriever), not its stages or K."""
    return {**spec.row_identity(), "stages": [], **({"found": spec.found} if spec.found else {})}


def images_identity(dataset, cache_dir=None) -> str:
    """The dataset's images as the candidates index them: each split's names, order and contents. The protocol
    hash names a benchmark's split, not the copy of its files: candidates of another copy index other images."""
    return canonical_hash(dataset.images_fingerprint(cache_dir))


def write_candidates(path: Path, spec, found, images: str) -> Path:
    """`found` (a SearchResult) of `spec`'s retriever on the images `images` (`images_identity`), written whole or not at all."""
    from ..store.rows_file import hdf5_written

    path = Path(path)
    retriever = spec.model_copy(update={"stages": ()})
    with atomic_path(path) as temporary:
        with hdf5_written(temporary, path) as f:
            f.create_dataset("indices", data=np.asarray(found.indices, dtype=np.int64))
            f.create_dataset("scores", data=np.asarray(found.scores, dtype=np.float32))
            f.attrs.update({"format": FORMAT, "version": VERSION, "protocol_hash": spec.dataset.protocol_hash,
                            "protocol_id": spec.dataset.protocol_id, "images_key": images, "retriever_spec": canonical_json(retriever.to_json()),
                            "retriever_key": canonical_hash(retriever_identity(spec)), "k": int(found.indices.shape[1]),
                            "search": json.dumps(found.info, default=str, sort_keys=True)})
            if found.all_zero is not None:
                f.create_dataset("all_zero", data=np.asarray(found.all_zero.queries, dtype=np.uint8))
                f.attrs["all_zero_database"] = int(found.all_zero.database)
    remove_stale(temporaries_of(path))  # a killed export's half-written file, as atomic_write removes them
    return path


def read_candidates(path, spec, queries: int, database: int, depth: int, images: str) -> dict:
    """The file's candidates for `spec` ({"found": SearchResult, "file", "sha256", "k"}), after checking it
    is a candidates file of this protocol, these images (`images_identity`) and retriever, with every query and at
    least `depth` columns."""
    path = Path(path)
    regular_file(path, "Candidates file")  # a named pipe would hang the read
    if path.is_dir():  # the HDF5 library's message for a folder runs over several lines
        raise VPRBenchError(f"Candidates file {path} is a folder: give the .h5 file 'vprbench candidates export' wrote.")
    try:
        with h5py.File(path, "r") as f:
            attrs = _attributes(f, path)
            if attrs.get("format") != FORMAT:
                raise VPRBenchError(f"{path} is not a vprbench candidates file (make one with 'vprbench candidates "
                                    "export').")
            if not isinstance(attrs.get("version", 0), int):
                raise VPRBenchError(f"Candidates file {path} holds version {shortened(attrs['version'])}, not a vprbench "
                                    "candidates version; export it again.")
            if attrs.get("version", 0) > VERSION:
                raise VPRBenchError(f"Candidates file {path} is from a newer vprbench (version {attrs['version']}); "
                                    "upgrade vprbench.")
            # which data the file indexes is told by its attributes, before its arrays are bounded by this run's
            # size: a file of another dataset is named as such, not as a damaged one to export again
            _check_data(attrs, path, spec, images)
            indices = _numbers(f, "indices", path, "iub", queries * database)
            scores = _numbers(f, "scores", path, "iuf", queries * database)
            flags = _numbers(f, "all_zero", path, "iub", queries) if "all_zero" in f else None
    except FileNotFoundError:
        raise VPRBenchError(f"Candidates file not found: {path}") from None
    except (OSError, KeyError) as error:
        raise VPRBenchError(f"Cannot read candidates file {path} ({error}); export it again.") from None
    if attrs.get("retriever_key") != canonical_hash(retriever_identity(spec)):
        # what else tells the two apart is named on both sides, else both may read 'hog {}': the search (e.g. an
        # hnsw shortlist as deep as the export's --k), the store, the files' contents (weights, cached vocabularies)
        theirs, ours = _json(attrs.get("retriever_spec")), {"found": {}, **spec.to_json()}  # 'found' is written when any
        parts = [p for p in RETRIEVER_PARTS if theirs and {"found": {}, **theirs}.get(p, ours[p]) != ours[p]]
        shown = (f"{shortened(theirs.get('method'))} {shortened(theirs.get('options'))}" + "".join(
            f", {RETRIEVER_PARTS[p]} {shortened(theirs.get(p, {}))}" for p in parts)) if theirs else "an unreadable spec"
        raise VPRBenchError(f"Candidates file {path} was exported by another retriever ({shown}), not this run's "
                            f"{spec.method} {spec.options}" + "".join(f", {RETRIEVER_PARTS[p]} {ours[p]}" for p in parts)
                            + _options_differ(theirs.get("options"), spec.options)
                            + ": export candidates with this run's method, options, search, store and files.")
    if indices.ndim != 2 or indices.shape != scores.shape or indices.shape[0] != queries:
        raise VPRBenchError(f"Candidates file {path} holds {indices.shape} candidates for {queries} queries; export "
                            "it again.")
    if indices.shape[1] < depth:
        raise VPRBenchError(f"Candidates file {path} holds the top {indices.shape[1]} per query, but this run "
                            f"needs {depth} (--rerank-k): give --rerank-k <= {indices.shape[1]} or export with "
                            f"--k {depth}.")
    if not np.issubdtype(indices.dtype, np.integer) or indices.min() < 0 or indices.max() >= database \
            or not np.isfinite(scores).all():
        raise VPRBenchError(f"Candidates file {path} holds indices outside the {database} database images or "
                            "scores that are not finite; export it again.")
    # a hand-edited file would otherwise reach the re-ranker (blamed as "fix the stage") or silently change which
    # candidates count as first (alpha-QE's n, the order count ties keep): the export writes neither
    query = repeated_row(indices)
    unordered = unordered_row(scores)
    if query is not None or unordered is not None:
        fault = (f"one database image twice for query {query}" if query is not None
                 else f"the candidates of query {unordered} not best first (scores must not increase)")
        raise VPRBenchError(f"Candidates file {path} holds {fault}; export it again.")
    info = _json(attrs.get("search"))  # what the export's search reported; its dim goes into the record
    if type(info.get("dim")) is not int or info["dim"] < 1:
        raise VPRBenchError(f"Candidates file {path}: its search attribute does not give the descriptors' dimension "
                            "(dim); export it again.")
    info["from_candidates"] = str(path)
    found = SearchResult(scores[:, :depth].astype(np.float32), indices[:, :depth].astype(np.int64), info,
                         _all_zero(path, flags, attrs.get("all_zero_database"), queries, database))
    return {"found": found, "file": str(path.resolve()), "sha256": file_sha256(path), "k": int(indices.shape[1])}


def _check_data(attrs: dict, path: Path, spec, images: str) -> None:
    """Refuse a file exported on another protocol, or on another copy of this run's dataset."""
    if attrs.get("protocol_hash") != spec.dataset.protocol_hash:
        raise VPRBenchError(f"Candidates file {path} was exported under protocol {attrs.get('protocol_id')} "
                            f"({attrs.get('protocol_hash')}), not this run's {spec.dataset.protocol_id} "
                            f"({spec.dataset.protocol_hash}): export candidates on this dataset and protocol.")
    if attrs.get("images_key") != images:  # same protocol, another copy: its rows index other images
        raise VPRBenchError(f"Candidates file {path} was exported on " + ("other images of " if attrs.get("images_key")
                            else "images it does not name (an earlier vprbench's file) of ") + f"{spec.dataset.name} "
                            "than this run's (files changed or in another order): export candidates from this copy "
                            "of the dataset.")


def _numbers(f: h5py.File, name: str, path: Path, kinds: str, most: int) -> np.ndarray:
    """Dataset `name` of the file, read only after its header is checked: real numbers of `kinds`
    (numpy kind letters), stored in this file, at most `most` of them (the run's queries x database
    images bound every array the export writes: a header claiming more would be read whole first)."""
    from ..store.rows_file import stored_inside

    link = f.get(name, getlink=True)
    if link is not None and not isinstance(link, h5py.HardLink):
        # a link is resolved by opening what it names: another file (outside the sha256 the record gives), a
        # named pipe (a hang); the export writes its arrays in the file
        target = f"{link.filename}:{link.path}" if isinstance(link, h5py.ExternalLink) else link.path
        raise VPRBenchError(f"Candidates file {path}: its {name} holds a link to {shortened(target)}, not at most "
                            f"{most:,} real numbers stored in the file; export it again.")
    data = f.get(name)
    if not isinstance(data, h5py.Dataset) or data.dtype.kind not in kinds or not stored_inside(data) \
            or data.size > most:
        held = (f"{data.dtype} {data.shape}" + ("" if stored_inside(data) else " stored in another file")
                if isinstance(data, h5py.Dataset) else "no dataset" if data is None else f"a {type(data).__name__}")
        raise VPRBenchError(f"Candidates file {path}: its {name} holds {shortened(held)}, not at most {most:,} real "
                            "numbers stored in the file; export it again.")
    return data[...]


def _all_zero(path: Path, flags, count, queries: int, database: int):
    """The file's all-zero rows (search.AllZero), None when it has none (an earlier vprbench's file)."""
    if flags is None and count is None:
        return None
    if not isinstance(flags, np.ndarray) or flags.shape != (queries,) or flags.dtype.kind not in "biu" \
            or type(count) is not int or not 0 <= count <= database:
        raise VPRBenchError(f"Candidates file {path}: its all-zero rows (all_zero, all_zero_database) are not one "
                            f"flag per query and a count within the {database} database images; export it again.")
    return AllZero(flags != 0, count)


def _attributes(f, path: Path) -> dict:
    """The file's attributes, each one value (text decoded, numbers as Python's): a hand-edited one holding
    an array or bytes that are not UTF-8 would otherwise be a traceback in a comparison far from the file."""
    found = {}
    for key in f.attrs:
        try:
            value = f.attrs[key]
            value = value.item() if isinstance(value, np.generic) else value
            found[key] = value.decode() if isinstance(value, bytes) else value
        except (UnicodeDecodeError, OSError, TypeError) as error:
            raise VPRBenchError(f"Candidates file {path}: its attribute {shortened(key)} cannot be read ({error}); "
                                "export it again.") from None
        if not isinstance(found[key], (str, int, float)):
            raise VPRBenchError(f"Candidates file {path}: its attribute {shortened(key)} holds "
                                f"{type(found[key]).__name__} {shortened(found[key])}, not one value; export it again.")
    return found


def _options_differ(theirs, ours: dict) -> str:
    """The options a file's retriever and this run's set apart, named: the file's are shown cut short
    (AnyLoc's pca_on comes after the first four)."""
    if not isinstance(theirs, dict):
        return ""
    unset = object()
    differ = sorted(k for k in {*theirs, *ours} if theirs.get(k, unset) != ours.get(k, unset))
    shown = [f"{k} {shortened(repr(theirs[k])) if k in theirs else 'unset'} in the file, "
             f"{shortened(repr(ours[k])) if k in ours else 'unset'} in this run" for k in differ]
    return f"; options that differ: {'; '.join(shown)}" if shown else ""


def _json(text) -> dict:
    """The JSON object `text` holds, else {} (not JSON, not an object, or nested too deeply to parse)."""
    try:
        found = json.loads(text) if isinstance(text, str) else None
    except (ValueError, RecursionError):
        return {}
    return found if isinstance(found, dict) else {}


#: how far a file's score may lie from the one computed again: the search's grid (2^-16) and float32 products
#: of long rows are far inside it; another query's row, another retriever's scores are far outside
SCORE_SLACK = 1e-3
#: queries whose rows are read at once for that check (fewer when the budget is small)
CHECK_QUERIES = 256


def check_scores(path, found, database, queries, compare: str, budget: int) -> None:
    """Each query's first and last candidate in the file scored again from the retriever's descriptors (as its
    search saw them: `database`, `queries` row sources), two database rows per query. A file whose rows were moved
    between queries, whose scores or all-zero flags were edited or which another retriever wrote under this one's
    name was re-ranked and stored as this run's, its record served for it; the file cannot say so, the descriptors
    can. The count of all-zero database rows (a count in the record, no metric) is not read again: it takes a pass
    over the database."""
    if compare not in ("cosine", "mean-absolute-difference"):  # a plugin's own distance: not known here
        return
    columns = [0, found.indices.shape[1] - 1]
    # a query's row and its two candidates' in float64, and sad's differences: within a tenth of the run's budget
    step = max(1, min(CHECK_QUERIES, budget // 10 // (48 * max(1, queries.dim))))
    for lo in range(0, found.indices.shape[0], step):
        hi = min(lo + step, found.indices.shape[0])
        rows = queries.read_rows(lo, hi)
        flags = None if found.all_zero is None else found.all_zero.queries[lo:hi]
        wrong = None if flags is None else zero_rows(rows, "Query", lo) != flags  # a flagged query counts as failed
        if wrong is not None and wrong.any():
            q = lo + int(np.flatnonzero(wrong)[0])
            said, found_now = ("all zero", "is not") if flags[q - lo] else ("not all zero", "is all zero")
            raise VPRBenchError(f"Candidates file {path}: its all_zero flags say query {q}'s descriptor is {said}, but "
                                f"this run's {found_now}: export it again.")
        rows = rows.astype(np.float64)
        wanted = found.indices[lo:hi, columns]
        unique, at = np.unique(wanted, return_inverse=True)
        images = database.read_rows_at(unique).astype(np.float64)[at.reshape(wanted.shape)]
        if compare == "cosine":
            again = np.einsum("qd,qcd->qc", rows, images)
        else:  # sad's scores are minus the distance
            again = -np.abs(rows[:, None, :] - images).mean(-1)
        stored = found.scores[lo:hi, columns].astype(np.float64)
        off = np.abs(again - stored) > SCORE_SLACK * np.maximum(1.0, np.abs(again))
        if off.any():
            q, c = np.argwhere(off)[0]
            raise VPRBenchError(f"Candidates file {path}: query {lo + q}'s candidate {int(wanted[q, c])} has the score "
                                f"{stored[q, c]:.6g} there, but {again[q, c]:.6g} from this run's descriptors: its "
                                "rows are not this retriever's candidates for these queries (edited, or rows of "
                                "another order or retriever); export it again.")
