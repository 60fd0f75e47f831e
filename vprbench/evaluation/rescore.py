"""A record re-scored against its protocol's ground truth: the check `vprbench results verify` makes of
every bundled record and the leaderboard makes of every cell (one function, so both judge alike).

The ground truth is that of a protocol vprbench ships, read from the dataset on this machine
(DataGroundTruth), or any Truth a caller builds (the leaderboard's of a folder of one's own).
Its metrics are recomputed from the record's per-query arrays: counts, indices in range, first-positive
ranks, Recall@K (records keep 6 decimals, earlier ones 4) and the top-1 PR metrics (tolerance 1e-3),
the positives per query, the dataset's fingerprints and the bootstrap units.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from ..stages.base import unordered_row
from .blocks import Resampling, for_dataset, for_record, record_window
from .record import UNIT_FIELDS

RECALL_TOLERANCE = 1e-4
PR_TOLERANCE = 1e-3


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

    def __call__(self, dataset: str, protocol_hash: str, root: str | None = None) -> Truth:
        """The protocol's ground truth from the copy in the data root, or from the copy at `root`."""
        if (dataset, protocol_hash, root) not in self._found:
            self._found[dataset, protocol_hash, root] = self._read(dataset, protocol_hash, root)
        return self._found[dataset, protocol_hash, root]

    def _read(self, dataset: str, protocol_hash: str, root: str | None = None) -> Truth:
        from ..datasets import dataset_manifest, load_dataset, read_copy
        from .identity import benchmark_protocols

        known = benchmark_protocols(dataset)
        if not known:
            raise VPRBenchError(f"dataset {dataset!r} is no benchmark vprbench ships, so its ground truth is unknown here")
        if protocol_hash not in known:
            raise VPRBenchError(f"protocol hash {protocol_hash} is none of the protocols vprbench ships for {dataset} "
                                "(" + ", ".join(f"{p['id']} {h}" for h, p in known.items()) + ")")
        protocol = known[protocol_hash]
        if root is None:
            data = load_dataset(dataset, self.data_dir, fetch=False, protocol=protocol["name"],
                                cache_dir=self.cache_dir)
        else:
            data = read_copy(Path(root), dataset_manifest(dataset), protocol["name"])
        if data.protocol.get("hash") != protocol_hash:
            raise VPRBenchError(f"the copy of {dataset} on this machine ({data.root}) gives protocol hash "
                                f"{data.protocol.get('hash')}, not {protocol_hash}")
        # the board keeps one copy of a column's data (the fingerprint most runs share): a record
        # naming another copy than the one re-scored here could push the true runs out
        fingerprints = {"ground_truth": data.ground_truth_fingerprint()}
        if self.images:
            fingerprints.update(dataset=data.fingerprint(self.cache_dir), images=data.images_fingerprint(self.cache_dir))
        return Truth(protocol["id"], len(data.database), data.positives, for_dataset(data), fingerprints)


def rescore(record: dict, arrays: dict, gt: Truth, problems: list) -> dict[str, float]:
    """The record's metrics recomputed from its arrays against `gt`; each disagreement appended to `problems`."""
    from .metrics import PR_DECIMALS, RECALL_DECIMALS, correct_at, first_positive_rank, recall_at_k, top1_precision_recall

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
