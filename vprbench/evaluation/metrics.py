"""Scores of a retrieval: Recall@K and VPR-Bench's top-1 precision-recall (the search itself is in search/exact.py)."""
from __future__ import annotations

import numpy as np

from ..errors import VPRBenchError
from ..text import plural

#: decimals a record keeps of a recall in percent, and of the PR metrics (0 to 1): what is shown from them
#: (one decimal of R@K and R@100%P in percent, three of max F1) is then the metric's own rounding up to
#: 50,000 queries. Kept to 2 decimals fewer, a value rounded onto a .x5 was rounded again: 1,330 of VP-Air's
#: 2,706 queries, 49.150037 %, kept as 49.15 was shown as 49.1; an R@100%P of 836 / 1003 = 0.8334995 as 83.4.
RECALL_DECIMALS = 6
PR_DECIMALS = 8


def ks_within_database(ks, n_database: int, dataset: str = "the dataset") -> tuple[int, ...]:
    """K values within the database: the largest must not exceed it."""
    ks = tuple(sorted(set(int(k) for k in ks)))
    if not ks or ks[0] < 1:
        raise VPRBenchError(f"Recall@K needs K >= 1, got {list(ks)}")
    if ks[-1] > n_database:
        within = " ".join(str(k) for k in ks if k <= n_database) or "1"
        raise VPRBenchError(f"K = {ks[-1]} exceeds the {plural(n_database, 'database image')} of {dataset}: give --k with "
                            f"values up to {n_database}, e.g. --k {within}.")
    return ks


def correct_at(indices: np.ndarray, positives: list[np.ndarray], all_zero=None) -> np.ndarray:
    """(queries, k) bool: is the j-th retrieved image a positive of the query? Never for a query flagged
    in `all_zero` (one flag per query): its descriptor is all zero, it matches nothing, and its list is
    only the search's tie rule (rows 0, 1, ...), so it counts as a failure at every K."""
    if len(indices) != len(positives):  # zip would drop the extra queries silently
        raise VPRBenchError(f"correct_at takes one row of indices per query and one positive list per query; got "
                            f"{len(indices)} rows and {len(positives)} lists.")
    correct = np.stack([np.isin(row, pos) for row, pos in zip(indices, positives)])
    if all_zero is not None:
        correct[np.asarray(all_zero) != 0] = False
    return correct


def first_positive_rank(correct: np.ndarray) -> np.ndarray:
    """Per query, the 1-based rank of the first positive among the retrieved (0 = none)."""
    correct = np.asarray(correct, dtype=bool)
    return np.where(correct.any(axis=1), correct.argmax(axis=1) + 1, 0)


def percent_true(found: np.ndarray) -> float:
    """100 x the share of True in `found` (0 when empty), from the count: 100 * count / n is rounded once,
    100 * mean twice (23 of 80 came out 28.749999999999996 and was shown as 28.7, not 28.8)."""
    found = np.asarray(found)
    return 100.0 * int(np.count_nonzero(found)) / len(found) if len(found) else 0.0


def successes(first_rank: np.ndarray, k: int) -> np.ndarray:
    """Per query: is a positive among the top k (ranks are 1-based, 0 = none in the top K)?"""
    first = np.asarray(first_rank)
    if first.ndim != 1 or not (np.issubdtype(first.dtype, np.integer) or first.size == 0):
        raise VPRBenchError(f"Recall@K takes each query's first-positive rank, whole numbers in a 1-D array; got "
                            f"{first.dtype} of shape {first.shape}.")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:  # K = 0 would read as 0 %, K = '5' fail deep
        raise VPRBenchError(f"Recall@K takes K as a whole number >= 1; got {k!r}.")
    return (first >= 1) & (first <= k)


def recall_at_k(first_rank: np.ndarray, ks) -> dict[int, float]:
    """Recall@K in percent over ALL queries (queries without positives count as failures), from
    each query's first-positive rank: the one Recall@K of vprbench (records, cells, figures)."""
    return {int(k): percent_true(successes(first_rank, k)) for k in ks}


def kept_metrics(recalls: dict[int, float], pr: dict) -> dict:
    """Recall@K ({K: percent}) and the PR metrics as a record keeps them (and a proof recomputes them)."""
    return {"recall": {str(k): round(v, RECALL_DECIMALS) for k, v in recalls.items()},
            **{name: round(pr[name], PR_DECIMALS) for name in ("auc_pr", "max_f1", "recall_at_100_precision")}}


def top1_precision_recall(top1_scores: np.ndarray, top1_correct: np.ndarray) -> dict:
    """VPR-Bench's PR metrics: sklearn's curve over top-1 matches ranked by their similarity.

    auc_pr is the area under that curve; recall_at_100_precision the largest recall whose
    precision is 1 (0 when even the most confident match is wrong); max_f1 the largest
    2PR / (P + R) over its thresholds. Recall is VPR-Bench's, over the correct top-1 matches (not
    the robotics' over queries with a positive: docs/evaluation.md), so accepting all gives 1.
    """
    from sklearn.metrics import auc, precision_recall_curve

    correct, scores = np.asarray(top1_correct, dtype=bool), np.asarray(top1_scores)
    if correct.ndim != 1 or scores.shape != correct.shape:  # None would be a 0-d False: zeros, silently
        raise VPRBenchError(f"top1_precision_recall takes one top-1 score and one correct flag per query, two 1-D "
                            f"arrays of one length; got shapes {scores.shape} and {correct.shape}.")
    if not correct.any():
        return {"auc_pr": 0.0, "recall_at_100_precision": 0.0, "max_f1": 0.0, "curve": {"precision": [], "recall": []}}
    precision, recall, _ = precision_recall_curve(correct, top1_scores)
    exact = precision[:-1] == 1.0  # the last point (precision 1, recall 0) has no threshold
    f1 = 2 * precision * recall / np.maximum(precision + recall, 1e-12)
    return {
        "max_f1": float(f1.max()),
        "auc_pr": float(auc(recall, precision)),
        "recall_at_100_precision": float(recall[:-1][exact].max()) if exact.any() else 0.0,
        "curve": {"precision": precision.round(6).tolist(), "recall": recall.round(6).tolist()},
    }
