"""What a researcher reads, checked against the records: `evaluate`'s table, the terminal board,
the published pages and downloads say which search and store a run used where it belongs (its
name, not its Weights), give every unit, and never round a measured cost to nothing."""
from __future__ import annotations

import copy
import os
import shutil

import pytest

from vprbench.cli.evaluate import results_table
from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.leaderboard import grid
from vprbench.leaderboard.cells import build_board
from vprbench.leaderboard.downloads import summary
from vprbench.leaderboard.site import dataset_page, overview
from vprbench.leaderboard.tables import cell_stats
from vprbench.leaderboard.tracks import track_page


@pytest.fixture(scope="module")
def runs(shared_data, tmp_path_factory):
    """Real hog runs on Corridor: single-image and with the diagonal sequence matcher."""
    root = tmp_path_factory.mktemp("reading")
    shutil.copytree(shared_data / "corridor", root / "data" / "corridor", copy_function=os.symlink)
    for extra in ([], ["--sequence", "diagonal"]):
        assert main(["evaluate", "--method", "hog", "--dataset", "corridor", "--quiet", "--data-dir",
                     str(root / "data"), "--cache-dir", str(root / "cache"), *extra]) == 0
    found = read_results(root / "cache")
    return {r.get("track", "single-image"): r for r in found}


def _variants(record: dict) -> list[dict]:
    """The run as an exact float32 one, an HNSW one and a float16-store one, as `evaluate` records them."""
    found = []
    for n, (index, dtype) in enumerate((("exact", "float32"), ("hnsw", "float32"), ("exact", "float16"))):
        again = copy.deepcopy(record)
        again["spec"]["search"]["index"], again["spec"]["store_dtype"] = index, dtype
        again["descriptor_bytes"] = record["descriptor_dim"] * (2 if dtype == "float16" else 4)
        again["run_id"] = f"{record['run_id']}-{n}"
        found.append(again)
    return found


def _page(board, tmp_path) -> str:
    (tmp_path / "figures").mkdir(exist_ok=True)
    (tmp_path / "downloads").mkdir(exist_ok=True)
    return dataset_page(tmp_path, board, board.columns[0], {key: cell_stats(c) for key, c in board.cells.items()})


def _results_rows(page: str) -> dict[str, list[str]]:
    lines = page.split("## Results", 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|:--"))
    rows = {}
    for line in lines[start + 1:]:
        if not line.startswith("| "):
            break
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        rows[cells[0]] = cells
    return rows


def test_the_evaluate_table_names_an_approximate_search_and_a_float16_store(runs):
    """Before: `evaluate --index hnsw` and `--store-dtype float16` were titled 'hog on corridor:vpr-bench',
    as the exact float32 run; the board gives each a row of its own ('hog † hnsw search')."""
    exact, hnsw, half = (results_table(r) for r in _variants(runs["single-image"]))
    assert exact.title == "hog on corridor:vpr-bench"
    assert hnsw.title == "hog (hnsw search) on corridor:vpr-bench"
    assert half.title == "hog (float16 store) on corridor:vpr-bench"


def test_the_evaluate_caption_gives_every_unit_and_the_stored_bytes(runs):
    """Before: the caption said 'Recall in percent' beside AUC-PR 0.655 and max F1 (fractions), and
    gave no size: a float16 store's 2 bytes per dimension were nowhere."""
    half = _variants(runs["single-image"])[2]
    caption = results_table(half).caption
    assert "AUC-PR and max F1 from 0 to 1" in caption
    # a perfect AUC-PR beside R@1 60 read as a contradiction: the caption says whose recall it is
    assert "(the last three over each query's top-1 match, recall being the share of correct ones accepted" in caption
    assert f"dim 35721 ({2 * 35721} bytes as stored)" in caption, caption


def test_the_weights_column_says_what_was_learnt_not_the_search_or_store(runs):
    """Before: the Weights column of hog's HNSW and float16 rows read 'hnsw search' and 'float16 store'
    (terminal, CSV, JSON, pages, downloads); hog learns nothing, whatever its search."""
    board = build_board(_variants(runs["single-image"]))
    table = grid(board)
    assert table["weights"].to_dict() == {"hog": "none (nothing learnt)", "hog † float16 store": "none (nothing learnt)",
                                          "hog † hnsw search": "none (nothing learnt)"}


def test_a_dataset_page_names_each_row_by_its_search_and_store(runs, tmp_path):
    """Before: the Results table read 'hog †' twice, told apart only by a Weights cell that held
    'hnsw search' or 'float16 store'."""
    rows = _results_rows(_page(build_board(_variants(runs["single-image"])), tmp_path))
    assert sorted(rows) == ["hog", "hog † float16 store", "hog † hnsw search"]
    assert {name: cells[1] for name, cells in rows.items()} == dict.fromkeys(rows, "none (nothing learnt)")
    assert rows["hog † float16 store"][10] == str(2 * 35721) and rows["hog"][10] == str(4 * 35721)


def test_a_float16_record_without_its_bytes_is_not_shown_at_float32_width(runs, tmp_path):
    """Before: a record without descriptor_bytes was shown at 4 bytes per dimension, float16 store or not."""
    half = _variants(runs["single-image"])[2]
    half["descriptor_bytes"] = None
    rows = _results_rows(_page(build_board([half]), tmp_path))
    assert rows["hog † float16 store"][10] == str(2 * 35721)


def test_a_dataset_page_says_what_its_columns_hold(runs, tmp_path):
    """Before: AUC-PR read 0.655 and R@100%P 5.6 side by side, and 'Bytes' and 'Images/s' said of what,
    with no word of their units."""
    page = _page(build_board([runs["single-image"]]), tmp_path)
    legend = page.split("| Images/s |", 1)[1].split("The runs in the cells above")[0]
    assert "R@K and R@100%P in percent" in legend and "AUC-PR from 0 to 1" in legend
    assert "2 in a float16 store" in legend


def test_the_downloads_name_each_row_and_give_max_f1(runs):
    """Before: leaderboard.csv/json and <dataset>.csv gave 'hog' as the method of all three rows (the
    search and store only in the Weights column), and no max F1 though `evaluate` and the sequence
    page give it."""
    board = build_board(_variants(runs["single-image"]))
    found = [summary(cell, cell_stats(cell)) for cell in board.cells.values()]
    assert sorted(e["row"] for e in found) == ["hog", "hog † float16 store", "hog † hnsw search"]
    assert {e["max_f1"] for e in found} == {runs["single-image"]["max_f1"]}


def test_the_overview_does_not_say_a_filled_cell_is_never_filled(runs, tmp_path):
    """Before: 'Other runs' said its runs 'never fill a cell above', while a row marked only for a
    part fitted on the evaluated database (as the paper's AnyLoc vocabularies are) fills Table II;
    and its list of marks left out approximate search and float16 stores."""
    fitted = copy.deepcopy(runs["single-image"])
    fitted["provenance"]["fitted_on_evaluated_database"] = True
    board = build_board([fitted])
    (tmp_path / "figures").mkdir()
    page = overview(tmp_path, board, [fitted], {key: cell_stats(c) for key, c in board.cells.items()})
    assert "| hog † fitted on the evaluated database | – / – |" in page  # Table II: it fills a cell
    other = page.split("## Other runs", 1)[1].split("|", 1)[0]
    assert "never fill a cell above" not in other
    assert "approximate search" in other and "float16 store" in other


def test_a_cell_just_outside_the_tolerance_does_not_read_as_inside_it(runs, tmp_path, monkeypatch):
    """Before: a delta of +1.04 against a tolerance of 1.0 read "+1.0 | ±1.0 | **no**"."""
    from vprbench.leaderboard import site

    board = build_board([runs["single-image"]])
    found = {"method": "hog", "row": "hog", "dataset": "baidu-mall", "metric": "R@1", "measured": 76.24, "ci": None,
             "reported": 75.2, "delta": 76.24 - 75.2, "tolerance": 1.0, "reproduced": False, "table": "II"}
    monkeypatch.setattr(site, "comparisons", lambda board, seed=0: [found])
    (tmp_path / "figures").mkdir()
    page = overview(tmp_path, board, [runs["single-image"]], {key: cell_stats(c) for key, c in board.cells.items()})
    assert "| 76.2 | *75.2* (Table II) | +1.04 | ±1.00 | **no** |" in page


def test_a_stage_cost_under_a_twentieth_of_a_millisecond_is_not_shown_as_zero(runs):
    """Before: SeqSLAM's 0.038 ms per query on Corridor read '0.0' on the sequence page."""
    sequence = copy.deepcopy(runs["sequence"])
    sequence["stages"][0]["ms_per_query"] = 0.038
    board = build_board([sequence])
    page = track_page(board, "sequence", {key: cell_stats(c) for key, c in board.cells.items()})
    row = next(line for line in page.splitlines() if line.startswith("| hog + diagonal"))
    assert row.split(" | ")[-2] == "0.038", row


def test_the_efficiency_figure_does_not_call_its_bytes_float32(runs, tmp_path):
    """Before: the x axis read 'descriptor size (bytes, float32)' while it plots each record's stored
    bytes (a float16 store's at 2 per dimension)."""
    from vprbench.leaderboard import figures

    board = build_board(_variants(runs["single-image"]))
    svg = figures.efficiency(board.column_cells(board.columns[0]), tmp_path / "e.svg").read_text()
    assert "descriptor size (bytes as stored)" in svg and "float32" not in svg
