"""vprbench datasets list / info / download / import / verify (their imports are made when they run:
`vprbench --help` answers at once)."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

from ..errors import VPRBenchError
from ..text import literal, one_line, quantity
from .console import console, say, styled
from .options import add_location_options, check_new_folder, path_argument, refuse_unused, resolve_locations


def add_parsers(commands) -> None:
    datasets = commands.add_parser("datasets", help="list datasets, show their counts, get them")
    sub = datasets.add_subparsers(dest="datasets_command", required=True, metavar="COMMAND")
    p = sub.add_parser("list", help="every dataset with its domain and whether it is on disk")
    add_location_options(p, cache=False)
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_list)
    p = sub.add_parser("info", help="counts, positives, unit and radius of one dataset, and its protocols")
    p.add_argument("name", help="dataset name or a folder of your own")
    p.add_argument("--protocol", help="show the dataset under this protocol (default: its first)")
    p.add_argument("--protocols", action="store_true", help="only list the dataset's protocols (no data needed)")
    add_location_options(p, cache_help="with a folder of your own: where its image identities are remembered")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=run_info)
    p = sub.add_parser("download", help="fetch a dataset with a direct source, else print how to get it")
    p.add_argument("name")
    add_location_options(p, cache=False)
    p.add_argument("--no-strict", dest="strict", action="store_false", help="only warn when counts differ from the manifest")
    p.set_defaults(run=run_download)
    p = sub.add_parser("import", help="register a copy of a dataset already on disk (checked first)")
    p.add_argument("name")
    p.add_argument("path", type=path_argument, help="folder holding the dataset in its release layout (or a supported alternative)")
    add_location_options(p, cache=False)
    p.add_argument("--strict", action="store_true", help="refuse when counts differ from the manifest")
    p.set_defaults(run=run_import)
    p = sub.add_parser("verify", help="check a dataset on disk: layout, counts, ground truth, images")
    p.add_argument("name", help="dataset name or a folder of your own")
    add_location_options(p, cache=False)
    p.add_argument("--strict", action="store_true", help="counts that differ from the manifest are errors")
    p.add_argument("--sample", type=int, help="images decoded per split (default 20)")
    p.add_argument("--all-images", action="store_true", help="decode every image")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(run=run_verify)


def run_list(args) -> int:
    from rich.table import Table

    from ..datasets import dataset_location, dataset_manifests, nearest_existing

    resolve_locations(args)
    named = None if args.data_dir is None else Path(args.data_dir).expanduser()
    if named is not None and not named.exists():  # the default one is made on first use: missing, it is listed
        # listed, every dataset would read "not on disk", as if the folder (a typo?) held none of them
        raise VPRBenchError(f"The data root {named} ({args.data_dir_source}) does not exist (closest existing path: "
                            f"{nearest_existing(named)}): check the path (a dataset downloaded or imported into it "
                            "makes it).")
    rows = []
    for manifest in dataset_manifests().values():
        root = dataset_location(manifest, args.data_dir)
        rows.append({"name": manifest.name, "title": manifest.title, "domain": manifest.domain,
                     "database": manifest.database_count, "queries": manifest.query_count,
                     "unit": manifest.unit, "radius": manifest.radius,
                     "radius_unit": manifest.radius_unit or (manifest.unit if manifest.unit != "positives" else None),
                     "on_disk": root.exists(), "path": str(root)})
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    table = Table(title="Datasets")
    # a name is what the user types next: whole on one line, never cut to "mid-atlantic-…" at 80 columns
    table.add_column("name", no_wrap=True, min_width=max((len(r["name"]) for r in rows), default=4))
    for column in ("domain", "database", "queries", "radius", "on disk"):
        table.add_column(column)
    for r in rows:
        radius = quantity(r["radius"], r["radius_unit"])
        radius += " (lists)" if r["unit"] == "positives" else ""
        table.add_row(r["name"], r["domain"], str(r["database"] or "?"), str(r["queries"] or "?"), radius,
                      styled("yes", "green") if r["on_disk"] else "no")
    console().print(table)
    return 0


def run_info(args) -> int:
    from rich.table import Table

    from ..datasets import dataset_location, dataset_manifest, dataset_manifests, is_path, load_dataset, protocols

    if args.protocols:  # read from the manifest alone
        for dest in ("data_dir", "cache_dir"):
            refuse_unused(args, dest, "with --protocols (the protocols need no data)")
    elif is_path(args.name):  # a folder of your own: no data root; its images' identities are remembered in the cache
        refuse_unused(args, "data_dir", f"for a folder of your own ({args.name})")
    else:
        refuse_unused(args, "cache_dir", f"for dataset {args.name!r} (the cache only remembers a folder of your own's "
                                         "image identities)")
    resolve_locations(args)
    if args.protocols:
        if args.protocol is not None:  # ignored, it would let a user think the list was narrowed to it
            raise VPRBenchError("--protocols lists every protocol and --protocol shows the dataset under one: "
                                "give one of them.")
        listed = [p.record() for p in protocols(dataset_manifest(args.name)).values()]
        if args.json:
            print(json.dumps(listed, indent=2))
        else:
            console().print(protocol_table(args.name, listed))
        return 0
    try:
        dataset = load_dataset(args.name, args.data_dir, fetch=False, protocol=args.protocol, cache_dir=args.cache_dir)
    except VPRBenchError as error:
        if args.name in dataset_manifests() and not dataset_location(dataset_manifest(args.name), args.data_dir).exists():
            raise VPRBenchError(f"{error} Its protocols need no data: 'vprbench datasets info {args.name} --protocols'.") from None
        raise
    info = dataset.summary()
    info.update({"citation": dataset.citation, "licence": dataset.licence, "notes": " ".join(dataset.notes),
                 "kind": dataset.kind, "protocol": dataset.protocol})
    listed = [p.record() for p in protocols(dataset_manifest(args.name)).values()] if dataset.kind == "benchmark" else [dataset.protocol]
    if args.json:
        print(json.dumps({**info, "protocols": listed}, indent=2))
        return 0
    table = Table(title=f"{dataset.title or dataset.name}", show_header=False)
    for key, value in info.items():
        table.add_row(key, value["id"] if key == "protocol" else str(value))
    console().print(table)
    console().print(protocol_table(dataset.name, listed))
    return 0


def protocol_table(name: str, listed: list[dict]):
    """The protocols, readable at 80 columns: names and hashes never wrap, sources follow the table."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    table = Table(title=f"Protocols of {name} (the first is the default; choose with --protocol NAME)")
    for column in ("name", "hash"):
        table.add_column(column, no_wrap=True)
    for column in ("database", "queries", "positive if"):
        table.add_column(column, overflow="fold")
    for p in listed:
        gt = p["ground_truth"]
        within = f"within {quantity(gt['radius'], gt['radius_unit'])}" + (" (lists)" if gt["unit"] == "positives" else "")
        db, q = p["database"], p["queries"]
        table.add_row(p["name"], p["hash"],
                      f"{db['count'] or '?'} ({db['split']}{', without ' + ', '.join(db['exclude_folders']) if db['exclude_folders'] else ''})",
                      f"{q['count'] or 'all'} ({q['split']}{', listed subset' if q['subset'] else ''})", within)
    sources = [Text.assemble(styled(f"{p['name']}: ", "bold"), literal(p["source"])) for p in listed if p.get("source")]
    return Group(table, *sources)


def run_download(args) -> int:
    from ..datasets import download_dataset

    resolve_locations(args)
    if args.data_dir is not None:  # a typo would otherwise make a tree of folders anywhere
        check_new_folder(Path(args.data_dir), args.data_dir_source)
    dataset = download_dataset(args.name, args.data_dir, strict=args.strict)
    say(f"{args.name}: {len(dataset.database)} database and {len(dataset.queries)} query images at {dataset.root}")
    return 0


def run_import(args) -> int:
    from ..datasets import import_dataset

    resolve_locations(args)
    if args.data_dir is not None:
        check_new_folder(Path(args.data_dir), args.data_dir_source)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset = import_dataset(args.name, args.path, args.data_dir, strict=args.strict)
    for warning in caught:
        say(f"warning: {one_line(warning.message)}")  # one line, as every other warning
    say(
        f"Imported {args.name!r} from {dataset.root} (layout {dataset.layout}): "
        f"{len(dataset.database)} database and {len(dataset.queries)} query images."
    )
    return 0


def run_verify(args) -> int:
    from ..datasets import is_path, verify_dataset

    if is_path(args.name):
        refuse_unused(args, "data_dir", f"for a folder of your own ({args.name})")
    if args.all_images:
        refuse_unused(args, "sample", "with --all-images (every image is decoded)")
    resolve_locations(args)
    sample = 20 if args.sample is None else args.sample
    report = verify_dataset(args.name, args.data_dir, strict=args.strict, sample=None if args.all_images else sample)
    if args.json:
        print(json.dumps({
            "name": report.name, "root": str(report.root), "layout": report.layout, "ok": report.ok,
            "problems": report.problems, "warnings": report.warnings, "summary": report.summary,
            "images_checked": report.images_checked, "utm_zones": report.zones,
        }, indent=2))
    else:
        say("\n".join(report.lines()))
    return 0 if report.ok else 1
