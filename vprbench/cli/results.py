"""vprbench results export / verify / import / import-vpr-bench: result bundles and results repositories."""
from __future__ import annotations

import math

from ..errors import VPRBenchError
from .console import say
from .options import check_new_folder, output_file, path_argument, resolve_locations


def add_parsers(commands) -> None:
    p = commands.add_parser("results", help="result bundles: export runs, verify and import contributed ones")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")

    e = actions.add_parser("export", help="the chosen runs as one bundle (records, per-query arrays, method cards)")
    e.add_argument("--run", dest="run_ids", nargs="+", default=[], metavar="ID", help="run ids to export")
    e.add_argument("--method", help="with --dataset: every run of this method (name or label) on the dataset")
    e.add_argument("--dataset", help="with --method: the dataset")
    e.add_argument("--to", type=output_file(), required=True, metavar="FILE", help="the bundle to write (e.g. runs.tar.gz)")
    e.add_argument("--contributor", help="who contributes the runs, at most 200 characters (shown beside them on the "
                                         "leaderboard)")
    e.add_argument("--cache-dir", help="the results store to export from")
    e.set_defaults(run=run_export)

    v = actions.add_parser("verify", help="re-score every record of bundles, or of results repositories, against the "
                                          "ground truth vprbench ships")
    v.add_argument("bundles", nargs="+", type=path_argument, metavar="FILE|DIR",
                   help="bundles (.tar.gz), or results repositories (every run in them is re-scored)")
    _check_options(v)
    v.set_defaults(run=run_verify)

    i = actions.add_parser("import", help="merge verified bundles into a results repository")
    i.add_argument("bundles", nargs="+", type=path_argument, metavar="FILE")
    i.add_argument("--into", type=path_argument, required=True, metavar="DIR", help="the results repository")
    i.add_argument("--lock-timeout", type=float, help="seconds to wait for another import into DIR (default: as long as it takes)")
    _check_options(i)
    i.set_defaults(run=run_import)
    add_vpr_bench_parser(actions)


def _check_options(parser) -> None:
    parser.add_argument("--data-dir", help="where the datasets are: their ground truth is what the records are checked against")
    parser.add_argument("--cache-dir", help="where image identities are remembered")
    parser.add_argument("--max-size", type=float, default=1024, metavar="MIB",
                        help="the most a bundle may unpack to, in MiB (default 1024): archive bombs stop here")


def _max_bytes(args) -> int:
    if not (args.max_size > 0 and math.isfinite(args.max_size)):
        raise VPRBenchError(f"--max-size takes a positive number of MiB, got {args.max_size:g}.")
    return int(args.max_size * 2**20)


def _truth(args):
    from ..evaluation.rescore import DataGroundTruth

    return DataGroundTruth(args.data_dir, args.cache_dir)


def run_export(args) -> int:
    from ..bundles import export_bundle, select_records
    from ..evaluation import read_results

    resolve_locations(args)
    chosen = select_records(read_results(args.cache_dir), run_ids=args.run_ids, method=args.method, dataset=args.dataset)
    path = export_bundle(chosen, args.to, args.contributor)
    say(f"Wrote {path}: {len(chosen)} run(s), {path.stat().st_size / 1024:.1f} KiB")
    return 0


def run_verify(args) -> int:
    from ..bundles import verify_bundle, verify_repository

    resolve_locations(args)
    truth, ok = _truth(args), True
    for bundle in args.bundles:
        verify = verify_repository if bundle.is_dir() else verify_bundle
        report = verify(bundle, truth, max_bytes=_max_bytes(args))
        for line in report.lines():
            say(line)
        ok &= report.ok
    return 0 if ok else 1


def run_import(args) -> int:
    from ..bundles import import_bundles

    resolve_locations(args)
    check_new_folder(args.into, "--into")
    reports = import_bundles(args.bundles, args.into, _truth(args), max_bytes=_max_bytes(args),
                             lock_timeout=args.lock_timeout)
    for report in reports:
        for line in report.lines():
            say(line)
    return 0 if all(r.ok for r in reports) else 1


def add_vpr_bench_parser(actions) -> None:
    p = actions.add_parser("import-vpr-bench", help="VPR-Bench's precomputed matches as records, re-scored here")
    p.add_argument("folder", type=path_argument, metavar="FOLDER",
                   help="precomputed_matches/<dataset> (one folder per method) or one method's folder")
    p.add_argument("--dataset", required=True, help="the vprbench dataset they were computed on, e.g. corridor")
    p.add_argument("--data-dir", help="where the dataset is (its ground truth scores the matches)")
    p.add_argument("--cache-dir", help="the results store the records go to")
    p.set_defaults(run=run_import_vpr_bench)


def run_import_vpr_bench(args) -> int:
    from ..bundles.vpr_bench import import_vpr_bench
    from ..evaluation import save_result
    from ..text import recall_text

    resolve_locations(args)
    records = import_vpr_bench(args.folder, args.dataset, data_dir=args.data_dir, cache_dir=args.cache_dir)
    for record in records:
        path = save_result(record, args.cache_dir)
        shown = " ".join(f"R@{k} {recall_text(v)}" for k, v in record["recall"].items())  # as the leaderboard shows it
        say(f"{record['imported']['method']} on {record['protocol']['id']}: {shown} (imported from VPR-Bench, "
              f"re-scored) -> {path}")
    return 0
