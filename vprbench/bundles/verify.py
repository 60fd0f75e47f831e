"""`vprbench results verify`: nothing in a bundle is trusted that can be recomputed.

The archive is read into memory, bounded and never extracted, and its manifest checked against
every member (archive.py). Each record is then validated (a record of a newer schema is refused), the names it gives must be
its spec's and vprbench's (claims.py), its protocol hash must be one vprbench ships for its
dataset, and its metrics are recomputed from its per-query arrays against that protocol's ground truth, read from the dataset on this machine: query and database
counts, indices in range, every query present, first-positive ranks, and Recall@K (records keep
6 decimals, earlier ones 4) and the top-1 PR metrics (6 decimals, computed from the similarities the record keeps;
tolerance 1e-3 for records of earlier versions, computed before rounding). Units of the bootstrap a record keeps (each query's place,
the traverse order, blocks lengthened by its stages' sequence window) must be the protocol's, or its
intervals would be drawn from the wrong ones.
"""
from __future__ import annotations

import hashlib
import io
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from ..text import one_line, recall_text, shortened
from ..evaluation.blocks import Resampling, for_dataset, for_record, record_window
from ..evaluation.record import UNIT_FIELDS, per_query_arrays_in, validated
from ..evaluation.results import check_kinds
from ..stages.base import unordered_row
from .archive import _CARD, MAX_BYTES, RECORD_NAME, BundleError, _json, check_manifest, read_members
from .claims import false_card, false_claims, malformed, one_record_per_run
from .export import CARDS, KIND_WORDS

RECALL_TOLERANCE = 1e-4
#: the longest row label a verdict line shows
MAX_LABEL = 200
PR_TOLERANCE = 1e-3


# ---------------------------------------------------------------- the ground truth
@dataclass(frozen=True)
class Truth:
    protocol_id: str
    database: int
    positives: list
    #: the units the protocol's bootstrap draws (evaluation/blocks.py); None: not checked
    resampling: Resampling | None = None
    #: the dataset's identity here (images and ground truth, as records keep it); None: not checked
    fingerprints: dict | None = None


class DataGroundTruth:
    """Ground truth of a protocol vprbench ships, read from the dataset on this machine (once per protocol)."""

    def __init__(self, data_dir=None, cache_dir=None, *, images: bool = True):
        # images=False: the ground truth's fingerprint only (the leaderboard re-scores where the images may be absent)
        self.data_dir, self.cache_dir, self.images, self._found = data_dir, cache_dir, images, {}

    def __call__(self, dataset: str, protocol_hash: str) -> Truth:
        if (dataset, protocol_hash) not in self._found:
            self._found[dataset, protocol_hash] = self._read(dataset, protocol_hash)
        return self._found[dataset, protocol_hash]

    def _read(self, dataset: str, protocol_hash: str) -> Truth:
        from ..datasets import load_dataset
        from ..evaluation.identity import benchmark_protocols

        known = benchmark_protocols(dataset)
        if not known:
            raise VPRBenchError(f"dataset {dataset!r} is no benchmark vprbench ships, so its ground truth is unknown here")
        if protocol_hash not in known:
            raise VPRBenchError(f"protocol hash {protocol_hash} is none of the protocols vprbench ships for {dataset} "
                                "(" + ", ".join(f"{p['id']} {h}" for h, p in known.items()) + ")")
        protocol = known[protocol_hash]
        data = load_dataset(dataset, self.data_dir, fetch=False, protocol=protocol["name"], cache_dir=self.cache_dir)
        if data.protocol.get("hash") != protocol_hash:
            raise VPRBenchError(f"the copy of {dataset} on this machine ({data.root}) gives protocol hash "
                                f"{data.protocol.get('hash')}, not {protocol_hash}")
        # the board keeps one copy of a column's data (the fingerprint most runs share): a record
        # naming another copy than the one re-scored here could push the true runs out
        fingerprints = {"ground_truth": data.ground_truth_fingerprint()}
        if self.images:
            fingerprints.update(dataset=data.fingerprint(self.cache_dir), images=data.images_fingerprint(self.cache_dir))
        return Truth(protocol["id"], len(data.database), data.positives, for_dataset(data), fingerprints)


# ---------------------------------------------------------------- the records
@dataclass
class Verdict:
    """What was found about one record of a bundle."""

    member: str
    run_id: str
    label: str = ""
    problems: list[str] = field(default_factory=list)
    recall: dict[str, float] = field(default_factory=dict)
    #: a run on random weights: sound, but a pipeline check that fills no leaderboard cell
    check: bool = False

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class BundleReport:
    path: Path
    manifest: dict = field(default_factory=dict)
    members: dict[str, bytes] = field(default_factory=dict)
    verdicts: list[Verdict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and bool(self.verdicts) and all(v.ok for v in self.verdicts)

    def lines(self) -> list[str]:
        """One line per problem (naming the file and the record), or per record found sound."""
        from ..leaderboard.shown import PIPELINE_CHECK

        out = list(self.problems)
        for verdict in self.verdicts:
            head = f"{self.path}: {verdict.member} (run {verdict.run_id}{', ' + verdict.label if verdict.label else ''})"
            if verdict.ok:
                # rounded as the leaderboard shows it
                shown = " ".join(f"R@{k} {recall_text(v)}" for k, v in verdict.recall.items())
                check = f" ({PIPELINE_CHECK}; it fills no leaderboard cell)" if verdict.check else ""
                out.append(f"{head}: ok, re-scored from its arrays: {shown}{check}")
            out += [f"{head}: {problem}" for problem in verdict.problems]
        if not self.problems and not self.verdicts:
            out.append(f"{self.path}: it holds no records.")
        # names from a record (a label, a key) hold no line break: none can forge a verdict line
        return [one_line(line) for line in out]


def verify_bundle(path: Path, truth=None, *, max_bytes: int = MAX_BYTES) -> BundleReport:
    """Every record of the bundle at `path` checked and re-scored; `truth(dataset, protocol_hash)`
    gives the ground truth (default: `DataGroundTruth()`, the datasets on this machine)."""
    report = BundleReport(Path(path))
    truth = truth or DataGroundTruth()
    try:
        report.members = read_members(Path(path), max_bytes)
        report.manifest = check_manifest(report.members, str(path))
    except BundleError as error:
        report.problems.append(str(error))
        return report
    cards = {m.group(1) for m in map(_CARD.match, report.members) if m}
    for name in sorted(report.members):
        match = RECORD_NAME.match(name)
        if match and match.group(4) == "json":
            report.verdicts.append(check_record(name, match.groups()[:3], report.members, cards, truth, max_bytes))
    one_record_per_run(report.verdicts)
    return report


def check_record(name: str, place: tuple, members: dict[str, bytes], cards: set, truth,
                 max_bytes: int = MAX_BYTES) -> Verdict:
    protocol_hash, row_key, run_id = place
    verdict = Verdict(name, run_id)
    problems = verdict.problems
    try:
        record = validated(_json(members[name]), name)
    except ValueError as error:
        problems.append(f"not JSON ({error})")
        return verdict
    except VPRBenchError as error:
        problems.append(str(error).removeprefix(f"{name} ").removeprefix(f"{name}: "))
        return verdict
    from ..leaderboard.cells import row_of
    from ..leaderboard.shown import random_weights

    shapeless = malformed(record)  # the row's name and marks are read from these parts: none can be told
    if shapeless:
        problems += shapeless
        return verdict
    # the row as the leaderboard names it, marks included: a run on random weights (which fills no cell)
    # or fitted on the evaluated database does not read as an official one
    # cut: a method name or protocol id a stranger wrote can be megabytes, printed on each of the record's lines
    verdict.label = shortened(f"{row_of(record).name} on {record['protocol']['id']}", MAX_LABEL)
    verdict.check = random_weights(record)
    found = (record["protocol"]["hash"], record["row_key"], record["run_id"])
    if found != place or record["spec"]["dataset"]["protocol_hash"] != protocol_hash:
        problems.append(f"its protocol hash, row key and run id {'/'.join(found)} are not its place in the bundle")
        return verdict
    if row_key not in cards:
        problems.append(f"its method card {CARDS}/{row_key}.json is missing")
    elif f"{CARDS}/{row_key}.json" in members:
        problems += false_card(members[f"{CARDS}/{row_key}.json"], record)
    if record["dataset_kind"] != "benchmark":
        problems.append(f"it was run on {KIND_WORDS.get(record['dataset_kind'], 'a dataset of its own')}, whose ground "
                        "truth vprbench does not ship; only benchmark runs can be checked")
        return verdict
    problems += false_claims(record)
    arrays = _arrays(record, members, f"{protocol_hash}/{row_key}", problems, max_bytes)
    if arrays is None:
        return verdict
    try:
        gt = truth(record["dataset"], protocol_hash)
    except VPRBenchError as error:
        problems.append(f"cannot be checked: {error}")
        return verdict
    verdict.recall = rescore(record, arrays, gt, problems)
    return verdict


def _arrays(record: dict, members: dict[str, bytes], folder: str, problems: list, max_bytes: int) -> dict | None:
    section = record.get("per_query") or {}
    file = f"{folder}/{section.get('file')}"
    if section.get("file") != f"{record['run_id']}.npz" or file not in members:
        problems.append("its per-query arrays are missing (a bundle record must keep them)")
        return None
    data = members[file]
    if hashlib.sha256(data).hexdigest() != section.get("sha256"):
        problems.append(f"{file} does not match the sha256 its record gives")
        return None
    try:
        # an .npz is a zip of its own: a few kB may claim gigabytes (a bomb inside the bundle);
        # the sizes its members declare bound what they unpack to
        with zipfile.ZipFile(io.BytesIO(data)) as inner:
            unpacked = sum(info.file_size for info in inner.infolist())
        if unpacked > max_bytes:
            problems.append(f"{file} unpacks to {unpacked / 2**20:,.0f} MiB, more than the bound of "
                            f"{max_bytes / 2**20:g} MiB (an archive bomb, or a bundle too big: raise --max-size)")
            return None
        arrays = per_query_arrays_in(data, max_bytes)  # the bound above, not the reader's default
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as error:
        problems.append(f"{file} is not readable per-query arrays ({type(error).__name__}: {error})")
        return None
    try:
        check_kinds(arrays)  # the store's own test: what the metrics below compute with
    except ValueError as error:
        problems.append(f"{file}: {error}")
        return None
    return arrays


def rescore(record: dict, arrays: dict, gt: Truth, problems: list) -> dict[str, float]:
    """The record's metrics recomputed from its arrays against `gt`; each disagreement appended to `problems`."""
    from ..evaluation.metrics import PR_DECIMALS, RECALL_DECIMALS, correct_at, first_positive_rank, recall_at_k, top1_precision_recall

    indices, scores = arrays["database_indices"].astype(np.int64), arrays["similarities"].astype(np.float64)
    queries, k = indices.shape
    counts = record["counts"]
    odd = [key for key in record["recall"] if not re.fullmatch(r"[1-9][0-9]{0,8}", key)]
    if odd:  # a key the checks below would not read (' 1', '01') or cannot ('abc')
        problems.append(f"its recall has key {odd[0][:20]!r}, not a K (a whole number from 1, as vprbench writes it)")
    if queries != len(gt.positives):
        problems.append(f"it has top-K lists for {queries} queries; protocol {gt.protocol_id} has {len(gt.positives)} "
                        f"({'missing' if queries < len(gt.positives) else 'extra'} queries)")
    if counts.get("queries") != len(gt.positives) or counts.get("database") != gt.database:
        problems.append(f"its counts ({counts.get('queries')} queries, {counts.get('database')} database) are not "
                        f"protocol {gt.protocol_id}'s ({len(gt.positives)}, {gt.database})")
    if indices.size and (indices.min() < 0 or indices.max() >= gt.database):
        bad = int(np.argmax((indices < 0).any(axis=1) | (indices >= gt.database).any(axis=1)))
        problems.append(f"query {bad} lists database index {int(indices[bad][(indices[bad] < 0) | (indices[bad] >= gt.database)][0])}, "
                        f"outside the {gt.database} database images")
    if problems:
        return {}
    repeated = np.flatnonzero([len(np.unique(row)) != k for row in indices])
    if len(repeated):
        problems.append(f"query {int(repeated[0])} lists a database image twice in its top {k}")
    rising = unordered_row(scores)
    if rising is not None:  # indices moved without their scores: a list not ranked by what it claims
        problems.append(f"query {rising}: its similarities increase along its top {k}, so the list is not ranked "
                        "by them (best first)")
    ks = sorted(int(x) for x in record["recall"])
    if ks and ks[-1] > k:
        problems.append(f"it reports R@{ks[-1]} but keeps only the top {k} per query")
        return {}
    flags = arrays.get("all_zero")  # queries whose descriptor was all zero: failures whatever they list
    # (a sequence run counts them but flags none: a sequence stage places them from their neighbours)
    if flags is not None and counts.get("all_zero_queries") != np.count_nonzero(flags):
        problems.append(f"its counts say {counts.get('all_zero_queries', 'nothing of')} all-zero queries; its "
                        f"arrays flag {np.count_nonzero(flags)}")
    first = first_positive_rank(correct_at(indices, gt.positives, flags))
    if not np.array_equal(first, arrays["first_positive_rank"]):
        q = int(np.flatnonzero(first != arrays["first_positive_rank"])[0])
        problems.append(f"query {q}: its first positive is at rank {int(first[q])} of its top K, the record says "
                        f"{int(arrays['first_positive_rank'][q])}")
    _check_positives(record, arrays["positives"], gt, problems)
    _check_top_predictions(record.get("top_predictions"), indices, problems)
    recall = {str(k): round(v, RECALL_DECIMALS) for k, v in recall_at_k(first, ks).items()}
    for key, value in recall.items():
        if abs(float(record["recall"][key]) - value) > RECALL_TOLERANCE:
            problems.append(f"R@{key} is {record['recall'][key]} in the record but {value:.{RECALL_DECIMALS}f} from its arrays")
    if queries and "auc_pr" in record:
        pr = top1_precision_recall(scores[:, 0], first == 1)
        for name in ("auc_pr", "recall_at_100_precision", "max_f1"):
            if name in record and abs(float(record[name]) - pr[name]) > PR_TOLERANCE:
                problems.append(f"{name} is {record[name]} in the record but {pr[name]:.{PR_DECIMALS}f} from its arrays")
    _check_fingerprints(record, gt, problems)
    stated = for_record(record, arrays)
    # the protocol's units for this run: blocks lengthen by its stages' query window, by the same rule;
    # checked when the record keeps unit arrays, states its resampling (written with them) or the units
    # need none (records before unit arrays kept none, and no resampling)
    expected = gt.resampling.for_window(record_window(record)) if gt.resampling is not None else None
    needs_arrays = expected is not None and (expected.order is not None or expected.places is not None)
    checked = set(UNIT_FIELDS) & set(arrays) or "resampling" in record or not needs_arrays
    if expected is not None and checked and not stated.same_as(expected):
        problems.append(f"its bootstrap units ({stated.text()}) are not those of protocol {gt.protocol_id} "
                        f"({expected.text()}); its intervals would be drawn from the wrong units")
    return {k: v for k, v in recall.items()}


def _check_fingerprints(record: dict, gt: Truth, problems: list) -> None:
    """The dataset identity the record gives is that of the copy its arrays are re-scored against."""
    if gt.fingerprints is None:
        return
    parts = record.get("dataset_fingerprints", {})
    if not isinstance(parts, dict):
        problems.append(f"its dataset_fingerprints is a {type(parts).__name__}, not a table")
        return
    # the parts' "dataset" repeats the top-level one; a 0.2 record's (hashed another way) is recomputed by
    # its upgrade, its parts' copy is not: only the top-level one is compared
    given = [("dataset", record.get("dataset_fingerprint")),
             *((n, parts[n]) for n in gt.fingerprints if n in parts and n != "dataset")]
    wrong = sorted({name for name, value in given if value != gt.fingerprints[name]})
    if wrong:
        problems.append(f"its dataset fingerprint ({', '.join(wrong)}) is not that of the copy of {record['dataset']} "
                        f"here ({gt.fingerprints['dataset']}); a record names only the data it ran on: verify it against "
                        "that copy (--data-dir), or run it again on this one")


def _check_positives(record: dict, stored: np.ndarray, gt: Truth, problems: list) -> None:
    """The positives per query its arrays keep, and the counts the record gives, are the protocol's."""
    expected = np.array([len(p) for p in gt.positives], dtype=np.int64)
    stored = np.asarray(stored)  # one per query, as many as the protocol's (checked before)
    if not np.array_equal(stored, expected):
        q = int(np.flatnonzero(stored != expected)[0])
        problems.append(f"query {q}: its arrays give it {int(stored[q])} positives, protocol {gt.protocol_id} "
                        f"{int(expected[q])}")
    counts = record["counts"]
    for name, value in (("positive_pairs", int(expected.sum())), ("queries_without_positives", int((expected == 0).sum()))):
        if name in counts and counts[name] != value:
            problems.append(f"its counts say {counts[name]} {name.replace('_', ' ')}; protocol {gt.protocol_id} has {value}")


def _check_top_predictions(shown, indices: np.ndarray, problems: list) -> None:
    """`top_predictions` (the first columns of the top K, kept for vprbench 0.1's readers) match the arrays."""
    if shown is None:
        return
    try:
        shown = np.asarray(shown, dtype=np.int64)
    except (ValueError, TypeError, OverflowError):
        shown = None
    if shown is None or shown.ndim != 2 or len(shown) != len(indices) or not 1 <= shown.shape[1] <= indices.shape[1] \
            or not np.array_equal(shown, indices[:, :shown.shape[1]]):
        problems.append("its top_predictions are not the first columns of its per-query top-K indices")
