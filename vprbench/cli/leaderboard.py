"""vprbench leaderboard [--format] / leaderboard publish --to DIR."""
from __future__ import annotations

from pathlib import Path

from rich.table import Table

from ..errors import VPRBenchError
from ..evaluation import read_results
from ..leaderboard import FORMATS, leaderboard, publish, render
from .console import console
from .options import apply_locations


def add_parsers(commands) -> None:
    p = commands.add_parser("leaderboard", help="methods x datasets table of R@1 / R@5 from all evaluations")
    p.add_argument("action", nargs="?", choices=("show", "publish"), default="show")
    p.add_argument("--format", choices=FORMATS, default="table")
    p.add_argument("--to", type=Path, help="with 'publish': folder for leaderboard.md (e.g. docs/)")
    p.add_argument("--cache-dir", help="where the results store lives")
    p.set_defaults(run=run)


def run(args) -> int:
    apply_locations(args)
    if args.action == "publish":
        if args.to is None:
            raise VPRBenchError("leaderboard publish needs --to FOLDER (e.g. --to docs/)")
        print(f"Wrote {publish(args.to, args.cache_dir)}")
        return 0
    table = leaderboard(read_results(args.cache_dir))
    if table.empty:
        raise VPRBenchError("No results yet: run 'vprbench evaluate --method M --dataset D' first.")
    if args.format != "table":
        print(render(table, args.format))
        return 0
    view = Table(title="R@1 / R@5 (%)")
    view.add_column("method")
    for column in table.columns:
        view.add_column(str(column), justify="right")
    for method, row in table.iterrows():
        view.add_row(str(method), *row.tolist())
    console().print(view)
    return 0
