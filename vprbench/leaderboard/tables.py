"""Boards -> tables: the terminal/CSV grid, the paper-style group tables, measured vs reported."""
from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass

import pandas as pd

from ..errors import VPRBenchError
from ..reference import paper_results
from ..text import CONTROL, literal, recall_text
from .cells import AGREES, CELL_KS, CONTRIBUTED, IMPORTED, STRUCTURED, UNSTRUCTURED, Board, Cell, Column, Row
from .escape import code, public_data, text, to_csv
from .shown import left_out, licence_shown, weights_shown
from ..evaluation.blocks import for_record
from ..evaluation.metrics import successes
from .stats import bootstrap_ci

#: a measured cell reproduces the paper when |measured - reported| is within this many
#: percentage points, or within its own 95 % interval's half-width when that is wider
TOLERANCE_PP = 1.0
GROUPS = {"II": ("Structured environments", STRUCTURED), "III": ("Unstructured environments", UNSTRUCTURED)}


fmt = recall_text  # a recall as every surface shows it (text.recall_text)


def with_ci(entry) -> str:
    """A recall (cell_stats' entry) with its 95 % interval when it has one: '71.2 [65.0, 77.1]'."""
    return f"{fmt(entry['value'])} [{entry['ci'][0]:.1f}, {entry['ci'][1]:.1f}]" if entry["ci"] else fmt(entry["value"])


@dataclass(frozen=True)
class Shown:
    """One cell as every format shows it (CLI table, Markdown, CSV, JSON, the site's tables)."""
    row: str       # the row's name: its label, and after † what sets it apart
    label: str
    weights: str
    licence: str   # the weights' licence (licence_shown)
    column: str    # the column's title, e.g. "my-traverse (own, ±1 frame)"
    r1: float | None
    r5: float | None
    source: str    # where the cell's number comes from (Cell.source)
    run_id: str
    #: the run's protocol id and track, as the site's downloads give them: a JSON entry read alone names its run
    protocol: str | None
    track: str


#: the mark after a cell's numbers in the site's tables, by where they come from (measured here: none;
#: reported by a paper: italics), first match of the source's beginning
SOURCE_MARKS = ((AGREES, "c✓", "contributed, and re-run here agreeing within the contributed run's 95 % interval"),
                ("contributed, re-run here and disagreeing", "c≠",
                 "contributed, and re-run here outside its interval (the dataset page gives both numbers)"),
                ("contributed", "c", "contributed to the results repository, re-scored here from its per-query arrays"),
                (IMPORTED, "v", "VPR-Bench's matches, imported and re-scored here"))


#: a grid cell's plain mark (grid), set as the site sets it in Markdown
MARKED = re.compile(f" ({'|'.join(re.escape(mark) for _, mark, _ in SOURCE_MARKS)})$")


def plain_mark(source: str) -> str:
    """The mark of a cell's source (Cell.source) as plain text ('c', 'c✓', 'c≠', 'v'), "" when measured here."""
    return next((mark for start, mark, _ in SOURCE_MARKS if source.startswith(start)), "")


def source_mark(source: str) -> str:
    """`<sup>mark</sup>` for a cell's source (Cell.source), or "" when it was measured here."""
    return f"<sup>{mark}</sup>" if (mark := plain_mark(source)) else ""


def row_cells(row: Row, cell: Cell) -> str:
    """A row's first three cells on every page: its name (escaped) with the mark of where its number comes
    from, its weights and their licence."""
    from .shown import row_name

    return (f"{row_name(row)}{source_mark(cell.source)} | {text(weights_shown(row, cell.record))} | "
            f"{text(licence_shown(cell.record))}")


def number(value, digits: int) -> str:
    """A metric other than a recall (AUC-PR, max F1, images/s) to `digits` decimals, '–' without one."""
    return "–" if value is None else f"{value:.{digits}f}"


def marks_legend(sources, form: str = "site") -> str:
    """What each source mark among `sources` means, for a table's legend ("" when none is there). Forms:
    "site", "markdown" (`leaderboard show`'s: no page of the site to point to), "terminal" (plain marks too)."""
    def said(mark: str, meaning: str) -> str:
        meaning = meaning if form == "site" else meaning.split(" (")[0]  # '(the dataset page gives ...)'
        return f"{mark}: {meaning}" if form == "terminal" else f"<sup>{mark}</sup> {meaning}"

    shown = [said(mark, meaning) for _, mark, meaning in SOURCE_MARKS if any(plain_mark(s) == mark for s in sources)]
    return (" " + "; ".join(shown) + ".") if shown else ""


def left_out_section(board: Board) -> list[str]:
    """"## Runs left out": every run of `board` that fills no cell, with why; one renderer for the
    overview and the track pages. A contributed or imported run carries its cells' source mark."""
    lines = ["## Runs left out", ""]
    if not board.excluded:
        return lines + ["None."]
    sources = [IMPORTED if r.get("imported") else CONTRIBUTED if r.get("_contribution") else "" for r, _ in board.excluded]
    # its mark as on a cell, without the cell's meaning ("re-scored here"): a run left out may not re-score
    legend = [f"{source_mark(s)} {meaning}" for s, meaning in ((CONTRIBUTED, "contributed to a results repository"),
              (IMPORTED, "imported from VPR-Bench")) if s in sources]
    lines += [f"Marks: {'; '.join(legend)}.", ""] if legend else []
    lines += ["| Run | Method | Dataset | Why |", "|:--|:--|:--|:--|"]
    for (record, why), source in zip(board.excluded, sources):
        run, label, dataset = left_out(record)
        lines.append(f"| {code(run)} | {text(label)}{source_mark(source)} | {text(dataset)} | {text(why)} |")
    return lines


def computed(board: Board) -> list[Shown]:
    """The board's cells, row by row in the board's order: what every format renders."""
    return [Shown(row.name, row.label, weights_shown(row, cell.record), licence_shown(cell.record), column.title,
                  cell.recall(1), cell.recall(5), cell.source, str(cell.record.get("run_id")),
                  public_data((cell.record.get("protocol") or {}).get("id")), row.track)
            for row in board.rows for column in board.columns if (cell := board.cell(row, column))]


def grid(board: Board) -> pd.DataFrame:
    """Rows x dataset columns of 'R@1 / R@5', with each row's weights and licence: the terminal, Markdown
    and CSV view. A cell not measured here ends with the site's mark of its source ('48.6 / 75.7 c')."""
    data: dict[str, dict] = {}
    for shown in computed(board):
        entry = data.setdefault(shown.row, {"method": shown.row, "weights": shown.weights, "licence": shown.licence})
        entry[shown.column] = f"{fmt(shown.r1)} / {fmt(shown.r5)}" + (f" {mark}" if (mark := plain_mark(shown.source)) else "")
    columns = [c.title for c in board.columns]
    frame = pd.DataFrame(list(data.values()), columns=["method", "weights", "licence", *columns]).set_index("method")
    return frame.fillna("-")


def render(table: pd.DataFrame, fmt_name: str, board: Board | None = None) -> str:
    """The grid as Markdown or CSV, or the cells as JSON; control characters of names from records
    written out (text.literal; JSON escapes them its way), so none breaks a row or reaches a terminal."""
    if fmt_name == "json" and board is not None:
        out = json.dumps([asdict(s) for s in computed(board)], indent=1, ensure_ascii=False)
        return CONTROL.sub(lambda found: f"\\u{ord(found.group()):04x}", out)  # C1 controls, which json keeps
    if fmt_name not in ("markdown", "csv"):
        raise VPRBenchError(f"Unknown leaderboard format {fmt_name!r}; use markdown, csv or json")
    table = table.rename(index=literal, columns=literal).map(literal)
    if fmt_name == "csv":
        return to_csv(table, lineterminator="\n")  # printed as lines; literal() wrote out every carriage return
    table = table.rename(index=text, columns=text).map(text)  # Markdown from records: escaped as on the site
    table.iloc[:, 2:] = table.iloc[:, 2:].map(lambda v: MARKED.sub(r"<sup>\1</sup>", v))  # the dataset columns
    return table.to_markdown()


def cell_stats(cell: Cell, ks=CELL_KS, seed: int = 0) -> dict[int, dict]:
    """{k: {"value", "ci"}} for a cell: the recall and its bootstrap interval (None without per-query data),
    drawn by the units of its dataset (blocks, places or queries: evaluation/blocks.py)."""
    found = {}
    for k in ks:
        value = cell.recall(k)
        ci = None
        if cell.arrays is not None and (cell.record.get("per_query") or {}).get("k", 0) >= k:
            ci = bootstrap_ci(successes(cell.arrays["first_positive_rank"], k), for_record(cell.record, cell.arrays),
                              seed=seed)
        found[k] = {"value": value, "ci": ci}
    return found


def paper_rows(table: str) -> pd.DataFrame:
    """The paper's table, each row's `method` the label of the run that reproduces it: the reproduction
    plan's method with the options it sets on top of the preset (Table II's AnyLoc-VLAD-DINO: the domain
    vocabularies, where the preset fits the map's), so no other setting of a method is set against it."""
    from ..spec import RunSpec
    from ..spec_options import given_options
    from ..sweep.reproduce import reproduce_tables

    frame = paper_results(table=table).copy()
    plan = next((t for t in reproduce_tables("anyloc").values() if t.get("paper") == table), {})
    labels = {row["row"]: RunSpec.model_construct(method=row["method"], stages=[],
                                                  given=given_options(row.get("options", {}), row["method"])).label()
              for row in plan.get("rows", []) if row.get("method")}
    frame["method"] = [labels.get(row, "") for row in frame["row"]]
    return frame


def reported(method: str | None = None) -> pd.DataFrame:
    """The paper's Table II and III values, one row per (row, dataset, metric); `method` as paper_rows."""
    frame = pd.concat([paper_rows("II"), paper_rows("III")], ignore_index=True)
    return frame if method is None else frame[frame["method"] == method]


def _value(frame: pd.DataFrame, dataset: str, metric: str) -> float | None:
    hit = frame[(frame["column"] == dataset) & (frame["metric"] == metric)]
    return float(hit["value"].iloc[0]) if len(hit) else None


def _reported_value(frame: pd.DataFrame, method: str, dataset: str, metric: str) -> float | None:
    return _value(frame[frame["method"] == method], dataset, metric) if method else None


def fell_back(record: dict, dataset: str) -> bool:
    """A run asked for the paper's domain vocabulary that fitted another (the map's: none of the domain's
    fitted these features): not the setting the paper's number was measured with."""
    from ..methods.anyloc_vocabulary import paper_vocabulary

    vocabulary = (record.get("provenance") or {}).get("vocabulary") or {}
    return vocabulary.get("option") == "domain" and vocabulary.get("name") != paper_vocabulary(dataset)


def comparisons(board: Board, seed: int = 0) -> list[dict]:
    """Every measured cell of a row like the paper's (Row.like_the_paper) the paper also reports: both
    values, the delta, reproduced or not."""
    frame = reported()
    found = []
    for row in board.rows:
        if not row.like_the_paper:
            continue
        for column in board.columns:
            cell = board.cell(row, column)
            if cell is None or column.kind != "benchmark" or not column.default:  # the paper's protocols
                continue
            if fell_back(cell.record, column.dataset):
                continue
            stats = cell_stats(cell, seed=seed)
            for k in CELL_KS:
                paper = _reported_value(frame, row.label, column.dataset, f"r{k}")
                measured = stats[k]["value"]
                if paper is None or measured is None:
                    continue
                ci = stats[k]["ci"]
                tolerance = max(TOLERANCE_PP, (ci[1] - ci[0]) / 2) if ci else TOLERANCE_PP
                table = frame[(frame["method"] == row.label) & (frame["column"] == column.dataset)]["table"].iloc[0]
                found.append({"method": row.label, "row": row.name, "dataset": column.dataset, "metric": f"R@{k}", "measured": measured,
                              "ci": ci, "reported": paper, "delta": measured - paper, "tolerance": tolerance,
                              "reproduced": abs(measured - paper) <= tolerance, "table": table,
                              "run_id": cell.record.get("run_id")})
    return found


def group_table(board: Board, table: str, link=lambda column: column.dataset) -> str:
    """A paper-style table (II structured, III unstructured) in Markdown: our measured rows like the paper's
    and the paper's rows; R@1 / R@5 per dataset; best in bold. The Average is over the paper's
    datasets of the table, for rows that have them all; a measured row with fewer has its mean in a
    column of its own, "Measured so far". Reported values are in italics, never presented as measured."""
    title, domains = GROUPS[table]
    paper = paper_rows(table)
    datasets = list(dict.fromkeys(paper["column"]))
    averaged = list(datasets)  # what the paper's averages are over
    ours = [c for c in board.columns if c.kind == "benchmark" and c.default and c.domain in domains]
    datasets += [c.dataset for c in ours if c.dataset not in datasets]
    by_name = {c.dataset: c for c in ours}

    lines: list[tuple[str, str, dict]] = []  # (name, source, {(dataset, k): (value, is_reported)})
    marks: dict[tuple[str, str], str] = {}  # (row name, dataset): where a measured cell's number comes from
    for row in [r for r in board.rows if r.like_the_paper]:  # a † row shows its mark
        values = {}
        for name in datasets:
            cell = board.cell(row, by_name[name]) if name in by_name else None
            if cell is not None and cell.recall(1) is not None:
                marks[(text(row.name), name)] = cell.source
            for k in CELL_KS:
                measured = cell.recall(k) if cell else None
                paper_value = _reported_value(paper, row.label, name, f"r{k}")
                values[(name, k)] = (measured, False) if measured is not None else (paper_value, paper_value is not None)
        if any(v is not None and not rep for v, rep in values.values()):
            lines.append((text(row.name), "measured", values))
    for label, part in paper.groupby("row", sort=False):
        values = {(name, k): (_value(part, name, f"r{k}"), True)
                  for name in datasets for k in CELL_KS}
        lines.append((f"*{label}* (paper)", "reported", values))
    measured_any = any(source == "measured" for _, source, _ in lines)

    best = {}
    for name in datasets:
        for k in CELL_KS:
            shown = [v[(name, k)][0] for n, source, v in lines
                     if v[(name, k)][0] is not None and (source != "measured" or not v[(name, k)][1])]
            best[(name, k)] = max(shown) if shown else None

    def show(value, is_reported, name, k):
        if value is None:
            return "–"
        text = f"{value:.1f}"
        text = f"*{text}*" if is_reported else text
        # best as shown: two values that read alike (91.46 and the paper's 91.5) are both bold, or neither
        return f"**{text}**" if best.get((name, k)) is not None and f"{value:.1f}" == f"{best[(name, k)]:.1f}" else text

    averages = {name: _average(values, averaged, source) for name, source, values in lines}
    partial = {name: _average(values, datasets, source, partial=True) for name, source, values in lines
               if averages[name] is None and source == "measured"}
    header = ["Method", *[f"[{text(n)}]({link(by_name[n])})" if n in by_name else n for n in datasets],
              f"Average ({len(averaged)})", *(["Measured so far"] if partial else [])]
    note = "" if measured_any else " No official run measured in this group yet: every value below is reported."
    legend = LEGEND.format(n=len(averaged)) + marks_legend(marks.values()) + (PARTIAL_LEGEND if partial else "")
    out = [f"### Table {table}: {title}", "", "R@1 / R@5 (%) per dataset. " + legend + note, "",
           "| " + " | ".join(header) + " |", "|" + "|".join([":--"] + ["--:"] * (len(header) - 1)) + "|"]
    for name, source, values in lines:
        cells = [f"{show(*values[(n, 1)], n, 1)} / {show(*values[(n, 5)], n, 5)}{source_mark(marks.get((name, n), ''))}"
                 for n in datasets]
        out.append("| " + " | ".join([name, *cells, averages[name] or "–", *([partial.get(name) or ""] if partial else [])])
                   + " |")
    return "\n".join(out) + "\n"


def _average(values: dict, datasets: list[str], source: str, partial: bool = False) -> str | None:
    """The R@1 / R@5 means over `datasets`, of values of the row's own kind (a measured row's never
    mix in reported numbers): None unless the row has every one of them. With `partial`, the means
    over those it has, with how many ('(n of m)'); None when it has none."""
    parts, have = [], 0
    for k in CELL_KS:
        own = [values[(n, k)][0] for n in datasets
               if values[(n, k)][0] is not None and (source != "measured" or not values[(n, k)][1])]
        if not own or (len(own) < len(datasets) and not partial):
            return None
        have = max(have, len(own))
        parts.append(fmt(sum(own) / len(own)) if source == "measured" else f"*{fmt(sum(own) / len(own))}*")
    return " / ".join(parts) + (f" ({have} of {len(datasets)})" if partial else "")


LEGEND = ("Upright: measured (one run per cell), here unless marked. *Italic*: reported by the AnyLoc paper, not measured. "
          "**Bold**: best in its column. Average ({n}): over the paper's {n} datasets of this table, each value of "
          "the row's own kind, only for a row that has all of them.")


def marks_note(board: Board, column: Column | None = None) -> str:
    """The note at the top of every page: which cells are marked, and why. A dataset page (`column`)
    counts only its own cells and the runs left out on its dataset; the overview, which shows every
    cell, counts the whole leaderboard and says so."""
    page = column is not None
    board = board.of_column(column) if page else board
    found, are = board.marked, "on this page are" if page else "are"
    parts = []
    if found["marked_rows"]:
        parts.append(f"{found['marked_rows']} cell(s) {are} on rows marked † (weights other than the authors' release, "
                     "a vocabulary named as theirs that is not their release, approximate search, a float16 store or anything fitted on the evaluated database: the mark says which)")
    if found["own_data"]:
        own = next(c.title for c in board.columns if c.kind == "own")  # how such a column is headed: name it as it reads
        parts.append(f"{found['own_data']} cell(s) {are} on the user's own data, in columns headed by the data's name "
                     f"and \"own\", e.g. {text(own)}")
    elsewhere = [c.source for c in board.cells.values() if source_mark(c.source)]
    if elsewhere:
        parts.append(f"{len(elsewhere)} cell(s){' on this page' if page else ''} have runs contributed to a results "
                     "repository or imported, each re-scored here from its per-query arrays:" + marks_legend(elsewhere).rstrip("."))
    if found["excluded"]:
        runs = f"run(s) on {text(column.dataset)}" if page else "run(s)"
        parts.append(f"{found['excluded']} {runs} are left out of every cell (see [Runs left out](index.md#runs-left-out))")
    if page:
        note = "; ".join(parts) if parts else "every cell on this page is an official run on a benchmark's protocol"
    else:
        note = "across the leaderboard, " + ("; ".join(parts) if parts else "every cell is an official run on a "
                                             "benchmark's protocol")
    return f"!!! note \"Marks\"\n    {note[0].upper() + note[1:]}. Nothing here is presented as measured unless it was measured.\n"


#: what the Results table's columns hold, in which units
RESULTS_LEGEND = ("R@K and R@100%P in percent (R@100%P: the share of correct top-1 matches ranked above the most "
                  "confident wrong one); AUC-PR from 0 to 1. Dim: descriptor dimensions. Bytes: one descriptor as stored (4 per "
                  "dimension, 2 in a float16 store). Images/s: descriptors computed per second of extraction, by the "
                  "run named below.")
DOWNLOAD_UNITS = ("r1 .. r20 and their intervals in percent, to 6 decimals where the pages show one; auc_pr, max_f1 and recall_at_100_precision from 0 to 1, "
                  "as in the records")
PARTIAL_LEGEND = (" Measured so far: a measured row's mean over the datasets it has been run on, of all those "
                  "shown (n of m); not comparable with the averages.")


def other_rows(board: Board) -> list[tuple[Row, Column, Cell]]:
    """Cells that are not official runs on a benchmark: non-official weights or own data."""
    return [(row, column, cell) for row in board.rows for column in board.columns
            if (cell := board.cell(row, column)) and (not row.official or column.kind != "benchmark")]


def reported_page() -> str:
    """The paper's reported values (Tables II-VII), as reported, never as measured."""
    frame = paper_results()
    lines = ["# Reported by the AnyLoc paper", "",
             "Keetha et al., *AnyLoc: Towards Universal Visual Place Recognition*, IEEE RA-L 2023. Values as "
             "reported (percent), from `manifests/reference/anyloc-paper.csv`; none of them was measured here.", ""]
    for table, part in frame[~frame["table"].str.startswith("ablation")].groupby("table", sort=False):
        recall = part["metric"] != part["column"]  # a column of its own (Table VI's dim) is no recall
        grid = part.assign(col=(part["column"] + " " + part["metric"].str.upper().str.replace("R", "R@")).where(recall, part["column"]))
        wide = grid.pivot_table(index="row", columns="col", values="value", aggfunc="first", sort=False)
        counts = list(dict.fromkeys(grid.loc[~recall, "col"]))
        wide[counts] = wide[counts].astype("Int64")  # a dimension as the paper gives it: 384, not 384.0
        lines += [f"## Table {table}", "", wide.to_markdown(floatfmt=".1f"), ""]
        settings = [s for s in part["setting"].unique() if s]
        lines += [f"*{s}*" for s in settings] + ([""] if settings else [])
    return "\n".join(lines)
