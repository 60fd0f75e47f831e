"""`vprbench results import-vpr-bench`: VPR-Bench's precomputed matches as vprbench records.

VPR-Bench publishes, per dataset and method, `precomputed_matches/<dataset>/<method>/
precomputed_data_corrected.npy`: a numpy object array of 6, pickled by Python 2 (protocol 2):

    0  query indices                      int64 (Q,)
    1  the matched database index          int64 (Q,)
    2  its similarity                      float64 (Q,)
    3  the query x database similarities   float64 (Q, N)
    4  encoding time, 5  matching time     seconds

The file is read by the restricted .npy reader (datasets/layouts/npy.py: only numpy's own
array, dtype and scalar reconstruction; nothing else a pickle names is ever loaded, so no code
runs), then checked to be exactly that. The top K of each query come from its row of the
similarity matrix (ties: the lower database index first, as VPR-Bench's argmax), and every
metric is computed against vprbench's ground truth of the dataset's default protocol: the
record is vprbench's score of VPR-Bench's matches, marked `imported` with the method's name
as VPR-Bench gives it.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from ..methods import Method
from ..paths import regular_file

FILE = "precomputed_data_corrected.npy"
SOURCE = "VPR-Bench"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}$")
_EXPECTED = ("a VPR-Bench precomputed-matches file: an object array of 6 (query indices, matched indices, "
             "their scores, the query x database similarity matrix, encoding and matching times)")


@dataclass(frozen=True)
class Precomputed:
    query_indices: np.ndarray
    matched: np.ndarray
    scores: np.ndarray
    similarity: np.ndarray
    encoding_s: float
    matching_s: float


def read_precomputed(path: Path) -> Precomputed:
    """The six parts of a precomputed-matches file, each checked; a VPRBenchError naming the file otherwise."""
    from ..datasets.layouts.npy import read_npy

    path = Path(path)
    try:
        found = read_npy(path, "VPR-Bench precomputed matches", _EXPECTED)
    except OSError as error:
        raise VPRBenchError(f"Cannot read {path} ({error.strerror or error}).") from None

    def refuse(why: str):
        raise VPRBenchError(f"{path} is not {_EXPECTED}: {why}.")

    if found.dtype != object or found.shape != (6,):
        refuse(f"it holds a {found.dtype} array of shape {found.shape}")
    parts = list(found)
    for i, (kind, ndim) in enumerate([("iu", 1), ("iu", 1), ("f", 1), ("f", 2)]):
        part = parts[i]
        if not isinstance(part, np.ndarray) or part.dtype.kind not in kind or part.ndim != ndim:
            shown = f"{part.dtype} {part.shape}" if isinstance(part, np.ndarray) else type(part).__name__
            refuse(f"part {i} is {shown}, not a {ndim}-d {'whole-number' if kind == 'iu' else 'float'} array")
    queries, similarity = parts[0], parts[3]
    if not (len(parts[1]) == len(parts[2]) == len(queries) == similarity.shape[0]):
        refuse(f"its parts disagree on the number of queries ({len(queries)}, {len(parts[1])}, {len(parts[2])}, "
               f"{similarity.shape[0]})")
    for i in (4, 5):
        if not isinstance(parts[i], (int, float, np.integer, np.floating)) or isinstance(parts[i], bool):
            refuse(f"part {i} is a {type(parts[i]).__name__}, not a time in seconds")
    if not np.isfinite(similarity).all() or not np.isfinite(parts[2]).all():
        refuse("its similarities hold NaN or infinity")
    return Precomputed(queries.astype(np.int64), parts[1].astype(np.int64), parts[2].astype(np.float64),
                       similarity.astype(np.float64, copy=False), float(parts[4]), float(parts[5]))


def method_files(folder: Path) -> list[tuple[str, Path]]:
    """(VPR-Bench method name, file) for a folder of method folders, or one method's own folder."""
    folder = Path(folder)
    if not folder.is_dir():
        state = "is a file, not a folder" if folder.exists() else "does not exist"
        raise VPRBenchError(f"VPR-Bench folder {folder} {state}: give the folder of its precomputed matches "
                            f"(precomputed_matches/<dataset>/, or one method's folder in it).")
    found = [(folder.name, folder / FILE)] if (folder / FILE).exists() else \
        [(p.parent.name, p) for p in sorted(folder.glob(f"*/{FILE}"))]
    # a named pipe there (an archive of VPR-Bench's folders can carry one) would hang the read, a device never end it
    for _, path in found:
        regular_file(path, "VPR-Bench precomputed matches")
    if not found:
        raise VPRBenchError(f"{folder} holds no {FILE} (expected precomputed_matches/<dataset>/<method>/{FILE}).")
    for name, path in found:
        if not _NAME.match(name):
            raise VPRBenchError(f"{path.parent}: {name!r} is not a method name this importer takes (letters, digits, "
                                "_ . + -, up to 64); rename the folder.")
    return found


def top_k(similarity: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the k most similar columns, best first (ties: the lower index first)."""
    order = np.argsort(-similarity, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(similarity, order, axis=1), order


def aligned(found: Precomputed, n_queries: int, n_database: int, path: Path) -> Precomputed:
    """`found` in query order, checked against the protocol's counts and against its own matrix."""
    q = found.query_indices
    if found.similarity.shape != (n_queries, n_database):
        raise VPRBenchError(f"{path}: its similarity matrix is {found.similarity.shape[0]} x {found.similarity.shape[1]}, "
                            f"but the protocol has {n_queries} queries x {n_database} database images.")
    if not np.array_equal(np.sort(q), np.arange(n_queries)):
        missing = sorted(set(range(n_queries)) - set(q.tolist()))
        raise VPRBenchError(f"{path}: its query indices are not each of the {n_queries} queries once"
                            + (f" (query {missing[0]} is missing)." if missing else " (some repeat or are out of range)."))
    if found.matched.min() < 0 or found.matched.max() >= n_database:
        raise VPRBenchError(f"{path}: a matched index lies outside the {n_database} database images.")
    order = np.argsort(q)
    sim = found.similarity[order]
    matched = found.matched[order]
    best = sim.max(axis=1)
    chosen = sim[np.arange(n_queries), matched]
    wrong = np.flatnonzero(~np.isclose(chosen, best, rtol=1e-9, atol=1e-12))
    if len(wrong):
        raise VPRBenchError(f"{path}: query {int(q[order][wrong[0]])}'s match {int(matched[wrong[0]])} is not its most "
                            "similar database image in the matrix (a distance matrix?); nothing was imported.")
    return Precomputed(np.arange(n_queries), matched, found.scores[order], sim, found.encoding_s, found.matching_s)


class _Imported(Method):
    """Stands for the VPR-Bench method in the record (it describes nothing)."""

    needs_fit = False

    def __init__(self, name: str):
        self.name, self.options = name, {}

    def describe(self, images):  # pragma: no cover - never called
        raise VPRBenchError("an imported method describes no images")

    def provenance(self):
        return {"weights": {"source": SOURCE}}


def import_file(name: str, path: Path, dataset, *, ks=(1, 5, 10, 20), cache_dir=None) -> dict:
    """The vprbench record of one VPR-Bench file, re-scored against `dataset`'s ground truth."""
    from ..evaluation.record import result_record
    from ..fsutil import file_sha256
    from ..spec import DatasetSpec, RunSpec

    found = aligned(read_precomputed(path), len(dataset.queries), len(dataset.database), path)
    ks = tuple(sorted({min(int(k), len(dataset.database)) for k in ks}))
    scores, indices = top_k(found.similarity, ks[-1])
    sha = file_sha256(path)
    protocol = dataset.protocol
    spec = RunSpec(method=f"vpr-bench/{name}", options={"source": SOURCE}, dataset=DatasetSpec(
        name=dataset.name, kind="benchmark", protocol=protocol["name"], protocol_id=protocol["id"],
        protocol_hash=protocol["hash"]), ks=ks)
    imported = {"from": SOURCE, "method": name, "file": FILE, "sha256": sha, "encoding_s": found.encoding_s,
                "matching_s": found.matching_s, "note": "imported from VPR-Bench; re-scored by vprbench"}
    record = result_record(
        spec=spec, method=_Imported(spec.method), fingerprint={"imported": SOURCE, "method": name, "sha256": sha},
        dataset=dataset, dataset_key=dataset.fingerprint(cache_dir), ks=ks, scores=scores.astype(np.float32),
        indices=indices, positives=dataset.positives, descriptor_dim=0, computed={"database": 0, "queries": 0},
        timings={"fit_s": 0.0, "database_s": 0.0, "queries_s": 0.0, "search_s": 0.0, "total_s": 0.0},
        search={"index": "exact", "from": "the similarity matrix of the file"}, context={"imported": imported},
        cache_dir=cache_dir)
    record.update(imported=imported, descriptor_dim=None, descriptor_bytes=None, served_from_store=False,
                  hardware={"note": "unknown: the matches were computed by VPR-Bench"}, run={})
    return record


def import_vpr_bench(folder: Path, dataset_name: str, *, data_dir=None, cache_dir=None, ks=(1, 5, 10, 20)) -> list[dict]:
    """Every method's file under `folder`, as records on the dataset's default protocol (not saved).
    All files are read and checked before any record is returned: one bad file fails the import."""
    from ..datasets import load_dataset

    dataset = load_dataset(dataset_name, data_dir, fetch=False, cache_dir=cache_dir)
    return [import_file(name, path, dataset, ks=ks, cache_dir=cache_dir) for name, path in method_files(folder)]
