"""Sweeps: plans of methods x datasets (with protocols) x K, run once across processes sharing a cache."""
from .plan import Cell, Plan, build_plan, read_plan
from .runner import Outcome, evaluate_cell, run_cells, summary_table

__all__ = ["Cell", "Outcome", "Plan", "build_plan", "evaluate_cell", "read_plan", "run_cells", "summary_table"]
