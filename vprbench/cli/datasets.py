"""vprbench datasets list / info."""
from __future__ import annotations

import json

from rich.console import Console
from rich.table import Table

from ..datasets import dataset_location, dataset_manifests, load_dataset
from .options import add_location_options, apply_locations


def add_parsers(commands) -> None:
    datasets = commands.add_parser("datasets", help="list datasets, show their counts, get them")
    sub = datasets.add_subparsers(dest="datasets_command", required=True, metavar="COMMAND")
    p = sub.add_parser("list", help="every dataset with its domain and whether it is on disk")
    add_location_options(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_list)
    p = sub.add_parser("info", help="counts, positives, unit and radius of one dataset")
    p.add_argument("name", help="dataset name or a folder of your own")
    add_location_options(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_info)


def run_list(args) -> int:
    apply_locations(args)
    rows = []
    for manifest in dataset_manifests().values():
        root = dataset_location(manifest, args.data_dir)
        rows.append({"name": manifest.name, "title": manifest.title, "domain": manifest.domain,
                     "database": manifest.database_count, "queries": manifest.query_count,
                     "unit": manifest.unit, "radius": manifest.radius,
                     "on_disk": root.exists(), "path": str(root)})
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    table = Table(title="Datasets")
    for column in ("name", "domain", "database", "queries", "radius", "on disk"):
        table.add_column(column)
    for r in rows:
        radius = "positive lists" if r["unit"] == "positives" else f"{r['radius']:g} {r['unit']}"
        table.add_row(r["name"], r["domain"], str(r["database"] or "?"), str(r["queries"] or "?"), radius,
                      "[green]yes[/]" if r["on_disk"] else "no")
    Console().print(table)
    return 0


def run_info(args) -> int:
    apply_locations(args)
    dataset = load_dataset(args.name, args.data_dir, fetch=False)
    info = dataset.summary()
    info.update({"citation": dataset.citation, "licence": dataset.licence})
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    table = Table(title=f"{dataset.title or dataset.name}", show_header=False)
    for key, value in info.items():
        table.add_row(key, str(value))
    Console().print(table)
    return 0

