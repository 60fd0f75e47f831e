"""What a researcher reads on the published leaderboard, checked against the records: every label
tells its row apart, a number reads the same (unit, digits) on every page and figure, bold marks the
best value as shown, a caption names the machines its speeds come from, and a contributed run's
mark is decided by the interval the site gives that run."""
from __future__ import annotations

import copy
import os
import shutil

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.leaderboard.cells import Board, Cell, Column, Row, build_board
from vprbench.leaderboard.site import dataset_page
from vprbench.leaderboard.tables import cell_stats, group_table
from vprbench.leaderboard.tracks import track_page


@pytest.fixture(scope="module")
def corridor_root(shared_data, tmp_path_factory):
    """<root>/data (the real Corridor, as symlinks) and <root>/cache with real hog runs on it:
    single-image and with the diagonal sequence matcher."""
    root = tmp_path_factory.mktemp("site-numbers")
    shutil.copytree(shared_data / "corridor", root / "data" / "corridor", copy_function=os.symlink)
    for extra in ([], ["--sequence", "diagonal"]):
        assert main(["evaluate", "--method", "hog", "--dataset", "corridor", "--quiet", "--data-dir",
                     str(root / "data"), "--cache-dir", str(root / "cache"), *extra]) == 0
    return root


@pytest.fixture(scope="module")
def corridor_runs(corridor_root):
    return read_results(corridor_root / "cache")


def _variants(record: dict) -> list[dict]:
    """The run as an exact float32 one, an HNSW one and a float16-store one (three rows of one label)."""
    found = []
    for n, (index, dtype) in enumerate((("exact", "float32"), ("hnsw", "float32"), ("exact", "float16"))):
        again = copy.deepcopy(record)
        again["spec"]["search"]["index"], again["spec"]["store_dtype"] = index, dtype
        again["run_id"] = f"{record['run_id']}-{n}"
        found.append(again)
    return found


def _table_rows(page: str, after: str) -> list[list[str]]:
    lines = page.split(after, 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|:--"))
    rows = []
    for line in lines[start + 1:]:
        if not line.startswith("| "):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split(" | ")])
    return rows


def _sequence_rows(corridor_runs) -> tuple[Board, list[list[str]]]:
    sequence = next(r for r in corridor_runs if r.get("track") == "sequence")
    board = build_board(_variants(sequence))
    stats = {key: cell_stats(cell) for key, cell in board.cells.items()}
    return board, _table_rows(track_page(board, "sequence", stats), "## corridor")


def test_the_sequence_track_names_each_row(corridor_runs):
    """Before: two rows read 'hog + diagonal †' (HNSW and float16 store), and no Weights column
    told them apart."""
    _, rows = _sequence_rows(corridor_runs)
    assert [row[0] for row in rows] == ["hog + diagonal", "hog + diagonal † float16 store", "hog + diagonal † hnsw search"]


def test_the_sequence_track_gives_recall_at_full_precision_in_percent(corridor_runs):
    """Before: R@100%P read 0.181 on the sequence page (a fraction) while the dataset pages, the
    terminal and `evaluate` give it in percent (5.6 for hog on Corridor)."""
    board, rows = _sequence_rows(corridor_runs)
    fraction = next(iter(board.cells.values())).record["recall_at_100_precision"]
    assert 0 < fraction < 1 and [row[6] for row in rows] == [f"{100 * fraction:.1f}"] * 3, rows


def test_the_runs_table_of_a_dataset_page_names_each_row(corridor_runs, tmp_path):
    """Before: 'The runs in the cells above' listed 'hog †' twice, one run id each, with nothing to
    say which was the HNSW run and which the float16 one."""
    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    board = build_board(_variants(single))
    (tmp_path / "figures").mkdir()
    (tmp_path / "downloads").mkdir()
    stats = {key: cell_stats(cell) for key, cell in board.cells.items()}
    page = dataset_page(tmp_path, board, board.columns[0], stats)
    runs = {row[0]: row[3].removeprefix("<code>").removesuffix("</code>")
            for row in _table_rows(page, "The runs in the cells above")}
    assert runs == {"hog": f"{single['run_id']}-0", "hog † hnsw search": f"{single['run_id']}-1",
                    "hog † float16 store": f"{single['run_id']}-2"}


@pytest.mark.parametrize("measured", [91.46, 91.54])
def test_bold_marks_every_value_that_reads_as_the_best(measured):
    """Before: a measured Pitts-30k R@1 of 91.46 read '91.5' beside MixVPR's reported *91.5*, and only
    the paper's was bold (91.54: only the measured one); R@5 95.74 was bold and CosPlace's 95.7 not."""
    row, column = Row("k", "hog", "official", ""), Column("pitts30k", "pitts30k", "benchmark", "urban", "fp")
    cell = Cell(row, column, {"recall": {"1": measured, "5": 95.74}, "run_id": "r"})
    table = group_table(Board([row], [column], {(row, column.key): cell}), "II")
    lines = {line.split(" | ")[0]: line.split(" | ") for line in table.splitlines() if line.startswith("| ")}
    at = lines["| Method"].index("[pitts30k](pitts30k)") if "[pitts30k](pitts30k)" in lines["| Method"] else \
        lines["| Method"].index("pitts30k")
    assert lines["| hog"][at] == "**91.5** / **95.7**"
    assert lines["| *MixVPR* (paper)"][at].startswith("***91.5***")
    assert lines["| *CosPlace* (paper)"][at].endswith("***95.7***")


def test_the_efficiency_caption_names_the_machines_the_speeds_were_measured_on(corridor_runs, tmp_path):
    """Before: the caption said '(this machine)' whatever machines the runs named (a cache shared by
    several machines, or contributed runs), while the runs table beside it named each one."""
    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    runs = _variants(single)
    runs[2]["hardware"] = {**runs[2]["hardware"], "cpu": "Other CPU", "cpu_count": 64, "cuda": "NVIDIA A100"}
    board = build_board(runs)
    (tmp_path / "figures").mkdir()
    (tmp_path / "downloads").mkdir()
    page = dataset_page(tmp_path, board, board.columns[0], {key: cell_stats(cell) for key, cell in board.cells.items()})
    caption = next(line for line in page.splitlines() if line.startswith("*Efficiency"))
    here = f"{single['hardware']['cpu']} ({single['hardware']['cpu_count']} cores), no GPU"
    assert "this machine" not in caption and here in caption and "Other CPU (64 cores), NVIDIA A100" in caption, caption


def test_the_precision_recall_legend_gives_auc_as_the_page_does(corridor_runs, tmp_path):
    """Before: the page gave hog's AUC-PR as 0.655 and the figure's legend as 0.65."""
    from vprbench.leaderboard import figures

    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    board = build_board([single])
    auc = next(iter(board.cells.values())).record["auc_pr"]
    assert f"{auc:.3f}" == "0.655" and f"{auc:.2f}" == "0.65"  # hog on the real Corridor: where the two differ
    svg = figures.pr_curves(board.column_cells(board.columns[0]), tmp_path / "pr.svg").read_text()
    assert "hog (AUC 0.655)" in svg and "(AUC 0.65)" not in svg


def test_a_re_run_is_judged_by_the_interval_the_site_gives_the_contributed_run(corridor_runs):
    """Before: c✓ / c≠ came from a per-query interval ([39.6, 57.7] for hog on Corridor) while every
    page gives the contributed run's block interval ([34.5, 62.7]): a re-run at 60.4 was marked
    'disagreeing ... outside its interval [39.6, 57.7]', inside the interval shown for that run."""
    from vprbench.evaluation.results import per_query
    from vprbench.leaderboard.cells import AGREES

    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    arrays = per_query(single)
    inline = {"k": int(arrays["database_indices"].shape[1]), **{n: a.tolist() for n, a in arrays.items()}}
    theirs = {**copy.deepcopy(single), "per_query": inline, "_contribution": {"contributor": "A. Lab"}}
    ranks = arrays["first_positive_rank"].copy()
    ranks[np.flatnonzero(ranks != 1)[:13]] = 1  # 54 + 13 of 111 queries right at the top: R@1 60.4
    ours = {**copy.deepcopy(single), "per_query": {**inline, "first_positive_rank": ranks.tolist()},
            "run_id": single["run_id"] + "-here", "created": "2999-01-01T00:00:00.000+00:00",
            "recall": {k: round(100 * float(np.mean((ranks >= 1) & (ranks <= int(k)))), 4) for k in single["recall"]},
            "auc_pr": None, "recall_at_100_precision": None, "max_f1": None}  # recomputed from the arrays
    (shown,) = build_board([theirs]).cells.values()
    assert [round(v, 1) for v in cell_stats(shown)[1]["ci"]] == [34.5, 62.7]  # the contributed run's, on every page
    (cell,) = build_board([theirs, ours]).cells.values()
    assert cell.record["run_id"] == ours["run_id"] and f"{cell.recall(1):.1f}" == "60.4"
    assert cell.source == AGREES, cell.source


def test_a_mosaic_caption_says_how_many_matches_it_shows(corridor_root, corridor_runs, tmp_path):
    """Before: a run kept with --k 1 had its mosaic drawn with one match per query under the caption
    'queries and their top 5'."""
    from vprbench.evaluation.results import per_query

    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    arrays = per_query(single)
    ranks = arrays["first_positive_rank"]
    top1 = {**copy.deepcopy(single), "recall": {"1": single["recall"]["1"]},
            "per_query": {"k": 1, "database_indices": arrays["database_indices"][:, :1].tolist(),
                          "similarities": arrays["similarities"][:, :1].tolist(),
                          "first_positive_rank": np.where(ranks == 1, 1, 0).tolist(), "positives": arrays["positives"].tolist()}}
    board = build_board([top1])
    (tmp_path / "figures").mkdir()
    (tmp_path / "downloads").mkdir()
    page = dataset_page(tmp_path, board, board.columns[0], {key: cell_stats(cell) for key, cell in board.cells.items()},
                        data_dir=corridor_root / "data")
    assert "![hog: queries and their top 1](figures/corridor-mosaic-hog.png)" in page, page
    assert "top 5" not in page


def test_the_marks_note_names_own_data_columns_as_they_are_headed(corridor_runs):
    """Before: every page's note said own-data cells are 'marked *(own data)*', a mark no page shows:
    their columns read e.g. 'corridor (own, ±2 frames)'."""
    from vprbench.leaderboard.tables import marks_note

    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    own = {**copy.deepcopy(single), "dataset_kind": "own"}
    board = build_board([single, own])
    titles = [c.title for c in board.columns]
    assert titles == ["corridor", "corridor (own, ±2 frames)"]
    note = marks_note(board)
    assert "1 cell(s) are on the user's own data" in note and "corridor (own, ±2 frames)" in note
    assert "(own data)" not in note, note


def test_a_contributed_run_kept_without_k_1_is_judged_from_its_arrays(corridor_runs):
    """Before: a contributed run evaluated with --k 5 10 (no '1' among its recall keys) was shown as
    'has no interval', though its per-query arrays give R@1 and its interval."""
    from vprbench.evaluation.results import per_query
    from vprbench.leaderboard.cells import AGREES

    single = next(r for r in corridor_runs if r.get("track", "single-image") == "single-image")
    arrays = per_query(single)
    inline = {"k": int(arrays["database_indices"].shape[1]), **{n: a.tolist() for n, a in arrays.items()}}
    theirs = {**copy.deepcopy(single), "per_query": inline, "_contribution": {"contributor": "A. Lab"},
              "recall": {k: v for k, v in single["recall"].items() if k != "1"}}
    ours = {**copy.deepcopy(single), "run_id": single["run_id"] + "-here", "created": "2999-01-01T00:00:00.000+00:00"}
    (cell,) = build_board([theirs, ours]).cells.values()
    assert cell.record["run_id"] == ours["run_id"] and cell.source == AGREES, cell.source
