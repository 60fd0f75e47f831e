"""Result records -> leaderboards: cells (one run each), statistics, tables, figures, the docs site.

    cells.py    which run fills which (method row, dataset column) cell, and which runs are left out
    stats.py    bootstrap intervals over queries, paired tests between two methods
    tables.py   the terminal/CSV grid, the paper-style tables, measured vs reported
    figures.py  matplotlib figures written next to the pages
    site.py     `vprbench leaderboard publish`: the leaderboard section of the docs
"""
import warnings

from ..errors import VPRBenchError
from ..stages.base import TRACKS
from .cells import CELL_RULE, Board, Cell, build_board
from .shown import method_label
from .site import publish
from .tables import Shown, computed, grid, render
from .truth import PROVEN, LocalTruth, truth_note  # with build_board, as docs/leaderboard-guide.md uses them


def leaderboard(records: list[dict], data_dir=None, cache_dir=None, *, rescore: bool = True,
                track: str = "single-image"):
    """Methods x datasets table of 'R@1 / R@5' (one run per cell) of one `track` ("single-image",
    "re-ranked" or "sequence": each is a table of its own, as `leaderboard show --track` shows it) from
    result records, each run first re-scored from its top-K indices against the ground truth on this
    machine as the command line does (a benchmark's under `data_dir`, else the default data root;
    `rescore=False` skips it). The table's `attrs["truth_note"]` says which cells were not re-scored, and
    a warning says so too."""
    if track not in TRACKS:  # checked before any record is re-scored
        raise VPRBenchError(f"leaderboard's track takes one of {', '.join(TRACKS)}; got {track!r}.")
    board = build_board(records, LocalTruth(data_dir, cache_dir) if rescore else None).of_track(track)
    table = grid(board)
    table.attrs["truth_note"] = truth_note(board)
    if any(cell.record["_proof"].get("ground_truth") != PROVEN for cell in board.cells.values()):
        warnings.warn(table.attrs["truth_note"], stacklevel=2)  # a notebook shows it; it is not silent
    return table


__all__ = ["CELL_RULE", "Board", "Cell", "LocalTruth", "Shown", "build_board", "computed", "grid", "leaderboard",
           "method_label", "publish", "render", "truth_note"]
