"""`vprbench leaderboard compare A B --dataset D`: two cells, paired over the same queries (and the
same blocks or places of them)."""
from __future__ import annotations

from ..errors import VPRBenchError, closest_names, require
from ..text import plural
from .cells import Board, Cell
from .shown import left_out
from .tables import plain_mark
from .truth import unproven_note
from ..evaluation.blocks import for_record, shared
from ..evaluation.metrics import successes
from .stats import RESAMPLES, bootstrap_ci, check_k_and_seed, format_p, overlaps, paired_test


def _cell(board: Board, method: str, dataset: str) -> Cell:
    """The cell of `method` in the column `dataset` names: its heading as every table shows it
    (e.g. 'my-traverse (own, ±10 frames)'), its key, or a dataset name that only one column has."""
    known = ", ".join(repr(c.title) for c in board.columns) or "none"
    columns = [c for c in board.columns if dataset in (c.title, c.key)] or \
        [c for c in board.columns if c.dataset == dataset] or _own_columns(board, dataset)
    benchmark = [c for c in columns if c.kind == "benchmark"]
    if not columns:
        _left_out(board, method, dataset)
        titles = [c.title for c in board.columns]
        raise VPRBenchError(f"No run on dataset {dataset!r} fills a cell.{closest_names(dataset, titles)} "
                            f"Datasets on the leaderboard: {known}.")
    if len(columns) > 1 and not benchmark:
        raise VPRBenchError(f"Several columns are datasets named {dataset!r}: give one of "
                            f"{', '.join(repr(c.title) for c in columns)}. Datasets on the leaderboard: {known}.")
    column = ([c for c in benchmark if dataset in (c.title, c.key) or c.default] or benchmark or columns)[0]
    rows = [r for r in board.find_row(method) if board.cell(r, column)]
    if not rows:
        _left_out(board, method, column.dataset)
        names = [r.name for r in board.rows if board.cell(r, column)]
        raise VPRBenchError(f"No run of {method!r} on {column.title}.{closest_names(method, names)} "
                            f"Rows on {column.title}: {', '.join(names)}.")
    official = [r for r in rows if r.official]
    if len(rows) > 1 and len(official) != 1:
        raise VPRBenchError(f"{method!r} has several rows on {column.title}: give one of {', '.join(repr(r.name) for r in rows)}.")
    return board.cell((official or rows)[0], column)


def _own_columns(board: Board, dataset: str) -> list:
    """The columns of the folder `--dataset ./mydata` names, the path evaluate was given: by the folder
    its runs' records name (dataset_root, resolved)."""
    from ..datasets import own_root

    root = own_root(dataset)
    keys = {c.column.key for c in board.cells.values() if root is not None and c.record.get("dataset_root") == root}
    return [c for c in board.columns if c.key in keys]


def _left_out(board: Board, method: str, dataset: str) -> None:
    """A run of `method` on the column's dataset that the board left out of every cell (random weights,
    damaged arrays) is named with why, as the board and the site name it: 'no run' would deny it exists."""
    for record, why in board.excluded:
        run, label, shown = left_out(record)
        if record.get("dataset") == dataset and method in (label, record.get("method"), record.get("label")):
            raise VPRBenchError(f"Run {run} of {method!r} on {shown} is left out of every cell: {why}. Compare "
                                "two rows the leaderboard shows ('vprbench leaderboard' lists them).")


def shared_resampling(first: Cell, second: Cell):
    """The units both runs are drawn by: their dataset's (the same queries, so the same units), on a
    traverse the longer blocks of the two (a sequence run's cover its window: evaluation/blocks.py);
    a run that keeps no places (recorded before them) takes the other's."""
    found = [for_record(c.record, c.arrays) for c in (first, second)]
    both = shared(*found)
    if both is not None:
        return both
    richer = [r for r in found if r.scheme != "queries"]
    if len(richer) == 1:
        return richer[0]
    raise VPRBenchError(f"Runs {first.record.get('run_id')} and {second.record.get('run_id')} state different "
                        f"resampling units ({found[0].text()} and {found[1].text()}) for the same queries; "
                        "rerun one of them.")


def compare(board: Board, a: str, b: str, dataset: str, *, k: int = 1, seed: int = 0) -> dict:
    """Both cells' R@k with intervals, and the paired tests of A against B: the bootstrap draws the
    dataset's units (blocks, places) for both; per-query intervals are given beside them."""
    require(board, Board, "compare takes a Board: vprbench.leaderboard.build_board(read_results(cache_dir))")
    for what, value in (("a", a), ("b", b)):
        require(value, str, f"compare's {what} takes a row's name or key as the leaderboard shows it")
    require(dataset, str, "compare's dataset takes a column's name as the leaderboard shows it, e.g. 'corridor'")
    k, seed = check_k_and_seed(k, seed)
    first, second = _cell(board, a, dataset), _cell(board, b, dataset)
    if first is second:  # one row named twice (by name, label or key): its run against itself proves nothing
        raise VPRBenchError(f"{a!r} and {b!r} name the same run ({first.record.get('run_id')}, {first.row.name} on "
                            f"{first.column.title}): compare two different rows ('vprbench leaderboard' lists them).")
    for cell in (first, second):
        if cell.arrays is None:
            raise VPRBenchError(f"Run {cell.record.get('run_id')} ({cell.row.name}) has no per-query data (recorded by "
                                "vprbench 0.1, or its .npz is gone): rerun it to compare.")
        if cell.record["per_query"]["k"] < k:
            raise VPRBenchError(f"Run {cell.record.get('run_id')} searched only the top {cell.record['per_query']['k']}: "
                                f"R@{k} cannot be compared; use a smaller --k.")
    ranks = [c.arrays["first_positive_rank"] for c in (first, second)]
    if len(ranks[0]) != len(ranks[1]) or first.record.get("dataset_fingerprint") != second.record.get("dataset_fingerprint"):
        raise VPRBenchError(f"The two runs were not on the same queries of {dataset} (dataset fingerprints "
                            f"{first.record.get('dataset_fingerprint')} and {second.record.get('dataset_fingerprint')}).")
    wins = [successes(r, k) for r in ranks]
    resampling = shared_resampling(first, second)
    intervals = [bootstrap_ci(w, resampling, seed=seed) for w in wins]
    return {"dataset": first.column.title, "k": k, "cells": (first, second), "intervals": intervals,
            "overlap": overlaps(*intervals), "test": paired_test(*wins, resampling, seed=seed),
            "resampling": resampling, "per_query": {"intervals": [bootstrap_ci(w, seed=seed) for w in wins],
                                                    "test": paired_test(*wins, seed=seed)}}


def _source(cell: Cell) -> str:
    """Where a cell's number comes from, with the site's mark, when not measured here: a contributed run
    set against a local one says which is which (and who sent it)."""
    if not (mark := plain_mark(cell.source)):
        return ""
    sent = (cell.record.get("_contribution") or {}).get("contributor")
    return f" ({mark}: {cell.source}" + (f", sent by {sent})" if sent else ")")


def describe(result: dict) -> str:
    first, second = result["cells"]
    t, k, units = result["test"], result["k"], result["resampling"]
    plain = result["per_query"]
    width = max(len(first.row.name), len(second.row.name))
    per = units.scheme != "queries"  # per-query intervals beside the dataset's, for comparison
    lines = [f"{result['dataset']}: R@{k} of two runs over the same {t['queries']} queries "
             f"(seeded bootstrap, {RESAMPLES:,} resamples, seed {t['seed']}; resampled {units.text()}"
             + (", the same units for both" if per else "") + ")"]
    for cell, (low, high), value, (p_low, p_high) in zip((first, second), result["intervals"], (t["a"], t["b"]),
                                                          plain["intervals"]):
        lines.append(f"  {cell.row.name:<{width}}  R@{k} {value:5.1f} %  95 % CI [{low:.1f}, {high:.1f}]  "
                     + (f"(per query [{p_low:.1f}, {p_high:.1f}])  " if per else "") + f"run {cell.record.get('run_id')}"
                     + _source(cell))
    q = plain["test"]["ci"]
    # as `leaderboard` says it: numbers no ground truth here checked are compared all the same, not silently
    note = [note] if (note := unproven_note((first, second))) else []
    if t["identical"]:  # the same queries right and wrong: nothing to test, p = 1 would read as a finding
        lines += [f"  intervals overlap: {'yes' if result['overlap'] else 'no'}",
                  f"  same queries right: both get the same {plural(t['both'], 'query')} right at R@{k} and the same "
                  f"{t['neither']} wrong; no paired test is meaningful (difference 0).", *note]
        return "\n".join(lines)
    lines += [
        f"  intervals overlap: {'yes' if result['overlap'] else 'no'}",
        f"  difference ({first.row.name} - {second.row.name}): {t['difference']:+.1f} pp, 95 % CI "
        f"[{t['ci'][0]:+.1f}, {t['ci'][1]:+.1f}]" + (f" (per query [{q[0]:+.1f}, {q[1]:+.1f}])" if per else "")
        + f", paired bootstrap p {format_p(t['p_bootstrap'], t['resamples'])}",
        f"  McNemar exact test (takes the queries as independent): {plural(t['only_a'], 'query')} only {first.row.name} "
        f"gets right, {t['only_b']} only {second.row.name}; p = {t['p_mcnemar']:.3g}",
        f"  {'A difference at the 5 % level' if t['significant'] else 'No difference at the 5 % level'} "
        # units.text() reads after "resampled" ("by place (...)", "per query"), not after "over"
        f"(the paired-bootstrap interval, resampled {units.text()}, {'excludes' if t['significant'] else 'includes'} 0).",
        *note,
    ]
    return "\n".join(lines)
