"""Evaluation: positives from ground truth, faiss search, Recall@K and PR metrics, result records."""
from .metrics import DEFAULT_KS, recall_at_k, top1_precision_recall
from .search import search
from .extract import describe_splits
from .pipeline import evaluate
from .record import append_result, per_query, read_results, results_dir, results_path, save_result

__all__ = ["DEFAULT_KS", "append_result", "describe_splits", "evaluate", "per_query", "read_results", "recall_at_k",
           "results_dir", "results_path", "save_result", "search", "top1_precision_recall"]
