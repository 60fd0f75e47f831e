"""Scores of a retrieval: Recall@K and VPR-Bench's top-1 precision-recall (the search itself is in search.py)."""
from __future__ import annotations

import numpy as np

from ..errors import VPRBenchError

DEFAULT_KS = (1, 5, 10, 20)


def check_ks(ks, n_database: int) -> tuple[int, ...]:
    ks = tuple(sorted(set(int(k) for k in ks)))
    if not ks or ks[0] < 1:
        raise VPRBenchError(f"Recall@K needs K >= 1, got {list(ks)}")
    if ks[-1] > n_database:
        raise VPRBenchError(f"K = {ks[-1]} exceeds the {n_database} database images; use a smaller --k.")
    return ks


def correct_at(indices: np.ndarray, positives: list[np.ndarray]) -> np.ndarray:
    """(queries, k) bool: is the j-th retrieved image a positive of the query?"""
    return np.stack([np.isin(row, pos) for row, pos in zip(indices, positives)])


def recall_at_k(indices: np.ndarray, positives: list[np.ndarray], ks) -> dict[int, float]:
    """Percent of ALL queries with a positive among the top K (queries without positives fail)."""
    hits = np.cumsum(correct_at(indices, positives), axis=1) > 0
    return {k: float(100.0 * hits[:, k - 1].mean()) for k in ks}


def top1_precision_recall(top1_scores: np.ndarray, top1_correct: np.ndarray) -> dict:
    """VPR-Bench's PR metrics: sklearn's curve over top-1 matches ranked by their similarity.

    auc_pr is the area under that curve; recall_at_100_precision the largest recall whose
    precision is 1 (0 when even the most confident match is wrong).
    """
    from sklearn.metrics import auc, precision_recall_curve

    correct = np.asarray(top1_correct, dtype=bool)
    if not correct.any():
        return {"auc_pr": 0.0, "recall_at_100_precision": 0.0, "curve": {"precision": [], "recall": []}}
    precision, recall, _ = precision_recall_curve(correct, top1_scores)
    exact = precision[:-1] == 1.0  # the last point (precision 1, recall 0) has no threshold
    return {
        "auc_pr": float(auc(recall, precision)),
        "recall_at_100_precision": float(recall[:-1][exact].max()) if exact.any() else 0.0,
        "curve": {"precision": precision.round(6).tolist(), "recall": recall.round(6).tolist()},
    }
