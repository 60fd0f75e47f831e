"""vprbench stages list / vprbench candidates export."""
from __future__ import annotations

import json

from .console import console
from ..errors import DESCRIBED
from .options import (add_location_options, add_method_options, add_run_options, method_options, output_file,
                      progress, resolve_locations, run_settings)


def add_parsers(commands) -> None:
    stages = commands.add_parser("stages", help="list the post-retrieval stages (re-ranking, sequence matching)")
    sub = stages.add_subparsers(dest="stages_command", required=True, metavar="COMMAND")
    p = sub.add_parser("list", help="every stage, its track, options and where it comes from")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_list)

    candidates = commands.add_parser("candidates", help="freeze a retriever's candidates for re-rankers to share")
    sub = candidates.add_subparsers(dest="candidates_command", required=True, metavar="COMMAND")
    p = sub.add_parser("export", help="write a retrieval run's top K per query (HDF5, with its protocol and spec)")
    add_method_options(p)
    p.add_argument("--dataset", required=True, help="dataset name or folder of your own")
    p.add_argument("--protocol", help="the dataset's protocol (default: its first)")
    p.add_argument("--index", choices=("exact", "ivf-pq", "hnsw"), default=None, help="search (default exact)")
    p.add_argument("--index-option", action="append", default=[], metavar="KEY=VALUE",
                   help="an approximate index's option, e.g. nprobe=64 (repeatable), as evaluate takes it")
    p.add_argument("--store-dtype", choices=("float32", "float16"), default="float32")
    p.add_argument("--k", type=int, default=100, help="candidates per query (default 100)")
    p.add_argument("--out", required=True, type=output_file(".h5", ".hdf5"), help="output .h5 file")
    add_run_options(p)
    add_location_options(p)
    p.set_defaults(run=run_export, kept=DESCRIBED)


def run_list(args) -> int:
    from rich.table import Table

    from ..stages import available_stages

    entries = [_listed(e) for e in available_stages().values()]
    if args.json:
        print(json.dumps(entries, indent=2))
        return 0
    table = Table(title="Stages")
    for column in ("name", "track", "from", "options (defaults)", "description"):
        table.add_column(column)
    for e in entries:
        options = " ".join(f"{k}={v}" for k, v in (e["options"] or {}).items())
        description = f"UNLOADABLE: {e['unloadable']}" if "unloadable" in e else e["description"]
        table.add_row(e["name"], e["track"] or "?", e["source"], options, description)
    console().print(table)
    return 0


def _listed(entry) -> dict:
    """A stage as listed; one that cannot be loaded is marked with why, not the end of the list."""
    from ..errors import VPRBenchError

    try:
        cls = entry.cls
    except VPRBenchError as error:
        return {"name": entry.name, "track": None, "description": entry.description, "source": entry.source,
                "options": None, "unloadable": str(error)}
    return {"name": entry.name, "track": cls.track, "description": entry.description or cls.description,
            "source": entry.source, "options": cls.Options().model_dump(mode="json")}


def run_export(args) -> int:
    import sys

    from ..spec import resolve_spec, split_run_settings
    from ..evaluation.pipeline import export_candidates
    from .options import search_flags

    resolve_locations(args)
    settings = run_settings(args)
    spec = resolve_spec(args.method, args.dataset, options=split_run_settings(method_options(args))[0],
                        protocol=args.protocol,
                        search=search_flags(args), store_dtype=args.store_dtype, data_dir=settings.data_dir,
                        cache_dir=settings.cache_dir)
    with progress(args) as shown:
        written = export_candidates(spec, settings, args.out, k=args.k, progress=shown)
    print(f"Wrote the top {written['k']} candidates of {written['queries']} queries ({spec.title()}) to {args.out}",
          file=sys.stderr)
    return 0
