"""Evaluation: `evaluate(spec)` (the one entry point), stores, search, Recall@K and PR metrics, records."""
from .metrics import recall_at_k, successes, top1_precision_recall
from .pipeline import evaluate
from .results import per_query, read_results, results_dir, save_result
from .served import find_result

__all__ = ["evaluate", "find_result", "per_query", "read_results", "recall_at_k", "results_dir", "save_result",
           "successes", "top1_precision_recall"]
