"""vprbench methods list."""
from __future__ import annotations

import json

from rich.table import Table

from ..errors import VPRBenchError
from ..methods import available_methods
from .console import console


def add_parsers(commands) -> None:
    methods = commands.add_parser("methods", help="list the registered methods and the backbones AnyLoc can use")
    sub = methods.add_subparsers(dest="methods_command", required=True, metavar="COMMAND")
    p = sub.add_parser("list", help="every method and preset, with where it comes from")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_list)
    p = sub.add_parser("backbones", help="the ViT backbones AnyLoc and vocabulary fit can use")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_backbones)


def run_list(args) -> int:
    entries = available_methods().values()
    if args.json:  # the options need each factory imported (torch for most): only here, not for the table
        found = [(e, *_options(e)) for e in entries]
        print(json.dumps([{"name": e.name, "description": e.description, "source": e.source, "defaults": e.defaults,
                           "options": options, **({"unloadable": problem} if problem else {})}
                          for e, options, problem in found], indent=2, default=str))
        return 0
    table = Table(title="Methods")
    for column in ("name", "from", "description"):
        table.add_column(column)
    for e in entries:
        table.add_row(e.name, e.source, e.description)
    console().print(table)
    return 0


def _options(entry) -> tuple[list | None, str | None]:
    """(the method's options, None), or (None, why it cannot be loaded): one broken registration
    is marked in the list, not the end of it."""
    try:
        return entry.options(), None
    except VPRBenchError as error:
        return None, str(error)


def run_backbones(args) -> int:
    from ..features.catalogue import backbones

    entries = backbones().values()
    if args.json:
        print(json.dumps([e.model_dump(mode="json") for e in entries], indent=2))
        return 0
    table = Table(title="Backbones (manifests/backbones; or --backbone timm:ARCH.TAG)",
                  caption="ViT: blocks x width /patch, tokens before the patches, positions; every field: --json")
    # the names are what --backbone takes: whole on one line at any width (the rest wraps)
    table.add_column("name", no_wrap=True, min_width=max(len(e.name) for e in entries))
    for column in ("family", "ViT", "licence"):
        table.add_column(column)
    table.add_column("timm", overflow="fold")
    for e in entries:
        prefix = " + ".join(filter(None, ["CLS" if e.cls_token else "", f"{e.registers} reg" if e.registers else ""]))
        table.add_row(e.name, e.family, f"{e.depth} x {e.width} /{e.patch}, {prefix or 'none'}, {e.position}",
                      e.licence + (" (gated)" if e.gated else ""), e.timm_name)
    console().print(table)
    return 0
