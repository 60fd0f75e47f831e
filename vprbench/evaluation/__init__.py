"""Evaluation: positives from ground truth, faiss search, Recall@K and PR metrics, result records."""
from .metrics import DEFAULT_KS, recall_at_k, search, top1_precision_recall
from .pipeline import evaluate, extract
from .record import append_result, read_results, results_path

__all__ = ["DEFAULT_KS", "append_result", "evaluate", "extract", "read_results", "recall_at_k",
           "results_path", "search", "top1_precision_recall"]
