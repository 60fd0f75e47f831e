"""vprbench evaluate / describe."""
from __future__ import annotations

import io
import json
import os
import sys
from contextlib import nullcontext
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from ..datasets import load_dataset
from ..distributed import Ranks
from ..errors import VPRBenchError
from ..evaluation import append_result, describe_splits, evaluate
from ..fsutil import atomic_write
from ..methods import create_method
from ..paths import cache_root
from .console import console as make_console
from .options import (add_download_option, add_extraction_options, add_location_options, add_method_options,
                      add_search_options, apply_locations, extraction_settings, method_options, parse_ks,
                      search_settings)
from .run import add_sweep_options, run_matrix


def progress_bar(console: Console) -> Progress:
    return Progress(TextColumn("{task.description}", markup=False), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=console, transient=True)


def add_parsers(commands) -> None:
    p = commands.add_parser("evaluate", help="evaluate methods on datasets (Recall@K, PR); several of each run as a "
                                             "sweep; under torchrun, one evaluation sharded over the ranks")
    add_method_options(p, several=True)
    add_extraction_options(p)
    p.add_argument("--dataset", required=True, nargs="+", help="dataset names ('vprbench datasets list') or folders of your own")
    p.add_argument("--protocol", help="the dataset's protocol ('vprbench datasets info NAME'; default: its first)")
    add_sweep_options(p)
    add_search_options(p)
    add_location_options(p)
    add_download_option(p)
    p.add_argument("--k", nargs="+", help="K values for Recall@K (default 1 5 10 20)")
    p.add_argument("--strict", action="store_true", help="fail when image counts differ from the manifest")
    p.add_argument("--json", action="store_true", help="print the result record as JSON on stdout")
    p.set_defaults(run=run_evaluate)

    p = commands.add_parser("describe", help="write global descriptors of images to a .npy file, in input order")
    add_method_options(p)
    add_extraction_options(p)
    add_search_options(p)
    p.add_argument("images", nargs="+", type=Path, help="image files")
    p.add_argument("--out", required=True, type=Path, help="output .npy file")
    p.add_argument("--fit-on", type=Path,
                   help="folder of database images: the method's vocabulary and PCA-whitening are fitted on them "
                        "(without it, PCA is fitted on the images described)")
    p.add_argument("--dataset", help="apply this dataset's per-method settings (e.g. AnyLoc's resize and vocabulary)")
    add_location_options(p)
    p.set_defaults(run=run_describe)


def run_evaluate(args) -> int:
    apply_locations(args)
    options = method_options(args)
    if len(args.method) > 1 or len(args.dataset) > 1 or args.protocol:
        return run_matrix(args, options)  # the sweep: resumable, shared across processes
    args.method, args.dataset = args.method[0], args.dataset[0]
    ks = parse_ks(args.k)
    ranks = Ranks.from_environment(options["device"])
    try:
        options["device"] = ranks.device(options["device"])
        method = create_method(args.method, **options)  # method and options are checked before any data is touched
        ranks.agree({"method": args.method, "options": {k: v for k, v in options.items() if k != "device"},
                     "dataset": args.dataset, "data_dir": os.environ.get("VPRBENCH_DATA"), "k": ks,
                     "cache": str(cache_root().resolve()), "store_dtype": args.store_dtype,
                     "search": search_settings(args)}, "options")
        # loaded (and fetched, on first use) by rank 0 alone, then handed to the other ranks
        dataset = ranks.on_zero(lambda: load_dataset(args.dataset, args.data_dir, strict=args.strict,
                                                     fetch=args.download or None))
        with progress_bar(make_console(stderr=True)) if ranks.rank == 0 else nullcontext() as progress:
            record = evaluate(method, dataset, ks=ks, cache_dir=args.cache_dir, progress=progress, ranks=ranks,
                              **extraction_settings(args, options["device"]), **search_settings(args))
    finally:
        ranks.close()
    if record is None:  # another rank than 0: its shard is written, rank 0 reports
        return 0
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
    """The evaluation's describe path without the search: the --fit-on images are the database
    (what the method fits on, and what PCA-whitening is fitted on), the images the queries."""
    from ..evaluation.search import postprocessed

    apply_locations(args)
    if args.out.suffix != ".npy":
        raise VPRBenchError(f"--out must be a .npy file, got {args.out}")
    options = method_options(args)
    method = create_method(args.method, **options)
    for image in args.images:
        if not image.is_file():
            raise VPRBenchError(f"Image not found: {image}")
    splits = {}
    if args.fit_on is not None:
        if not args.fit_on.is_dir():
            raise VPRBenchError(f"--fit-on must be a folder of images, got {args.fit_on}")
        from ..images import list_images

        splits["database"] = list_images(args.fit_on)
    elif method.needs_fit:
        raise VPRBenchError(f"Method {args.method!r} fits a vocabulary on database images: give --fit-on FOLDER "
                            "(or a ready vocabulary with --vocabulary, where the method takes one).")
    splits["queries"] = list(args.images)
    if args.dataset:
        method.use_dataset(args.dataset)
    with progress_bar(make_console(stderr=True)) as progress:
        described = describe_splits(method, splits, label=f"describe-{args.dataset or 'images'}",
                                    cache_dir=args.cache_dir, progress=progress,
                                    **extraction_settings(args, options["device"]))
    queries = described.stores["queries"]
    database = described.stores.get("database", queries)
    _, queries, _ = postprocessed(method, database, queries, search_settings(args)["memory_budget"])
    descriptors = np.ascontiguousarray(queries.read_rows(0, queries.row_count), dtype=np.float32)
    buffer = io.BytesIO()
    np.save(buffer, descriptors)
    atomic_write(args.out, buffer.getvalue())
    print(f"Wrote {descriptors.shape[0]} descriptors of dimension {descriptors.shape[1]} to {args.out}", file=sys.stderr)
    return 0
