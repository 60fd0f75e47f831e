"""Records proven by their arrays: every metric a table, page, download, `compare` or `reproduce`
shows is recomputed from the run's per-query arrays with the one Recall@K of vprbench
(`metrics.recall_at_k`), never read from the record's JSON. A record whose stored metrics
disagree is named in a warning (its file) and shown with the recomputed values; one whose arrays
are missing or inconsistent is left out, with the reason.

Recomputing is cheap (a pass over the first-positive ranks and one top-1 PR curve) and cached
by the arrays' sha256, so boards of thousands of runs and repeated publishes pay it once.
"""
from __future__ import annotations

import hashlib
import json
import warnings

import numpy as np

from .metrics import kept_metrics, recall_at_k, top1_precision_recall
from .results import per_query

#: records keep Recall@K to metrics.RECALL_DECIMALS decimals (earlier ones 4): a recomputed value is within this
RECALL_TOLERANCE = 1e-4
#: similarities are kept to 6 decimals, so near-ties may reorder the PR curve a little
PR_TOLERANCE = 1e-3
#: arrays' sha256 (and the K asked) -> recomputed metrics
_CACHE: dict[tuple, dict] = {}


def proven(record: dict) -> dict | str:
    """A copy of `record` whose recall, auc_pr, recall_at_100_precision, max_f1 and per_query.k are
    recomputed from its per-query arrays (and `_proof` saying so), or the reason it has no metrics
    that can be shown."""
    section = record.get("per_query") or {}
    if not section:
        return "it keeps no per-query arrays, so its metrics cannot be recomputed; rerun it"
    with warnings.catch_warnings(record=True) as caught:  # per_query checks the arrays (sha256, ranges)
        warnings.simplefilter("always")
        arrays = per_query(record)
    for warning in caught:
        warnings.warn(str(warning.message), stacklevel=2)
    if arrays is None:
        why = f": {caught[0].message}" if caught else ""
        return f"its per-query arrays are missing or damaged, so its metrics cannot be recomputed{why}"
    ks = sorted(int(k) for k in record.get("recall") or {} if str(k).isdigit())
    key = (_digest(section, arrays), tuple(ks))
    if key not in _CACHE:
        _CACHE[key] = _recompute(record, arrays, ks)
    found = _CACHE[key]
    if isinstance(found, str):
        return found
    where = record.get("_source") or f"run {record.get('run_id')}"
    disagree = [f"R@{k} {float(record['recall'][str(k)]):g} (arrays: {found['recall'][str(k)]:g})" for k in ks
                if abs(float(record["recall"][str(k)]) - found["recall"][str(k)]) > RECALL_TOLERANCE]
    for name in ("auc_pr", "recall_at_100_precision", "max_f1"):
        stored = record.get(name)
        if stored is not None and (not isinstance(stored, (int, float)) or abs(float(stored) - found[name]) > PR_TOLERANCE):
            disagree.append(f"{name} {stored} (arrays: {found[name]:.6f})")
    # the depth cells read R@10, R@20 and intervals to is the arrays', not what the JSON says
    if section.get("k") != found["k"]:
        disagree.append(f"per_query.k {section.get('k')} (arrays: {found['k']})")
    if disagree:
        warnings.warn(f"{where}: its stored metrics disagree with its per-query arrays: {', '.join(disagree)}; "
                      "shown with the values recomputed from the arrays.", stacklevel=2)
    return {**record, "recall": dict(found["recall"]), "auc_pr": found["auc_pr"],
            "recall_at_100_precision": found["recall_at_100_precision"], "max_f1": found["max_f1"],
            "per_query": {**section, "k": found["k"]},
            "_proof": {"recomputed": True, "disagreed": disagree}}


def _digest(section: dict, arrays: dict[str, np.ndarray]) -> str:
    """The sha256 the record names for its .npz (verified on reading), else that of the arrays themselves."""
    if section.get("file") and section.get("sha256"):
        return str(section["sha256"])
    digest = hashlib.sha256()
    for name in sorted(arrays):
        digest.update(json.dumps([name, arrays[name].dtype.str, arrays[name].shape]).encode())
        digest.update(np.ascontiguousarray(arrays[name]).tobytes())
    return digest.hexdigest()


def _recompute(record: dict, arrays: dict[str, np.ndarray], ks: list[int]) -> dict | str:
    indices, first = arrays["database_indices"], np.asarray(arrays["first_positive_rank"])
    similarities, positives = arrays["similarities"], np.asarray(arrays["positives"])
    queries = (record.get("counts") or {}).get("queries")
    if indices.ndim != 2 or similarities.shape != indices.shape or first.shape != (len(indices),) \
            or positives.shape != first.shape:
        return (f"its per-query arrays do not fit together (top-K {indices.shape}, similarities {similarities.shape}, "
                f"ranks {first.shape}, positives {positives.shape}); rerun it")
    if queries is not None and len(first) != queries:
        return f"its per-query arrays hold {len(first)} queries, but the record counts {queries}; rerun it"
    k = indices.shape[1]
    if len(first) and (first.min() < 0 or first.max() > k or np.any((first > 0) & (positives <= 0))):
        return f"its first-positive ranks are not ranks within its top {k} of queries that have positives; rerun it"
    if ks and ks[-1] > k:
        return f"it reports R@{ks[-1]} but keeps only the top {k} per query; rerun it"
    if ks and ks[0] < 1:  # (Recall@K refuses K = 0)
        return f"it reports R@{ks[0]}, but K is a whole number >= 1; rerun it"
    pr = top1_precision_recall(similarities[:, 0].astype(np.float64), first == 1) if len(first) else \
        {"auc_pr": 0.0, "recall_at_100_precision": 0.0, "max_f1": 0.0}
    return {**kept_metrics(recall_at_k(first, ks), pr), "k": int(k)}
