"""Evaluation: positives from ground truth, memory-bounded search, Recall@K and PR metrics, result records."""
from .metrics import DEFAULT_KS, recall_at_k, top1_precision_recall
from .pipeline import evaluate, extract
from .record import append_result, read_results, results_path
from .search import SearchResult, exact_search, retrieve, search

__all__ = ["DEFAULT_KS", "SearchResult", "append_result", "evaluate", "exact_search", "extract", "read_results",
           "recall_at_k", "results_path", "retrieve", "search", "top1_precision_recall"]
