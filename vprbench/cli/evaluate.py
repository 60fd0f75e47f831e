"""vprbench evaluate / describe.

`evaluate` builds one run spec per method x dataset and calls `vprbench.evaluation.evaluate` for each: one
spec runs (and prints) at once, under torchrun too; several are a sweep (claimed, resumable,
shared by processes). Every option means the same either way.
"""
from __future__ import annotations

import io
import json
import sys

from ..errors import DESCRIBED, VPRBenchError
from ..text import plural, recall_text
from .console import console as make_console
from .console import say, say_error
from .options import (add_location_options, add_method_options, add_run_options, add_spec_options, add_sweep_options,
                      explicit_run_options, method_options, output_file, path_argument, progress, refuse_unused,
                      resolve_locations, run_settings, spec_overrides)


def add_parsers(commands) -> None:
    p = commands.add_parser("evaluate", help="evaluate methods on datasets (Recall@K, PR); several of each run as a "
                                             "sweep; under torchrun, one evaluation sharded over the ranks")
    add_method_options(p, several=True)
    p.add_argument("--dataset", required=True, nargs="+", help="dataset names ('vprbench datasets list') or folders of your own")
    p.add_argument("--protocol", help="the dataset's protocol ('vprbench datasets info NAME'; default: its first)")
    add_spec_options(p)
    add_run_options(p)
    add_sweep_options(p)
    add_location_options(p)
    p.add_argument("--candidates", type=path_argument, metavar="FILE",
                   help="start the re-ranking from candidates exported by 'vprbench candidates export' (named in the record)")
    p.add_argument("--json", action="store_true",
                   help="print the result record as JSON on stdout, as stored (one run only): its per-query arrays "
                        "by reference, per_query.file naming the .npz saved beside it")
    p.add_argument("--inline-arrays", action="store_true",
                   help="with --json: print the per-query arrays inline as lists instead (large: queries x K)")
    p.set_defaults(run=run_evaluate, kept=DESCRIBED)

    p = commands.add_parser("describe", help="write global descriptors of images to a .npy file, in input order")
    add_method_options(p)
    p.add_argument("--store-dtype", choices=("float32", "float16"), default="float32",
                   help="descriptor store precision (default: float32)")
    add_run_options(p, download=False, strict=False)  # describe loads no dataset: no counts to check
    p.add_argument("images", nargs="+", type=path_argument, help="image files")
    p.add_argument("--out", required=True, type=output_file(".npy"), help="output .npy file")
    p.add_argument("--fit-on", type=path_argument,
                   help="folder of database images (those directly in it, not in its subfolders): the method's "
                        "vocabulary and PCA-whitening are fitted on them (without it, PCA is fitted on the images "
                        "described)")
    p.add_argument("--dataset", help="apply this dataset's per-method settings (e.g. AnyLoc's resize and vocabulary); "
                                     "its own images then share the descriptor stores 'evaluate' keeps")
    add_location_options(p)
    p.set_defaults(run=run_describe, kept=DESCRIBED)


def run_evaluate(args) -> int:
    from ..datasets import is_path
    from ..distributed import Ranks

    if all(is_path(name) for name in args.dataset):  # folders of your own are read where they are
        refuse_unused(args, "data_dir", "when every --dataset is a folder of your own")
    resolve_locations(args)
    if args.inline_arrays and not args.json:  # it would be ignored, silently
        raise VPRBenchError("--inline-arrays is for --json (the record printed as JSON): add --json, or drop it.")
    settings = run_settings(args)
    if args.candidates is not None:
        import dataclasses

        settings = dataclasses.replace(settings, candidates=args.candidates)
    options, overrides = method_options(args), spec_overrides(args)
    runs = len(args.method) * len(args.dataset)
    ranks = Ranks.from_environment(settings.device)
    with ranks.working(say_error):
        if runs > 1:
            if ranks.distributed:
                raise VPRBenchError(f"torchrun shards one evaluation over its ranks; this command names {runs} "
                                    "(methods x datasets): give one method and one dataset per torchrun.")
            if args.json:
                raise VPRBenchError(f"--json prints one run's record, but this command makes {runs} runs (methods x "
                                    "datasets): give one method and one dataset, or read the records with "
                                    "'vprbench leaderboard --format csv'.")
            return run_matrix(args, settings, options, overrides)
        return run_one(args, settings, options, overrides, ranks)


def run_one(args, settings, options, overrides, ranks) -> int:
    from ..datasets import is_path, load_dataset
    from ..evaluation import evaluate, save_result
    from ..leaderboard.shown import PIPELINE_CHECK, random_weights
    from ..methods.registry import method_entry
    from ..spec import resolve_spec, split_run_settings

    name, own = args.dataset[0], None
    if is_path(name):  # a folder of one's own is read once, for its spec's protocol and for the run
        method_entry(args.method[0])  # a mistyped method is said before the folder is read
        own = load_dataset(name, protocol=args.protocol, cache_dir=settings.cache_dir)
    spec = resolve_spec(args.method[0], name if own is None else own, options=split_run_settings(options)[0],
                        protocol=args.protocol, search=overrides["search"], ks=overrides["k"],
                        stages=overrides["stages"] or (),
                        store_dtype=overrides["store_dtype"] or "float32", data_dir=settings.data_dir,
                        cache_dir=settings.cache_dir)
    with progress(args, ranks.rank == 0) as shown:
        record = evaluate(spec, settings, dataset=own, progress=shown, ranks=ranks)
    if record is None:  # another rank than 0: its shard is written, rank 0 reports
        return 0
    if not args.json:
        make_console().print(results_table(record))
    elif random_weights(record):  # no table titles the record: stderr says it, stdout stays the record alone
        say(PIPELINE_CHECK, stderr=True)
    try:
        stored = save_result(record, settings.cache_dir)
    except VPRBenchError:
        if args.json:  # not stored (full or read-only disk): still seen, its arrays inline as no .npz holds them
            print(json.dumps(record, indent=2, sort_keys=True))
        raise
    if args.json:  # as stored, so `jq` sees what read_results and the board read
        print(json.dumps(record if args.inline_arrays else json.loads(stored.read_text(encoding="utf-8")),
                         indent=2, sort_keys=True))
    return 0


def run_matrix(args, settings, options, overrides) -> int:
    """`vprbench evaluate --method A B --dataset X Y [--protocol P]`: a plan from the command line."""
    from ..sweep import build_plan, run_cells
    from .run import report

    data = {"methods": [{"name": m} for m in args.method],
            "datasets": [{"name": d, **({"protocol": args.protocol} if args.protocol else {})} for d in args.dataset]}
    plan = build_plan(data, "the command line", overrides={**overrides, "options": {**options, **explicit_run_options(args)}},
                      data_dir=settings.data_dir, cache_dir=settings.cache_dir)
    return report("evaluate", run_cells(plan.cells, settings, lease_s=args.lease, plan="evaluate", progress=progress(args)))


def results_table(record: dict):
    from rich.table import Table

    from ..leaderboard.cells import own_detail, row_of
    from ..leaderboard.shown import PIPELINE_CHECK, descriptor_bytes, random_weights
    from ..text import percent

    counts, timings = record["counts"], record["timings"]
    # the board keeps such a run out of every cell; its own table says so too
    random = f" ({PIPELINE_CHECK})" if random_weights(record) else ""
    # a row of its own on the board (other weights, an approximate search, a float16 store, a part fitted on
    # the evaluated database): its table names it by the board's marks (random weights are said after the dataset)
    marks = [m for m in row_of(record).mark.split("; ") if m and m != "weights random"]
    label = (record.get("label") or record["method"]) + (f" ({', '.join(marks)})" if marks else "")
    # an own folder's protocol id ('name:own') hides its radius: titled as its board column is
    own = record.get("dataset_kind") == "own"
    dataset = f"{record['dataset']} ({own_detail(record)})" if own else record["protocol"]["id"]
    table = Table(title=f"{label} on {dataset}{random}", show_header=True)
    for k in record["recall"]:
        table.add_column(f"R@{k}", justify="right")
    table.add_column("AUC-PR", justify="right")
    table.add_column("R@100%P", justify="right")
    table.add_column("max F1", justify="right")
    max_f1 = record.get("max_f1")  # older records lack it
    table.add_row(*[recall_text(v) for v in record["recall"].values()],
                  f"{record['auc_pr']:.3f}", percent(record["recall_at_100_precision"]),
                  "-" if max_f1 is None else f"{max_f1:.3f}")
    computed = record["descriptors_computed"]
    table.caption = (
        f"R@K and R@100%P in percent, AUC-PR and max F1 from 0 to 1 ({PR_CONVENTION}); {counts['database']} database, "
        f"{plural(counts['queries'], 'query')} "
        f"({counts['queries_without_positives']} without positives, counted as failures); "
        + all_zero_text(counts) +
        f"dim {record['descriptor_dim']}" + (f" ({size} bytes as stored)" if (size := descriptor_bytes(record)) else "")
        + f"; descriptors computed now: {computed['database'] + computed['queries']}; "
        f"{timings['total_s']:.1f} s total"
    )
    return table


#: VPR-Bench's precision-recall convention, which a perfect AUC-PR beside R@1 60 would otherwise hide
PR_CONVENTION = "the last three over each query's top-1 match, recall being the share of correct ones accepted, as VPR-Bench"


def all_zero_text(counts: dict) -> str:
    """The caption's note of all-zero descriptors, when there were any ('' too for a record from before
    they were counted)."""
    queries, database = counts.get("all_zero_queries", 0), counts.get("all_zero_database", 0)
    if not queries and not database:
        return ""
    return (f"{plural(queries, 'query')} and {plural(database, 'database image')} with all-zero descriptors "
            "(nothing described; such queries count as failures); ")


def run_describe(args) -> int:
    """The evaluation's describe path without the search: the --fit-on images are the database
    (what the method fits on, and what PCA-whitening is fitted on), the images the queries."""
    import numpy as np

    from ..distributed import Ranks
    from ..evaluation.extract import describe_splits
    from ..evaluation.joint import stacked
    from ..evaluation.pipeline import create_run_method, loader_workers
    from ..evaluation.postprocess import check_database_size, fits_on_database, postprocessed
    from ..fsutil import atomic_write
    from ..images import refuse_dead_link
    from ..leaderboard.shown import PIPELINE_CHECK, asks_random
    from ..loader import postprocess_datasets_of
    from ..methods.attributes import use_dataset
    from ..paths import regular_file
    from ..row_sources import DEFAULT_MEMORY_BUDGET

    if args.dataset is None:  # the images are given as paths: no dataset is looked up
        refuse_unused(args, "data_dir", "without --dataset (the images are read from the paths given)")
    resolve_locations(args)
    settings = run_settings(args)
    root, label = None, f"describe-{args.dataset or 'images'}"
    if args.dataset is not None:  # '' is an unknown name, not none
        from ..datasets import dataset_location, dataset_manifest

        manifest = dataset_manifest(args.dataset)  # an unknown name would apply no settings, silently
        root = _absolute(dataset_location(manifest, settings.data_dir))
        given = [*args.images, *([args.fit_on] if args.fit_on is not None else [])]
        if all(_absolute(p).is_relative_to(root) for p in given):  # its own images: named and stored
            label = args.dataset  # as evaluate names them, so either one serves the other's stores
        else:
            root = None
    method = create_run_method(args.method, method_options(args), settings)
    for image in args.images:
        if image.is_dir():
            raise VPRBenchError(f"{image} is a folder: give its image files (e.g. {image / '*.jpg'}).")
        if not regular_file(image, "Image"):  # a named pipe is refused as such, not as missing
            refuse_dead_link(image)  # said as the image lister says it ('not found' of a file ls shows)
            raise VPRBenchError(f"Image not found: {image}")
    splits = {}
    if args.fit_on is not None:
        if not args.fit_on.is_dir():
            raise VPRBenchError(f"--fit-on must be a folder of images, got {args.fit_on}")
        from ..images import list_images, nested_image_folders

        splits["database"] = [_absolute(p) if root else p for p in list_images(args.fit_on)]
        # as an own folder's database/ says them: a fit on the few images at the top was silent
        nested = nested_image_folders(args.fit_on)
        if not splits["database"]:  # was 'No images to describe in the database split', naming no folder
            where = f" directly (only in its subfolders {nested}: move them up into it)" if nested else ""
            raise VPRBenchError(f"--fit-on folder {args.fit_on} holds no images{where}: give the folder of database "
                                "images.")
        if nested:
            import warnings

            warnings.warn(f"--fit-on {args.fit_on}: the images in its subfolders ({nested}) are not read, only those "
                          "directly in it; move them up to fit on them too.", stacklevel=2)
    splits["queries"] = [_absolute(p) if root else p for p in args.images]
    keyed = None  # the method's own settings
    if args.dataset is not None:  # before needs_fit is read: the dataset's vocabulary may be ready (AnyLoc's domain)
        from ..spec_options import given_options, spec_options

        use_dataset(method, args.dataset)
        # keyed as evaluate keys them (its spec's options): an option naming this dataset is as unset
        keyed = spec_options(method.name, given_options(method.options, method.name, args.dataset))
    names = postprocess_datasets_of(method)
    if names is not None and list(names) != [args.dataset]:
        raise VPRBenchError(f"{stacked(args.method, names)}, as `vprbench evaluate --dataset {args.dataset}` does; "
                            "describe fits it on --fit-on (or the images described): evaluate, or drop the option that "
                            "stacks them (AnyLoc: --pca-on).")
    if args.fit_on is None and method.needs_fit:
        raise VPRBenchError(f"Method {args.method!r} fits a vocabulary on database images: give --fit-on FOLDER "
                            "(or a ready vocabulary with --vocabulary, where the method takes one).")
    # a dataset's own database images are still of use: described into the stores evaluate reads
    if args.fit_on is not None and root is None and not fits_on_database(method):
        raise VPRBenchError(f"Method {args.method!r} fits nothing on database images with these options (no vocabulary "
                            f"to fit, no post-processing such as PCA): --fit-on {args.fit_on} would be described for "
                            "nothing; drop it.")
    # before any image is described, as evaluate checks it (PCA wider than the images it is fitted on)
    fitted_on = f"--fit-on {args.fit_on}" if args.fit_on is not None else "the images described (no --fit-on)"
    check_database_size(method, len(splits.get("database", splits["queries"])), fitted_on)
    ranks = Ranks.from_environment(settings.device)
    with ranks.working(say_error), progress(args, ranks.rank == 0) as shown:
        described = describe_splits(method, splits, root=root, label=label,
                                    cache_dir=settings.cache_dir, progress=shown, store_dtype=args.store_dtype,
                                    workers=loader_workers(settings, method), lock_timeout=settings.lock_timeout,
                                    settings=keyed, ranks=ranks)
    if described.stores is None:  # another rank than 0 under torchrun: its share is written, rank 0 writes --out
        return 0
    queries = described.stores["queries"]
    database = described.stores.get("database", queries)
    _, queries, _ = postprocessed(method, database, queries, settings.memory_budget or DEFAULT_MEMORY_BUDGET)
    descriptors = np.ascontiguousarray(queries.read_rows(0, queries.row_count), dtype=np.float32)
    buffer = io.BytesIO()
    np.save(buffer, descriptors)
    atomic_write(args.out, buffer.getvalue())
    # descriptors of random weights are a pipeline check too: said as evaluate's table says it
    check = f" ({PIPELINE_CHECK})" if asks_random(method.options) else ""
    print(f"Wrote {plural(descriptors.shape[0], 'descriptor')} of dimension {descriptors.shape[1]} to {args.out}{check}",
          file=sys.stderr)
    return 0


def _absolute(path):
    """`path` absolute, '..' folded, links kept (an image linked from elsewhere is still the dataset's)."""
    import os
    from pathlib import Path

    return Path(os.path.abspath(Path(path).expanduser()))
