"""One run read on every surface: `evaluate`'s table, `results verify`, `leaderboard compare`, the
terminal board's JSON and the site's downloads name it, mark it and round it alike."""
from __future__ import annotations

import json

import pytest

from vprbench.bundles.verify import BundleReport, Verdict
from vprbench.cli.evaluate import results_table
from vprbench.errors import VPRBenchError
from vprbench.leaderboard import build_board, grid, render
from vprbench.leaderboard.compare import compare
from vprbench.leaderboard.downloads import summary
from vprbench.leaderboard.tables import cell_stats, fmt


def test_results_verify_rounds_a_recall_as_the_leaderboard_does(tmp_path):
    """Before: verify printed 'R@1 48.65' for the run every table shows as 48.6 (23 of 80 queries
    read 28.75 beside 28.8), as if one of them rounded wrongly."""
    verdict = Verdict("run.json", "r1", "hog on corridor:vpr-bench", recall={"1": 48.648649, "5": 75.675676})
    [line] = BundleReport(tmp_path / "b.tar.gz", verdicts=[verdict]).lines()
    assert line.endswith(f"re-scored from its arrays: R@1 {fmt(48.648649)} R@5 {fmt(75.675676)}"), line
    assert "R@1 48.6 R@5 75.7" in line


def test_compare_names_a_random_weights_run_the_board_left_out(make_record):
    """Before: 'No run of 'dense-vlad' on corridor', while the board and the site list that very run
    under the runs left out, with why."""
    hog = make_record("hog", seed=1)
    random = make_record("dense-vlad", weights={"source": "random"}, seed=2)
    board = build_board([hog, random])
    assert [record["run_id"] for record, _ in board.excluded] == [random["run_id"]]
    with pytest.raises(VPRBenchError, match="left out of every cell: random weights") as found:
        compare(board, "dense-vlad", "hog", "corridor")
    assert random["run_id"] in str(found.value)
    alone = build_board([hog, make_record("dense-vlad", dataset="gardens-point", weights={"source": "random"})])
    with pytest.raises(VPRBenchError, match="on gardens-point is left out of every cell: random weights"):
        compare(alone, "dense-vlad", "hog", "gardens-point")  # no cell at all on that dataset


@pytest.mark.parametrize("weights, fitted, mark", [
    ({"source": "none"}, True, "fitted on the evaluated database"),
    ({"source": "user", "sha256": "ab" * 32}, False, f"user weights sha256:{'ab' * 6}"),
])
def test_the_evaluate_table_names_the_row_the_board_gives_the_run(make_record, weights, fitted, mark):
    """Before: 'dense-vlad on corridor:vpr-bench' for a run the board and site show as
    'dense-vlad † fitted on the evaluated database' (or '† user weights sha256:...')."""
    record = make_record("dense-vlad", weights=weights)
    record["provenance"]["fitted_on_evaluated_database"] = fitted
    [row] = build_board([record]).rows
    assert row.mark == mark
    assert results_table(record).title == f"dense-vlad ({mark}) on corridor:vpr-bench"


def test_the_evaluate_table_says_random_weights_once(make_record):
    title = results_table(make_record("dense-vlad", weights={"source": "random"})).title
    assert title == "dense-vlad on corridor:vpr-bench (random weights: a pipeline check, not a result)"


def test_the_leaderboards_json_names_the_protocol_and_track_as_the_downloads_do(make_record):
    """Before: `leaderboard --format json` gave run id and row but no protocol (a column 'corridor'
    read alone names none) nor track (`--track re-ranked` printed entries like single-image ones)."""
    board = build_board([make_record("hog"), make_record("sad", seed=3)])
    shown = json.loads(render(grid(board), "json", board))
    downloads = [summary(cell, cell_stats(cell)) for cell in board.cells.values()]
    assert [(s["run_id"], s["row"], s["protocol"], s["track"]) for s in shown] == \
        [(d["run_id"], d["row"], d["protocol"], d["track"]) for d in downloads]
    assert {s["protocol"] for s in shown} == {"corridor:vpr-bench"}


def test_a_download_names_the_page_that_shows_its_cell(make_record, tmp_path):
    """Before: the re-ranked and sequence cells' `page` was corridor.md, a page that never shows them
    (they are on their track's page)."""
    from vprbench.evaluation import save_result
    from vprbench.leaderboard import publish

    for record in (make_record(seed=1), make_record(seed=2, stages=[{"name": "diagonal", "length": 10}])):
        save_result(record)
    out = publish(tmp_path / "docs")
    entries = json.loads((out / "downloads" / "leaderboard.json").read_text())
    assert {e["track"]: e["page"] for e in entries} == {"single-image": "corridor.md", "sequence": "track-sequence.md"}
    for entry in entries:
        assert entry["run_id"] in (out / entry["page"]).read_text()


def test_results_verify_names_the_row_with_the_marks_the_board_gives_it(make_record, tmp_path):
    """Before: a run on random weights verified as 'dense-vlad on corridor:vpr-bench: ok', as an
    official one reads; the board leaves it out of every cell and names it 'dense-vlad † weights random'."""
    from vprbench.bundles import export_bundle, verify_bundle
    from vprbench.evaluation import read_results, save_result

    save_result(make_record("dense-vlad", weights={"source": "random"}))
    [verdict] = verify_bundle(export_bundle(read_results(), tmp_path / "b.tar.gz"), None).verdicts
    assert verdict.label == "dense-vlad † weights random on corridor:vpr-bench"


def test_a_track_names_the_runs_of_its_own_it_left_out(make_record, capsys):
    """Before: a sequence run on random weights was missing from `leaderboard --track sequence`
    without a word ('No run in the sequence track yet'), while the site lists it under the runs left out."""
    from vprbench.cli.main import main
    from vprbench.evaluation import save_result

    random = make_record("dense-vlad", weights={"source": "random"}, stages=[{"name": "diagonal", "length": 10}])
    for record in (make_record(seed=1), random):
        save_result(record)
    board = build_board([make_record(seed=1), random])
    assert [r["run_id"] for r, _ in board.of_track("sequence").excluded] == [random["run_id"]]
    assert [r["run_id"] for r, _ in board.of_track("re-ranked").excluded] == []
    assert main(["leaderboard", "--track", "sequence"]) == 1
    err = capsys.readouterr().err
    assert "No run in the sequence track can fill a cell: run " + random["run_id"] in " ".join(err.split()), err
    assert "random weights" in err


def test_a_download_tells_apart_two_protocols_of_one_own_folder(make_record, tmp_path):
    """Before: ±1 and ±10 frames on one folder were both 'my-traverse:own' in the downloads; their
    pages give each protocol's hash beside the id."""
    own = dict(dataset="my-traverse", kind="own", unit="frames", n_database=40, n_queries=40, root=tmp_path / "t")
    board = build_board([make_record(radius=1, seed=1, **own), make_record(radius=10, seed=2, **own)])
    entries = [summary(cell, cell_stats(cell)) for cell in board.cells.values()]
    assert {e["protocol"] for e in entries} == {"my-traverse:own"}
    hashes = sorted(c.record["protocol"]["hash"] for c in board.cells.values())
    assert sorted(e["protocol_hash"] for e in entries) == hashes
    assert len({e["protocol_hash"] for e in entries}) == 2


def test_the_downloads_give_an_intervals_ends_to_the_recalls_decimals(make_record):
    """Before: r1 48.648649 beside r1_ci_low 34.54545454545455 (a full float) in leaderboard.csv/json."""
    (cell,) = build_board([make_record("hog", seed=1)]).cells.values()
    entry = summary(cell, cell_stats(cell))
    values = [entry[f"r{k}{end}"] for k in (1, 5) for end in ("", "_ci_low", "_ci_high")]
    assert all(isinstance(v, float) for v in values), values
    assert all(v == round(v, 6) for v in values), values


def test_a_sweep_summary_puts_no_random_weights_number_in_its_recall_columns(make_record):
    """Before: the sweep's (and reproduce's) summary showed R@1 20.7 and R@5 44.1 of a run on random
    weights in the columns beside real runs' numbers, with only a note '[1]' saying it was a check."""
    from types import SimpleNamespace

    from rich.console import Console

    from vprbench.sweep import Outcome, summary_table

    hog, random = make_record("hog", seed=1), make_record("dense-vlad", weights={"source": "random"}, seed=2)
    outcomes = [Outcome(SimpleNamespace(title=lambda m=m: f"{m} | corridor:vpr-bench", spec=SimpleNamespace(ks=(1, 5))),
                        "ran", "", r) for m, r in (("hog", hog), ("dense-vlad", random))]
    group = summary_table(outcomes)
    table = group.renderables[0]
    recall = {c.header: list(c._cells) for c in table.columns if c.header in ("R@1", "R@5")}
    assert recall["R@1"] == [fmt(hog["recall"]["1"]), ""] and recall["R@5"] == [fmt(hog["recall"]["5"]), ""]
    console = Console(width=300, record=True)
    console.print(group)
    shown = console.export_text()
    assert f"random weights: a pipeline check, not a result (R@1 {fmt(random['recall']['1'])}, R@5 {fmt(random['recall']['5'])})" in shown


def test_a_sweep_summary_shows_the_k_its_cells_asked(make_record):
    """Before: always R@1 and R@5, so 'evaluate --method hog sad --k 10 20' showed two empty columns."""
    from types import SimpleNamespace

    from vprbench.sweep import Outcome, summary_table

    hog = make_record("hog", seed=1)
    cell = SimpleNamespace(title=lambda: "hog | corridor:vpr-bench", spec=SimpleNamespace(ks=(10, 20)))
    table = summary_table([Outcome(cell, "ran", "", hog)]).renderables[0]
    recall = {c.header: list(c._cells) for c in table.columns if str(c.header).startswith("R@")}
    assert recall == {"R@10": [fmt(hog["recall"]["10"])], "R@20": [fmt(hog["recall"]["20"])]}, recall
