"""`vprbench leaderboard publish --to DIR`: the leaderboard section of the docs site.

Everything is written into a temporary folder beside the target and swapped in at the end,
so a failure (full disk, a kill) leaves the previous section whole and no partial one.
"""
from __future__ import annotations

import errno
import functools
from collections import Counter
import json
import os
import re
import shutil
import tempfile
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..errors import VPRBenchError, require
from ..fsutil import LockTimeout, lock
from ..paths import folder_path, safe_name
from ..text import percent, quantity
from . import figures
from .staging import alive, mark_read_at, newer_in_place, remove_stale_sections, swap
from .domains import domain_datasets
from .downloads import plain, record_download, summary
from .escape import code, public, text, to_csv
from .cells import CELL_RULE, Board, Cell, Column, build_board
from .shown import descriptor_bytes, hardware_of, licence_shown, plugins_shown, row_name, weights_shown
from .truth import LocalTruth, truth_note
from .stats import check_k_and_seed
from ..evaluation.blocks import RULE, for_record
from ..evaluation.identity import benchmark_protocols
from ..evaluation.metrics import successes
from .compare import shared_resampling
from .stats import RESAMPLES, format_test, overlaps, paired_test
from .tables import (DOWNLOAD_UNITS, GROUPS, RESULTS_LEGEND, TOLERANCE_PP, cell_stats, comparisons, fmt, group_table,
                     left_out_section, marks_note, number, other_rows, reported_page, row_cells, with_ci)

SECTION = "leaderboard"
#: MkDocs Material front matter: the wide tables get the table-of-contents column
PAGE_HEAD = "---\nhide:\n  - toc\n---\n"


def page_head(title: str) -> str:
    """PAGE_HEAD with the page's title set, HTML-escaped and without absolute paths (escape.public):
    without it MkDocs Material writes the title it takes from the heading with its entities decoded
    (`striptags`) into <title>, where a name holding '</title><img ...>' would become a live element."""
    import html

    return PAGE_HEAD.replace("---\n", f"---\ntitle: {json.dumps(html.escape(public(title), quote=True))}\n", 1)
#: mosaics drawn per dataset page (the best rows by R@1)
MOSAIC_ROWS = 4


def publish(folder: Path, cache_dir=None, *, data_dir=None, seed: int = 0, skipped: list | None = None,
            results=None, refused: list | None = None) -> Path:
    """Write <folder>/leaderboard/ (overview, one page per dataset, figures, downloads) from the
    results store, and from the results repository `results` when given (each cell marked by where
    its number comes from); returns that folder. Nothing is changed when anything fails. Each run is
    re-scored against its ground truth first (a benchmark's under `data_dir`, else the default data root; an own
    folder's at its path): the files of those that do not re-score to their numbers are appended to `refused`."""
    require(folder, (str, os.PathLike), "publish takes the docs folder to write the leaderboard into, e.g. 'docs'")
    folder, (_, seed) = Path(folder), check_k_and_seed(1, seed)  # before any record is read
    data_dir = folder_path(data_dir, "data_dir")  # else a wrong one is found out only when a page needs images
    if results is not None:
        require(results, (str, os.PathLike), "publish's results take the folder 'vprbench results import --into' wrote")
    if folder.exists() and not folder.is_dir():
        raise VPRBenchError(f"--to {folder} is a file, not a folder: give the docs folder, e.g. --to docs/")
    read_at = time.time_ns()  # before the results are read: of publishes at once, the one that read them last wins
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from ..bundles.repository import no_runs, read_runs

        records = read_runs(cache_dir, results, skipped)  # the runs 'leaderboard show' and 'compare' read too
    for warning in caught:  # corrupt or foreign records: named, then left out
        warnings.warn(str(warning.message), stacklevel=2)
    if not records:
        raise VPRBenchError(f"{no_runs(cache_dir)} Nothing was written.")
    target = folder / SECTION
    try:
        folder.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{SECTION}-new-", dir=folder))
    except OSError as error:
        raise VPRBenchError(f"Cannot write to {folder} ({error.strerror or error}): choose a folder you can write "
                            "to with --to; nothing was written.") from None
    try:
        with lock(alive(staging), announce=False):  # held while it is written: a staging folder whose lock is free is dead
            staging.mkdir(exist_ok=True)  # another publish may have taken it for dead before this lock was held
            truth = LocalTruth(data_dir, cache_dir)
            write_section(staging, build_board(records, truth, refused), records, cache_dir=cache_dir, data_dir=data_dir, seed=seed)
            with lock(folder / f".{SECTION}.lock", timeout=60, what=f"the leaderboard in {folder}"):
                if newer_in_place(folder, SECTION, read_at):  # swapped in, its site would lack runs stored meanwhile
                    warnings.warn(f"{target} was written meanwhile by a publish that read the results after this one "
                                  "did: its site is kept, not this one's.", stacklevel=2)
                else:
                    swap(staging, target)
                    mark_read_at(folder, SECTION, read_at)
                remove_stale_sections(folder, SECTION, staging)
    except OSError as error:
        full = error.errno in (errno.ENOSPC, errno.EDQUOT)
        raise VPRBenchError(f"Cannot write the leaderboard to {folder} ({error.strerror or error}); "
                            f"the previous {target} is unchanged" + (": free some space, then publish again, or "
                            "publish to a folder on another disk." if full else ".")) from None
    except LockTimeout as error:
        raise VPRBenchError(f"{error} Another 'leaderboard publish' is writing there; try again.") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        alive(staging).unlink(missing_ok=True)
    if (folder / f"{SECTION}.md").is_file():
        warnings.warn(f"{folder / f'{SECTION}.md'} (written by vprbench 0.1) and {target}/index.md are the same page "
                      "for MkDocs: delete the old file.", stacklevel=2)
    return target


# ---------------------------------------------------------------- pages
def write_section(out: Path, board: Board, records: list[dict], *, cache_dir=None, data_dir=None, seed: int = 0) -> None:
    (out / "figures").mkdir()
    (out / "downloads").mkdir()
    from .tracks import TITLES, track_file, track_page

    stats = {key: cell_stats(cell, seed=seed) for key, cell in board.cells.items()}
    full, board = board, board.of_track("single-image")  # every page below but the track pages: single-image only
    for track in [t for t in full.tracks if t != "single-image"]:
        _write(out / track_file(track), track_page(full, track, stats, PAGE_HEAD))
    colours = site_colours(board)
    others = [t for t in full.tracks if t != "single-image"]
    tracks = ["## Other tracks", "", "Re-ranked and sequence runs have tables of their own and never appear above: "
              + (", ".join(f"[{TITLES[t]}]({track_file(t)})" for t in others) if others else "none yet") + ".", ""]
    _write(out / "index.md", overview(out, board, records, stats, cache_dir=cache_dir, seed=seed, colours=colours)
           + "\n" + "\n".join(tracks))
    for column in board.columns:
        _write(out / f"{column.slug}.md", dataset_page(out, board, column, stats, data_dir=data_dir, seed=seed,
                                                       cache_dir=cache_dir, colours=colours))
    _write(out / "reported.md", reported_page())
    _write(out / NAV_FILE, navigation(board, [t for t in full.tracks if t != "single-image"]))
    rows = [summary(cell, stats[key], seed) for key, cell in full.cells.items()]
    to_csv(pd.DataFrame(rows), out / "downloads" / "leaderboard.csv", index=False)
    _write(out / "downloads" / "leaderboard.json", json.dumps(rows, indent=1, sort_keys=True, default=plain))


def site_colours(board: Board) -> dict[str, str]:
    """Every method's colour on every figure of this publish, computed once from all of them."""
    return figures.method_colours([r.name for r in board.rows] + [figures.paper_key(r) for r in figures.RADAR_PAPER_ROWS])


#: the section's navigation, read by the mkdocs-literate-nav plugin (mkdocs.yml: `Results: leaderboard/`)
NAV_FILE = "SUMMARY.md"


def navigation(board: Board, tracks: list[str] = ()) -> str:
    """The overview, every dataset page, the other tracks' pages and the paper's tables, in the site's navigation."""
    from .tracks import TITLES, track_file

    lines = ["* [Overview](index.md)", "* Datasets"]
    lines += [f"    * [{text(c.title)}]({c.slug}.md)" for c in board.columns]
    lines += [f"* [{TITLES[t]} track]({track_file(t)})" for t in tracks]
    return "\n".join([*lines, "* [Reported by the paper](reported.md)", ""])


#: where each page explains the cell rule (below its tables), linked from its top
RULE_HEADING = "How a cell is chosen"
RULE_LINK = "[How a cell is chosen](#how-a-cell-is-chosen)"


def _rule(extra: str = "") -> list[str]:
    return [f"## {RULE_HEADING}", "", extra + CELL_RULE, ""]


def _write(path: Path, text: str) -> None:
    path.write_text(text, encoding="utf-8")


def _from_repository(records) -> str:
    sent = sum(bool(r.get("_contribution")) for r in records)
    return f", {sent} of them contributed to a results repository and re-scored here" if sent else ""


def _regenerate(records) -> str:
    """The command that writes this section again: without --results, the repository's runs would be gone."""
    if any(r.get("_contribution") for r in records):
        return "`vprbench leaderboard publish --to docs/ --results DIR` (DIR: the results repository)"
    return "`vprbench leaderboard publish --to docs/`"


def overview(out: Path, board: Board, records, stats, *, cache_dir=None, seed: int = 0, colours=None) -> str:
    written = datetime.now(timezone.utc).date().isoformat()
    lines = [PAGE_HEAD, "# Leaderboard", "",
             f"Measured by `vprbench evaluate` ({len(records)} stored run(s){_from_repository(records)}; vprbench "
             f"{__version__}; written {written}). Regenerate with {_regenerate(records)}. Each cell is one run: "
             f"{RULE_LINK} (below the tables).", "", marks_note(board)]
    if note := truth_note(board):
        lines += ["", text(note), ""]
    for table in GROUPS:
        lines += [group_table(board, table, link=lambda c: f"{c.slug}.md"), ""]
    lines += ["## Measured against reported", "",
              f"A measured cell reproduces the paper when |measured − reported| ≤ {TOLERANCE_PP:.1f} percentage point, "
              "or ≤ the half-width of its 95 % bootstrap interval when that is wider.", ""]
    found = comparisons(board, seed=seed)
    if found:
        lines += ["| Method | Dataset | Metric | Measured [95 % CI] | Reported | Δ | Tolerance | Reproduced |",
                  "|:--|:--|:--|--:|--:|--:|--:|:--|"]
        for c in found:
            ci = f" [{c['ci'][0]:.1f}, {c['ci'][1]:.1f}]" if c["ci"] else ""
            lines.append(f"| {text(c['row'])} | {text(c['dataset'])} | {c['metric']} | {c['measured']:.1f}{ci} | *{c['reported']:.1f}* "
                         # two decimals: a delta of +1.04 at one read "+1.0 | ±1.0 | no"
                         f"(Table {c['table']}) | {c['delta']:+.2f} | ±{c['tolerance']:.2f} | {'yes' if c['reproduced'] else '**no**'} |")
    else:
        lines.append("No measured cell has a counterpart in the paper yet (the paper reports none of the "
                     "datasets measured here, or none of the methods).")
    lines += ["", "## Figures", ""]
    axes = domain_datasets()
    lines += _figure(lambda p: figures.radar(board, p, colours), out, "radar.svg",
                     "Average R@1 per domain (AnyLoc Fig. 1, right): measured rows solid; the paper's "
                     f"{', '.join(figures.RADAR_PAPER_ROWS)} dashed (reported). Each axis averages the paper's datasets "
                     "of its domain (" + "; ".join(f"{d}: {', '.join(axes[d])}" for d in figures.radar_domains(board, axes))
                     + "); a filled point has all of them, a hollow one only the datasets written beside it.",
                     "Radar chart")
    shown = [cell.record for cell in board.cells.values()]  # not the runs left out (random weights, damaged arrays)
    lines += _figure(lambda p: figures.pca_map(shown, p, cache_dir=cache_dir, seed=seed), out, "pca-gem.png",
                     "Database GeM descriptors of one method on every dataset it was run on, first two principal "
                     "components, coloured by domain (AnyLoc Fig. 1, middle).", "PCA map of GeM descriptors")
    others = other_rows(board)
    lines += ["## Other runs", "", "Runs that are not official runs on a benchmark: rows marked † (weights other than "
              "the authors' release, a vocabulary named as theirs that is not their release, approximate search, a float16 store or a part fitted on the evaluated database: "
              "the mark says which) or the user's own data. Only a row marked for a part fitted on the evaluated "
              "database also fills the tables above, as the paper's own methods do; the others never do.", ""]
    if others:
        lines += ["| Method | Weights | Licence | Dataset | R@1 [95 % CI] | R@5 [95 % CI] | Source | Run |",
                  "|:--|:--|:--|:--|--:|--:|:--|:--|"]
        for row, column, cell in others:
            s = stats[(row, column.key)]
            lines.append(f"| {row_name(row)} | {text(weights_shown(row, cell.record))} | "
                         f"{text(licence_shown(cell.record))} | [{text(column.title)}]({column.slug}.md) | {with_ci(s[1])} | "
                         f"{with_ci(s[5])} | {text(cell.source)} | {code(cell.record.get('run_id'))} |")
    else:
        lines.append("None.")
    lines += ["", *left_out_section(board)]
    lines += ["", "## Datasets", ""]
    lines += [f"- [{text(c.title)}]({c.slug}.md): {text(c.domain or 'no domain')}, {len(board.column_cells(c))} row(s)" for c in board.columns]
    lines += ["", "The paper's reported tables (II–VII), as reported: [reported numbers](reported.md).", "",
              "Downloads: [leaderboard.csv](downloads/leaderboard.csv), [leaderboard.json](downloads/leaderboard.json) "
              f"(one entry per cell: values, intervals, run and provenance; {DOWNLOAD_UNITS}).", "", *_rule()]
    return "\n".join(lines)


def _figure(draw, out: Path, name: str, caption: str, what: str | None = None) -> list[str]:
    try:
        draw(out / "figures" / name)
    except figures.Skipped as why:
        return [f"*{text(what or caption)}: not drawn, {text(why)}.*", ""]
    return [f"![{text(caption)}](figures/{name})", "", f"*{text(caption)}*", ""]


def dataset_page(out: Path, board: Board, column: Column, stats, *, data_dir=None, seed: int = 0, cache_dir=None,
                 colours=None) -> str:
    cells = sorted(board.column_cells(column), key=lambda c: -(c.recall(1) or -1))
    first = cells[0].record
    counts, gt, protocol = first["counts"], first.get("ground_truth", {}), first.get("protocol", {})
    if column.kind == "benchmark":  # what vprbench ships for the column's protocol hash, not what a record says of it
        protocol = benchmark_protocols(column.dataset).get(column.protocol_hash) or protocol
        gt = protocol.get("ground_truth") or gt
    positives = np.asarray((first.get("per_query") or {}).get("positives") or
                           (cells[0].arrays["positives"] if cells[0].arrays is not None else []))
    if len(positives):  # counted from the run's arrays (sha256-checked), as the positives per query beside them
        counts = {**counts, "queries_without_positives": int(np.sum(positives == 0)),
                  "positive_pairs": int(np.sum(positives))}
    colours = colours if colours is not None else site_colours(board)
    lines = [page_head(column.title), f"# {text(column.title)}", "", f"Each cell is one run: {RULE_LINK} (below the tables).", "",
             marks_note(board, column), *([text(note), ""] if (note := truth_note(board.of_column(column))) else []),
             f"Domain: {text(column.domain or '–')}. Kind: {'benchmark' if column.kind == 'benchmark' else 'own data (not a benchmark)'}.", "",
             "## Data and ground truth", "",
             "| Database | Queries | Queries without positives | Positive pairs | Positives per query (min / median / max) | Ground truth | Protocol | Dataset fingerprint |",
             "|--:|--:|--:|--:|:--|:--|:--|:--|",
             f"| {counts['database']} | {counts['queries']} | {counts.get('queries_without_positives', '–')} | "
             f"{counts.get('positive_pairs', '–')} | "
             + (f"{positives.min()} / {np.median(positives):g} / {positives.max()}" if len(positives) else "–")
             + f" | {text(gt.get('unit', '–'))}, radius {text(quantity(gt.get('radius'), gt.get('radius_unit')))} | "
             f"{code(protocol.get('id', '–'))} ({code(protocol.get('hash', '–'))}) | {code(column.fingerprint)} |", "",
             f"Protocol {code(protocol.get('id', '–'))}: {text(protocol.get('description') or 'no description')}"
             + (f" (source: {text(protocol['source'])})" if protocol.get("source") else "") + ".", "",
             "Queries without positives count as failures.", "",
             "## Results", "",
             f"Seeded 95 % bootstrap intervals ({RESAMPLES:,} resamples, seed {seed}), resampling "
             f"{_units(cells)}.", "",
             "| Method | Weights | Licence | R@1 [95 % CI] | R@5 [95 % CI] | R@10 | R@20 | AUC-PR | R@100%P | Dim | Bytes "
             "| Images/s |", "|:--|:--|:--|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    plugins = [plugins_shown(cell.record) for cell in cells]
    shown = any(p != "–" for p in plugins)  # no column when every run is vprbench's own: it would be all dashes
    runs = ["| Method | Source | Contributor | Run | Created | Hardware | vprbench | Commit | Descriptors computed | "
            f"{'Plugins | ' * shown}Older runs of the row | Images/s measured by |",
            f"|:--|:--|:--|:--|:--|:--|:--|:--|--:|{':--|' * shown}--:|:--|"]
    for cell, plugin in zip(cells, plugins):
        s, r = stats[(cell.row, column.key)], cell.record
        lines.append(f"| {row_cells(cell.row, cell)} | "
                     f"{with_ci(s[1])} | {with_ci(s[5])} | {fmt(cell.recall(10))} | {fmt(cell.recall(20))} | "
                     f"{number(r.get('auc_pr'), 3)} | {percent(r.get('recall_at_100_precision'))} | {text(r.get('descriptor_dim') or '–')} | "
                     f"{descriptor_bytes(r) or '–'} | "
                     f"{number(cell.images_per_second, 1)} |")
        versions, computed = r.get("versions") or {}, r.get("descriptors_computed") or {}
        sent = (r.get("_contribution") or {}).get("contributor") or "this machine"
        runs.append(f"| {text(cell.row.name)} | {text(cell.source)} | {text(sent)} | {code(r.get('run_id'))} | {text(r.get('created', '–'))} | "
                    f"{text(hardware_of(r))} | {text(versions.get('vprbench', '–'))} | "
                    f"{_commit(versions.get('git'))} | {sum(computed.values()) if computed else '–'} | {f'{plugin} | ' * shown}{cell.passed_over} | "
                    + (f"{code(cell.timed.get('run_id'))} on {text(cell.hardware)} |" if cell.timed else "no run computed its descriptors |"))
    lines += ["", RESULTS_LEGEND, "", "The runs in the cells above:", "", *runs, "", *_paired(cells, seed), "## Figures", ""]
    slug = column.slug
    lines += _figure(lambda p: figures.recall_curves(cells, p, colours), out, f"{slug}-recall.svg", "Recall@K per run")
    lines += _figure(lambda p: figures.pr_curves(cells, p, colours), out, f"{slug}-pr.svg",
                     "Precision-recall of the top-1 matches ranked by similarity (VPR-Bench)")
    machines = "; ".join(sorted({c.hardware for c in cells if c.images_per_second})) or "none, no run measured its speed"
    lines += _figure(lambda p: figures.efficiency(cells, p, colours), out, f"{slug}-efficiency.svg",  # the runs' machines
                     f"Efficiency: R@1 against descriptor bytes and images described per second (machine: {machines})")
    lines += ["### Retrieval mosaics", "", f"Seeded queries (seed {seed}) and their top matches: green frame = positive, red = not.", ""]
    for cell, file in zip(cells[:MOSAIC_ROWS], _file_names([c.row.name for c in cells[:MOSAIC_ROWS]])):
        top = min(5, cell.arrays["database_indices"].shape[1]) if cell.arrays is not None else 5  # it kept its top K
        draw = functools.partial(figures.mosaic, cell, data_dir=data_dir, seed=seed, top=top, cache_dir=cache_dir)
        lines += _figure(draw, out, f"{slug}-mosaic-{file}.png",
                         f"{cell.row.name}: queries and their top {top}", f"Mosaic of {cell.row.name}")
    download = [record_download(c) for c in cells]
    _write(out / "downloads" / f"{slug}.json", json.dumps(download, sort_keys=True, default=plain))  # compact: per-query arrays
    to_csv(pd.DataFrame([summary(c, stats[(c.row, column.key)], seed) for c in cells]), out / "downloads" / f"{slug}.csv",
           index=False)
    lines += ["## Downloads", "", f"[{slug}.csv](downloads/{slug}.csv) (one row per cell), "
              f"[{slug}.json](downloads/{slug}.json) (the cells' full records, per-query predictions included; "
              f"{DOWNLOAD_UNITS}).", "",
              *_rule()]
    return "\n".join(lines)


def _file_names(names: list[str]) -> list[str]:
    """Each name as a file name (paths.safe_name); names that would share one ('a/b' and 'a:b',
    'Hog' and 'hog' on a case-blind disk, a long name's first 80 characters) get a hash of the name
    each, so no row's figure overwrites another's."""
    import hashlib

    safe = [safe_name(name, 80) for name in names]
    seen = Counter(s.lower() for s in safe)
    return [s if seen[s.lower()] == 1 else f"{safe_name(name, 60)}-{hashlib.sha256(name.encode()).hexdigest()[:8]}"
            for s, name in zip(safe, names)]


def _units(cells: list[Cell]) -> str:
    """Which queries the column's intervals draw together, and by what rule (evaluation/blocks.py)."""
    each = [for_record(c.record, c.arrays) for c in cells]
    found, lengths = each[0], sorted({f.block_length for f in each if f.scheme == "blocks"})
    # a sequence run's blocks cover its window: a column of several windows names each length
    said = found.text() if len(lengths) < 2 else \
        f"blocks of {', '.join(map(str, lengths))} consecutive queries (per run, by its sequence window)"
    return f"{text(said)}: {text(RULE[found.scheme])}" + \
        (f" (n = {found.queries}, r = {found.radius:g})" if found.scheme == "blocks" else "")


def _paired(cells: list[Cell], seed: int) -> list[str]:
    """Paired tests between neighbours in the ranking whose R@1 intervals overlap."""
    lines = []
    for a, b in zip(cells, cells[1:]):
        if a.row.key == b.row.key:  # one method's two rows (e.g. before and after a mark): never tested against itself
            continue
        if a.arrays is None or b.arrays is None or len(a.arrays["first_positive_rank"]) != len(b.arrays["first_positive_rank"]):
            continue
        ci_a, ci_b = cell_stats(a, ks=(1,), seed=seed)[1]["ci"], cell_stats(b, ks=(1,), seed=seed)[1]["ci"]
        if not overlaps(ci_a, ci_b):
            continue
        t = paired_test(successes(a.arrays["first_positive_rank"], 1), successes(b.arrays["first_positive_rank"], 1),
                        shared_resampling(a, b), seed=seed)
        mcnemar = "–" if t["identical"] else f"{t['p_mcnemar']:.3g}"  # no query to test on
        lines.append(f"| {text(a.row.name)} − {text(b.row.name)} | {t['difference']:+.1f} [{t['ci'][0]:+.1f}, {t['ci'][1]:+.1f}] | "
                     f"{format_test(t)} | {t['only_a']} / {t['only_b']} | {mcnemar} |")
    if not lines:
        return []
    return ["### Paired tests where R@1 intervals overlap", "",
            "Over the same queries: paired-bootstrap difference of R@1 (percentage points; the same units drawn "
            "for both) and McNemar's exact test on the queries only one of the two gets right (which takes the "
            "queries as independent).", "",
            "| Pair | Δ R@1 [95 % CI] | p (bootstrap) | only first / only second | p (McNemar) |", "|:--|--:|--:|--:|--:|",
            *lines, ""]


def _commit(value) -> str:
    """A record's git commit as a code span when it is one (hex), else '–': a record can say anything."""
    found = str(value or "")
    return f"`{found[:10]}`" if re.fullmatch(r"[0-9a-f]{7,40}", found) else "–"
