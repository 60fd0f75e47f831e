"""`vprbench datasets ...`: download, import and verify (list and info are the lead's, same module).

Each handler takes the parsed arguments and returns the exit code; user errors are raised as
VPRBenchError for the main program to print. `--data-dir` is read from the arguments when the
main parser defines it (it also sets VPRBENCH_DATA).
"""
from __future__ import annotations

import argparse
import json
import warnings

from ..datasets import download_dataset, import_dataset, verify_dataset


def add_download_parser(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser("download", help="fetch a dataset that has a direct source (else print how to get it)")
    parser.add_argument("name")
    parser.add_argument("--no-strict", dest="strict", action="store_false", help="only warn when counts differ from the manifest")
    parser.set_defaults(handler=run_download)
    return parser


def add_import_parser(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser("import", help="register a copy of a dataset already on disk")
    parser.add_argument("name")
    parser.add_argument("path", help="folder holding the dataset in its release layout (or a supported alternative)")
    parser.add_argument("--strict", action="store_true", help="refuse when counts differ from the manifest")
    parser.set_defaults(handler=run_import)
    return parser


def add_verify_parser(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser("verify", help="check a dataset on disk: layout, counts, ground truth, images")
    parser.add_argument("name")
    parser.add_argument("--strict", action="store_true", help="counts that differ from the manifest are errors")
    parser.add_argument("--sample", type=int, default=20, help="images decoded per split (default 20)")
    parser.add_argument("--all-images", action="store_true", help="decode every image")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(handler=run_verify)
    return parser


def add_parser(subparsers) -> argparse.ArgumentParser:
    """The `datasets` command with download/import/verify (the lead adds list and info here)."""
    parser = subparsers.add_parser("datasets", help="get, register and check benchmark datasets")
    sub = parser.add_subparsers(dest="datasets_command", required=True)
    add_download_parser(sub)
    add_import_parser(sub)
    add_verify_parser(sub)
    return parser


def run_download(args) -> int:
    dataset = download_dataset(args.name, getattr(args, "data_dir", None), strict=args.strict)
    print(f"{args.name}: {len(dataset.database)} database and {len(dataset.queries)} query images at {dataset.root}")
    return 0


def run_import(args) -> int:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset = import_dataset(args.name, args.path, getattr(args, "data_dir", None), strict=args.strict)
    for warning in caught:
        print(f"warning: {warning.message}")
    print(
        f"Imported {args.name!r} from {dataset.root} (layout {dataset.layout}): "
        f"{len(dataset.database)} database and {len(dataset.queries)} query images."
    )
    return 0


def run_verify(args) -> int:
    report = verify_dataset(
        args.name, getattr(args, "data_dir", None), strict=args.strict, sample=None if args.all_images else args.sample
    )
    if args.json:
        print(json.dumps({
            "name": report.name, "root": str(report.root), "layout": report.layout, "ok": report.ok,
            "problems": report.problems, "warnings": report.warnings, "summary": report.summary,
            "images_checked": report.images_checked,
        }, indent=2))
    else:
        print("\n".join(report.lines()))
    return 0 if report.ok else 1
