"""Result records -> leaderboards: cells (one run each), statistics, tables, figures, the docs site.

    cells.py    which run fills which (method row, dataset column) cell, and which runs are left out
    stats.py    bootstrap intervals over queries, paired tests between two methods
    tables.py   the terminal/CSV grid, the paper-style tables, measured vs reported
    figures.py  matplotlib figures written next to the pages
    site.py     `vprbench leaderboard publish`: the leaderboard section of the docs
"""
from .cells import CELL_RULE, Board, Cell, build_board, method_label
from .site import publish
from .tables import Shown, computed, grid, render


def leaderboard(records: list[dict]):
    """Methods x datasets table of 'R@1 / R@5' (one run per cell) from result records."""
    return grid(build_board(records))


__all__ = ["CELL_RULE", "Board", "Cell", "Shown", "build_board", "computed", "grid", "leaderboard", "method_label",
           "publish", "render"]
