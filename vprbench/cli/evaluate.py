"""vprbench evaluate / describe."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from ..datasets import load_dataset
from ..errors import VPRBenchError
from ..evaluation import append_result, evaluate
from ..methods import create_method
from .console import console as make_console
from .options import add_download_option, add_location_options, add_method_options, apply_locations, method_options, parse_ks
from .run import add_sweep_options, run_matrix


def progress_bar(console: Console) -> Progress:
    return Progress(TextColumn("{task.description}", markup=False), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True)


def add_parsers(commands) -> None:
    p = commands.add_parser("evaluate", help="evaluate methods on datasets (Recall@K, PR); several of each run as a sweep")
    add_method_options(p, several=True)
    p.add_argument("--dataset", required=True, nargs="+", help="dataset names ('vprbench datasets list') or folders of your own")
    p.add_argument("--protocol", help="the dataset's protocol ('vprbench datasets info NAME'; default: its first)")
    add_sweep_options(p)
    add_location_options(p)
    add_download_option(p)
    p.add_argument("--k", nargs="+", help="K values for Recall@K (default 1 5 10 20)")
    p.add_argument("--strict", action="store_true", help="fail when image counts differ from the manifest")
    p.add_argument("--json", action="store_true", help="print the result record as JSON on stdout")
    p.set_defaults(run=run_evaluate)

    p = commands.add_parser("describe", help="write global descriptors of images to a .npy file, in input order")
    add_method_options(p)
    p.add_argument("images", nargs="+", type=Path, help="image files")
    p.add_argument("--out", required=True, type=Path, help="output .npy file")
    p.add_argument("--fit-on", type=Path, help="folder of database images to fit the method's vocabulary on")
    add_location_options(p)
    p.set_defaults(run=run_describe)


def run_evaluate(args) -> int:
    apply_locations(args)
    if len(args.method) > 1 or len(args.dataset) > 1 or args.protocol:
        return run_matrix(args, method_options(args))  # the sweep: resumable, shared across processes
    args.method, args.dataset = args.method[0], args.dataset[0]
    dataset = load_dataset(args.dataset, args.data_dir, strict=args.strict, fetch=args.download or None)
    method = create_method(args.method, **method_options(args))
    with progress_bar(make_console(stderr=True)) as progress:
        record = evaluate(method, dataset, ks=parse_ks(args.k), cache_dir=args.cache_dir, progress=progress)
    if args.json:  # shown first: a result that cannot be saved (full or read-only disk) is still seen
        print(json.dumps(record, indent=2, sort_keys=True))
    else:
        make_console().print(results_table(record))
    append_result(record, args.cache_dir)
    return 0


def results_table(record: dict) -> Table:
    counts, timings = record["counts"], record["timings"]
    table = Table(title=f"{record['method']} on {record['dataset']}", show_header=True)
    for k in record["recall"]:
        table.add_column(f"R@{k}", justify="right")
    table.add_column("AUC-PR", justify="right")
    table.add_column("R@100%P", justify="right")
    table.add_row(*[f"{v:.1f}" for v in record["recall"].values()],
                  f"{record['auc_pr']:.3f}", f"{record['recall_at_100_precision']:.3f}")
    computed = record["descriptors_computed"]
    table.caption = (
        f"{counts['database']} database, {counts['queries']} queries "
        f"({counts['queries_without_positives']} without positives, counted as failures); "
        f"dim {record['descriptor_dim']}; descriptors computed now: {computed['database'] + computed['queries']}; "
        f"{timings['total_s']:.1f} s total"
    )
    return table


def run_describe(args) -> int:
    apply_locations(args)
    if args.out.suffix != ".npy":
        raise VPRBenchError(f"--out must be a .npy file, got {args.out}")
    for image in args.images:
        if not image.is_file():
            raise VPRBenchError(f"Image not found: {image}")
    method = create_method(args.method, **method_options(args))
    if method.needs_fit:
        if args.fit_on is None:
            raise VPRBenchError(f"Method {args.method!r} fits a vocabulary on database images: give --fit-on FOLDER "
                                "(or a ready vocabulary with --vocabulary, where the method takes one).")
        from ..images import list_images

        method.fit(list_images(args.fit_on))
    rows = []
    batch = max(1, method.batch_size)
    for start in range(0, len(args.images), batch):
        rows.append(np.asarray(method.describe(args.images[start:start + batch]), dtype=np.float32))
    descriptors = np.concatenate(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.save(args.out, descriptors)
    print(f"Wrote {descriptors.shape[0]} descriptors of dimension {descriptors.shape[1]} to {args.out}", file=sys.stderr)
    return 0
