"""vprbench reproduce PAPER --table N [--dry-run] [--publish DIR]."""
from __future__ import annotations


from .console import console as make_console
from ..errors import DESCRIBED
from .options import (add_location_options, add_method_flags, add_run_options, add_spec_options, add_sweep_options,
                      check_new_folder, method_options, path_argument, progress, resolve_locations, run_settings,
                      spec_overrides)


def add_parsers(commands) -> None:
    p = commands.add_parser("reproduce", help="run a paper's table as a plan and print it with measured values")
    p.add_argument("paper", help="the paper (anyloc)")
    p.add_argument("--table", required=True, help="2, 3, 4, 5, 6, 7, layer, facet or backbones")
    p.add_argument("--dry-run", action="store_true", help="list the cells and what each needs; run nothing")
    p.add_argument("--publish", type=path_argument, metavar="DIR", help="also write the table (Markdown) and the leaderboard into DIR")
    add_method_flags(p, shown=False)  # refused by name (refuse_changes): the paper's settings are fixed
    add_spec_options(p, shown=False)
    add_run_options(p)
    add_sweep_options(p)
    add_location_options(p)
    p.set_defaults(run=run_reproduce, kept=DESCRIBED)


def refuse_changes(args) -> None:
    """Options that change what is computed would make the table another one: named, refused."""
    from ..errors import VPRBenchError
    from ..spec import split_run_settings

    given = [f"{k}={v}" for k, v in split_run_settings(method_options(args))[0].items()]
    given += [f"{k}={v}" for k, v in spec_overrides(args).items() if v is not None]
    if given:
        raise VPRBenchError(f"reproduce evaluates the paper's settings; {', '.join(given)} would change what is "
                            "computed, so the table would not be the paper's. Run those settings as a plan "
                            "('vprbench run PLAN.toml', docs/sweeps.md) or with 'vprbench evaluate'.")


def _row_weights(spec: dict) -> dict:
    return {row["row"]: row.get("weights") for row in spec.get("rows", [])}


def run_reproduce(args) -> int:
    from ..distributed import refuse_torchrun
    from ..errors import VPRBenchError
    from ..methods.registry import checked_run_options
    from ..sweep import run_cells, summary_table
    from ..sweep.needs import missing_for, needs_text, once_each
    from ..sweep.reproduce import table_cells
    from ..sweep.runner import FAILED
    from .evaluate import explicit_run_options

    # the locations given on the command line (an environment's reach the fit command too): named in
    # a vocabulary fit command, which would otherwise fit from and into the default ones
    given = {"data-dir": args.data_dir, "cache-dir": args.cache_dir}
    refuse_torchrun("reproduce")
    resolve_locations(args)
    refuse_changes(args)
    # checked once here: inside each cell's plan a bad --batch-size reads as that method's problem
    checked_run_options("reproduce", explicit_run_options(args))
    if args.publish and args.dry_run:
        raise VPRBenchError("--publish writes the table and the leaderboard after the cells run; --dry-run runs "
                            "nothing and publishes nothing: drop one of them (cells already measured are read, "
                            "not run again).")
    if args.publish:  # a folder that cannot be made is said before the cells run, not after
        check_new_folder(args.publish, "--publish")
        args.publish.mkdir(exist_ok=True)
    settings = run_settings(args)
    spec, table_cells_ = table_cells(args.paper, args.table, settings=explicit_run_options(args),
                                     data_dir=settings.data_dir, cache_dir=settings.cache_dir)
    weights = _row_weights(spec)
    cells = {c.key: (c, tc) for tc in table_cells_ for c in tc.cells}
    console = make_console()
    missing = once_each({key: missing_for(c, weights.get(tc.row), settings.data_dir, settings.cache_dir, given,
                                          settings.memory_budget) for key, (c, tc) in cells.items()},
                        {key: tc.row for key, (_, tc) in cells.items()})
    unrunnable = [tc for tc in table_cells_ if not tc.cells]
    no_method = f"{len(unrunnable)} not runnable as the paper ran them ({', '.join(sorted({tc.row for tc in unrunnable}))})"
    if args.dry_run:
        counted = f"{len(cells)} cells to evaluate{f', {no_method}' if unrunnable else ''}"
        if spec.get("dry_run") == "by-row":
            from ..sweep.reproduce import PaperRecords

            stored = PaperRecords(settings)  # computed on the data at hand, as run_cells judges it
            records = {key: stored.record(c.spec, c.settings) for key, (c, _) in cells.items()}
            status = {key: "complete" if records[key] else "missing" if missing[key] else "would run" for key in cells}
            console.print(by_row(table_cells_, status, missing, f"{spec['title']}: {counted} (dry run, nothing runs)"))
        else:
            console.print(dry_run_listing(spec, table_cells_, missing, settings, counted))
        return 0
    from ..sweep.reproduce import PaperRecords

    stored = PaperRecords(settings)  # one lookup for the run and the table after it: each copy fingerprinted once
    outcomes = run_cells([c for c, _ in cells.values()], settings, lease_s=args.lease, stored=stored,
                         plan=f"{args.paper} table {args.table}", runnable=lambda c: needs_text(missing[c.key]),
                         progress=progress(args))
    console.print(summary_table(outcomes, f"{args.paper} table {args.table}"))
    if unrunnable:
        console.print(f"Not evaluated: {no_method}; the paper's values stand alone there.", markup=False)
    rendered = paper_table(spec, table_cells_, settings, stored)
    console.print(rendered)
    if args.publish:
        publish(args, spec, rendered, settings)
    return 1 if any(o.status == FAILED for o in outcomes) else 0


def by_row(table_cells_, status, missing, title):
    """One line per row (a wide table): how many cells are complete or would run, and what the
    others lack, each need once (domain vocabularies in one command); each need's instructions
    once below the table."""
    from rich.table import Table

    from ..notes import Notes

    notes = Notes()
    listing = Table(title=title)
    for column in ("row", "complete", "would run", "missing", "needs"):
        listing.add_column(column, overflow="fold")
    rows: dict[str, list] = {}
    for tc in table_cells_:
        rows.setdefault(tc.row, []).extend(tc.cells)
    for row, cells in rows.items():
        kinds = [status[c.key] for c in cells]
        needs = dict.fromkeys(need for c in cells for need in missing[c.key])
        shown, vocabularies, fit, datasets = [], [], "", 0
        for thing, how in needs:
            if thing.startswith("dataset "):
                datasets += 1
                notes.refer(f"{thing}: {how}")
            elif thing.startswith("vocabulary '"):
                name = thing.split("'")[1]
                vocabularies.append(name)
                fit = how.replace(f"--domain {name} ", "--domain D ")
            else:
                shown.append(notes.short(f"{thing}: {how}"))
        if vocabularies:
            shown.append(notes.short(f"vocabularies D = {', '.join(vocabularies)}: {fit}"))
        if datasets:
            shown.append(f"{datasets} datasets (notes below)")
        listing.add_row(row, str(kinds.count("complete")), str(kinds.count("would run")), str(kinds.count("missing")),
                        "; ".join(shown))
    return notes.below(listing)


def dry_run_listing(spec: dict, table_cells_, missing: dict, settings, counted: str):
    """One line per cell (at 80 columns too): each need's instructions once, below the table, the
    cells referring to them by number."""
    from rich.table import Table
    from rich.text import Text

    from ..notes import Notes
    from ..sweep.reproduce import PaperRecords
    from ..sweep.runner import _minute

    notes, stored = Notes(), PaperRecords(settings)
    listing = Table(title=f"{spec['title']}: {counted} (dry run, nothing runs)")
    listing.add_column("row", overflow="fold")
    listing.add_column("column: dataset:protocol", overflow="fold")
    listing.add_column("status", no_wrap=True)  # short: the long part is a note
    for tc in table_cells_:
        if not tc.cells:
            listing.add_row(tc.row, tc.column, Text.assemble(("not runnable", "yellow"), f" {notes.refer(tc.reason)}"))
        for c in tc.cells:
            record = stored.record(c.spec, c.settings)
            needs = " ".join(notes.refer(f"{thing}: {how}") for thing, how in missing[c.key])
            status = (Text.assemble(("complete", "cyan"), f" ({_minute(record.get('created'))})") if record else
                      Text.assemble(("missing", "yellow"), f" {needs}") if needs else Text("would run", style="green"))
            where = c.spec.dataset.protocol_id
            listing.add_row(tc.row, where if where.startswith(f"{tc.column}:") else f"{tc.column}: {where}", status)
    return notes.below(listing)


def decimals(value: float) -> int:
    """The decimals a reported value was published with (the CSV holds at most two)."""
    return len(f"{value:.2f}".rstrip("0").partition(".")[2])


def as_published(value: float) -> str:
    """A reported value as published, at least one decimal: the authors' ablation runs give two
    (80.62 key and 80.56 query read 80.6 and 80.6 at one)."""
    return f"{value:.{max(1, decimals(value))}f}"


#: a plan's reported_columns -> the record field measured for it
RECORD_FIELD = {"dim": "descriptor_dim"}


def paper_table(spec: dict, table_cells_, settings, stored=None):
    """The paper's values beside the records the run judged complete (`stored`, a StoredRecords:
    computed on the data at hand, not on another copy's)."""
    from rich.table import Table

    from ..sweep.reproduce import PaperRecords, measured, reported_value

    stored, found_for = stored or PaperRecords(settings), {}

    def record_of(cell):  # each cell's record looked up (and proven) once, with its own run settings
        if cell.spec.key not in found_for:
            found_for[cell.spec.key] = stored.record(cell.spec, cell.settings)
        return found_for[cell.spec.key]

    table = Table(title=f"{spec['title']} — reported (paper) / measured here (delta) [95% bootstrap CI]")
    table.add_column("row")
    columns = list(dict.fromkeys(tc.column for tc in table_cells_))
    for column in columns:
        for metric in spec["metrics"]:
            table.add_column(f"{column} {metric.upper()}", overflow="fold")
    extras = spec.get("reported_columns", [])  # e.g. Table VI's descriptor dimension
    for extra in extras:
        table.add_column(extra, overflow="fold")
    by_row: dict[str, dict] = {}
    for tc in table_cells_:
        by_row.setdefault(tc.row, {})[tc.column] = tc
    for row, cells in by_row.items():
        values = []
        for column in columns:
            tc = cells.get(column)
            records = [record_of(c) for c in tc.cells] if tc else []
            for metric in spec["metrics"]:
                reported = reported_value(spec, row, column, metric)
                shown = "-" if reported is None else as_published(reported)
                found = measured(records, metric)
                if found:
                    value, low, high = found
                    delta = f" ({value - reported:+.{max(1, decimals(reported))}f})" if reported is not None else ""
                    shown += f" / {value:.1f}{delta} [{low:.1f}, {high:.1f}]"
                else:
                    shown += " / not measured"
                values.append(shown)
        found = [r for tc in cells.values() for c in tc.cells if (r := record_of(c))]
        for extra in extras:
            reported = reported_value(spec, row, extra, extra)
            got = sorted({str(r[RECORD_FIELD[extra]]) for r in found if r.get(RECORD_FIELD[extra])})
            values.append(f"{'-' if reported is None else f'{reported:.0f}'} / {', '.join(got) or 'not measured'}")
        table.add_row(row, *values)
    return table


def publish(args, spec: dict, rendered, settings) -> None:
    """The table as Markdown beside the leaderboard page (through the leaderboard's publish)."""
    from rich.console import Console as RichConsole

    from .. import leaderboard
    from ..errors import VPRBenchError
    from ..fsutil import atomic_write

    capture = RichConsole(record=True, width=200, markup=False)
    capture.print(rendered)
    page = args.publish / f"{args.paper}-table-{args.table}.md"
    # whole or not at all: a full disk (or a second reproduce writing the page) never leaves half a page
    atomic_write(page, f"# {spec['title']}\n\nReported by the paper / measured by vprbench here.\n\n```\n"
                       f"{capture.export_text()}```\n")
    try:
        leaderboard.publish(args.publish, settings.cache_dir)
    except VPRBenchError:
        pass  # no results yet: the table page alone
    make_console(stderr=True).print(f"wrote {page}")
