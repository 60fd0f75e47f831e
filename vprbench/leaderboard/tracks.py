"""The re-ranked and sequence tracks: one page each, one table per dataset, never mixed with
single-image retrieval (a re-ranker is compared beside its retriever, not among retrievers)."""
from __future__ import annotations

from .cells import Board, Cell
from .escape import code, text
from .tables import fmt, left_out_section, marks_legend, number, row_cells, source_mark, with_ci
from ..text import percent

TITLES = {"single-image": "Single-image retrieval", "re-ranked": "Re-ranked", "sequence": "Sequence matching"}
INTRO = {
    "re-ranked": "Runs whose retrieval's top K was re-ordered by a stage (geometric verification, query expansion, "
                 "...). Each row sits beside its retriever alone (the single-image run of the same method, options "
                 "and search) and the ceiling its re-ranker could reach: the share of queries with a positive among "
                 "the K candidates it was given. Stage ms / query is the stage's own wall clock, with the per-image "
                 "features it computed (SIFT keypoints, patches): a run that found them cached spends less (its "
                 "record's features_computed says how many it computed).",
    # the curve is VPR-Bench's, whose recall is over the correct top-1 matches: calling it the robotics'
    # convention (recall over the queries with a positive) invited comparison with SeqSLAM papers' F1max
    "sequence": "Runs matched over sequences of frames of an ordered traverse; AUC-PR, R@100%P and the largest F1 "
                "of VPR-Bench's precision-recall curve of the top-1 matches (recall over the correct matches, not "
                "over the queries with a positive as in robotics' single-match curves) beside Recall@K.",
}


def track_file(track: str) -> str:
    return f"track-{track}.md"


def retriever_key(cell: Cell) -> str:
    from ..spec import RunSpec

    return RunSpec.model_validate(cell.record["spec"]).model_copy(update={"stages": ()}).row_key


def _cost(cell: Cell, key: str, digits: int = 1) -> str:
    values = [s.get(key) for s in cell.record.get("stages") or [] if isinstance(s.get(key), (int, float))]
    return " + ".join(_amount(v, digits) for v in values) if values else "–"


def _amount(value: float, digits: int) -> str:
    """`digits` decimals, or two significant figures when those would read 0 (0.038 ms, not 0.0)."""
    shown = f"{value:,.{digits}f}"
    return f"{value:.2g}" if value and float(shown.replace(",", "")) == 0 else shown


def track_page(full: Board, track: str, stats: dict, head: str = "") -> str:
    """The page of `track` (re-ranked or sequence): per dataset, its runs with intervals and costs."""
    board = full.of_track(track)
    alone = {(row.key, key): cell for (row, key), cell in full.cells.items() if row.track == "single-image"}
    lines, sources = [], []  # sources: where each number shown comes from, for the marks' legend
    for column in board.columns:
        lines += [f"## {text(column.title)}", ""]
        if track == "re-ranked":
            lines += ["| Method | Weights | Licence | R@1 [95 % CI] | R@5 [95 % CI] | Ceiling (R@K of its candidates) "
                      "| Retriever alone R@1 | Stage ms / query | Stored bytes / database image | Run |",
                      "|:--|:--|:--|--:|--:|--:|--:|--:|--:|:--|"]
        else:
            lines += ["| Method | Weights | Licence | R@1 [95 % CI] | R@5 [95 % CI] | AUC-PR | R@100%P | max F1 "
                      "| Stage ms / query | Run |", "|:--|:--|:--|--:|--:|--:|--:|--:|--:|:--|"]
        for row in board.rows:
            cell = board.cell(row, column)
            if cell is None:
                continue
            s, r = stats[(row, column.key)], cell.record
            first = row_cells(row, cell)  # escaped name, weights, licence: as on the dataset pages
            sources.append(cell.source)
            if track == "re-ranked":
                base = alone.get((retriever_key(cell), column.key))
                sources += [base.source] if base else []
                alone_r1 = fmt(base.recall(1)) + source_mark(base.source) if base else "–"
                lines.append(f"| {first} | {with_ci(s[1])} | {with_ci(s[5])} | {_cost(cell, 'ceiling_recall')} | "
                             f"{alone_r1} | {_cost(cell, 'ms_per_query')} | "
                             f"{_cost(cell, 'stored_bytes_per_database_image', 0)} | {code(r.get('run_id'))} |")
            else:
                shown = [number(r.get("auc_pr"), 3), number(r.get("max_f1"), 3)]
                shown.insert(1, percent(r.get("recall_at_100_precision")))  # in percent, as on the dataset pages
                lines.append(f"| {first} | {with_ci(s[1])} | {with_ci(s[5])} | {' | '.join(shown)} | "
                             f"{_cost(cell, 'ms_per_query')} | {code(r.get('run_id'))} |")
        lines.append("")
    if not board.columns:
        lines += ["No run in this track yet.", ""]
    lines += left_out_section(board)  # the track's own (random weights, refused by the re-score)
    legend = marks_legend(sources)
    return "\n".join([head, f"# {TITLES[track]}", "", INTRO[track], "", *([f"Marks:{legend}", ""] if legend else []),
                      *lines])
