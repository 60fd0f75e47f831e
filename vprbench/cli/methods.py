"""vprbench methods list."""
from __future__ import annotations

import json

from rich.table import Table

from ..methods import available_methods
from .console import console


def add_parsers(commands) -> None:
    methods = commands.add_parser("methods", help="list the registered methods")
    sub = methods.add_subparsers(dest="methods_command", required=True, metavar="COMMAND")
    p = sub.add_parser("list", help="every method and preset, with where it comes from")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_list)


def run_list(args) -> int:
    entries = available_methods().values()
    if args.json:
        print(json.dumps([{"name": e.name, "description": e.description, "source": e.source,
                           "defaults": e.defaults, "options": e.options()} for e in entries], indent=2, default=str))
        return 0
    table = Table(title="Methods")
    for column in ("name", "from", "description"):
        table.add_column(column)
    for e in entries:
        table.add_row(e.name, e.source, e.description)
    console().print(table)
    return 0
