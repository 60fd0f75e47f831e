"""What a reader sees on the leaderboard, pinned where a small change to cells.py or tables.py went
unnoticed by the other tests (a hand mutation audit): which run fills a cell and lends it its speed,
column headings, the interval's order, the marks of a cell's source, the paper tables' averages,
protocol and marks, the sign of a comparison's delta; no paper comparison for a variant protocol, the
"nothing measured yet" note, undeclared weights giving way, runs left out per track, a row's search kept
apart from its weights, and no speed from a run served from stores."""
import pytest

from vprbench.leaderboard.cells import AGREES, CONTRIBUTED, IMPORTED, MEASURED, build_board
from vprbench.leaderboard.tables import cell_stats, source_mark, weights_shown, with_ci


def _cell(board, label="hog", dataset="corridor"):
    [row] = [r for r in board.rows if r.label == label]
    [column] = [c for c in board.columns if c.key == dataset]
    return board.cell(row, column)


def test_a_newer_run_that_reached_exactly_k_5_wins_over_an_older_deeper_one(make_record):
    """R@1 and R@5 is all a cell shows: a run searched to k=5 is complete, so the newest one wins."""
    old = make_record(quality=0.9, seed=1, created="2026-01-01T00:00:00+00:00")
    new = make_record(ks=(1, 5), k=5, quality=0.2, seed=2, created="2026-02-01T00:00:00+00:00")
    cell = _cell(build_board([old, new]))
    assert cell.record["run_id"] == new["run_id"] and cell.passed_over == 1
    assert (cell.recall(1), cell.recall(5)) == (new["recall"]["1"], new["recall"]["5"])
    assert cell.recall(5) != old["recall"]["5"]


def test_an_interval_reads_low_then_high_around_its_value(make_record):
    cell = _cell(build_board([make_record(quality=0.5, seed=3)]))
    entry = cell_stats(cell)[1]
    low, high = entry["ci"]
    assert low < entry["value"] < high
    assert with_ci(entry) == f"{entry['value']:.1f} [{low:.1f}, {high:.1f}]"
    assert with_ci({"value": 71.25, "ci": None}) == "71.2"


@pytest.mark.parametrize("source, mark", [
    (MEASURED, ""), (AGREES, "<sup>c✓</sup>"), (CONTRIBUTED, "<sup>c</sup>"), (IMPORTED, "<sup>v</sup>"),
    ("contributed, re-run here and disagreeing: R@1 40.0 here, outside its interval [50.0, 60.0]", "<sup>c≠</sup>"),
    ("contributed, re-run here (R@1 40.0; the contributed run has no interval)", "<sup>c</sup>")])
def test_each_source_of_a_cell_has_its_own_mark(source, mark):
    assert source_mark(source) == mark


def test_a_cells_speed_is_its_newest_timed_run_and_never_another_protocols(make_record):
    """Images/s: the newest run of the cell that computed its descriptors; a newer run of the row on the
    same images under another protocol lends its speed only to a cell with no timed run of its own."""
    old = make_record("hog", "vp-air", n_database=12706, n_queries=2706, seed=1, created="2026-01-01T00:00:00+00:00")
    new = make_record("hog", "vp-air", n_database=12706, n_queries=2706, seed=2, created="2026-02-01T00:00:00+00:00")
    other = make_record("hog", "vp-air", n_database=2706, n_queries=2706, protocol="no-distractors", seed=3,
                        fingerprint="fp-vp-air-2706", created="2026-03-01T00:00:00+00:00")
    for record, speed in ((old, 10.0), (new, 20.0), (other, 30.0)):
        record["images_per_second"] = speed
        record["dataset_fingerprints"] = {**record["dataset_fingerprints"], "images": "the same images"}
    cell = _cell(build_board([old, new, other]), dataset="vp-air")
    assert cell.record["run_id"] == new["run_id"] and cell.images_per_second == 20.0
    cell = _cell(build_board([old, other]), dataset="vp-air")
    assert cell.images_per_second == 10.0  # its own run's, though the other protocol's run is newer


def test_a_comparison_gives_measured_minus_reported(make_record):
    from vprbench.leaderboard.tables import comparisons

    record = make_record("anyloc-vlad-dinov2", "baidu-mall", quality=0.9)
    record["provenance"].update(vocabulary={"source": "released", "fitted_on_evaluated_database": True},
                                learnt=["vocabulary"], fitted_on_evaluated_database=True)
    found = comparisons(build_board([record]))
    assert [(c["metric"], c["reported"]) for c in found] == [("R@1", 75.2), ("R@5", 87.6)]
    for c in found:
        assert c["measured"] == record["recall"][c["metric"][2:]]
        assert c["delta"] == pytest.approx(c["measured"] - c["reported"])
        assert c["reproduced"] == (abs(c["delta"]) <= c["tolerance"])
        assert c["tolerance"] == max(1.0, (c["ci"][1] - c["ci"][0]) / 2) >= 1.0  # 1 pp, or the interval's half-width


def test_r5_comes_from_the_ranks_of_a_run_searched_exactly_to_k_5(make_record):
    from vprbench.evaluation.metrics import successes

    record = make_record(ks=(1,), k=5, quality=0.5, seed=4)
    cell = _cell(build_board([record]))
    assert "5" not in record["recall"]
    assert cell.recall(5) == pytest.approx(100 * successes(cell.arrays["first_positive_rank"], 5).mean())


def test_a_variant_protocols_column_is_headed_by_its_protocol(make_record):
    default = make_record("hog", "vp-air", n_database=12706, n_queries=2706, seed=1)
    variant = make_record("hog", "vp-air", n_database=2706, n_queries=2706, protocol="no-distractors", seed=2,
                          fingerprint="fp-vp-air-2706")
    board = build_board([default, variant])
    assert [c.title for c in board.columns] == ["vp-air", "vp-air [no-distractors]"]


def test_a_re_run_is_judged_against_the_newest_contributed_run_by_the_newest_local_one(make_record):
    from vprbench.leaderboard.cells import _source

    def run(quality, seed, day, contributed=False):
        record = make_record(quality=quality, seed=seed, created=f"2026-01-0{day}T00:00:00+00:00")
        if contributed:
            record["_contribution"] = "a results repository"
        return record

    far, theirs = run(0.95, 1, 1, contributed=True), run(0.5, 2, 2, contributed=True)
    stale, ours = run(0.05, 3, 3), run(0.5, 2, 4)  # ours: the contributed run's numbers, re-run
    assert _source(ours, [far, theirs, stale, ours]) == AGREES
    assert _source(ours, [theirs, ours]) == AGREES
    assert _source(stale, [theirs, stale]).startswith("contributed, re-run here and disagreeing")


def test_an_imported_run_is_marked_imported_not_measured(make_record):
    from vprbench.leaderboard.cells import _source

    record = make_record()
    record["imported"] = {"from": "vpr-bench"}
    assert _source(record, [record]) == IMPORTED and source_mark(_source(record, [record])) == "<sup>v</sup>"


def test_a_row_with_some_of_the_papers_datasets_has_no_average_only_its_mean_so_far(make_record):
    from vprbench.leaderboard.tables import group_table

    runs = [make_record("hog", name, seed=i) for i, name in enumerate(("baidu-mall", "pitts30k"))]
    board = build_board(runs)
    lines = [line for line in group_table(board, "II").splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    hog = next([c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith("| hog |"))
    assert header[-2:] == ["Average (6)", "Measured so far"]
    r1 = [c.recall(1) for c in board.cells.values()]
    r5 = [c.recall(5) for c in board.cells.values()]
    assert hog[-2] == "–" and hog[-1] == f"{sum(r1) / 2:.1f} / {sum(r5) / 2:.1f} (2 of 6)"


def test_an_own_column_in_metres_reads_m(make_record):
    own = make_record(kind="own", dataset="my-walk", n_database=40, n_queries=30, unit="metres", radius=25)
    assert [c.title for c in build_board([own]).columns] == ["my-walk (own, 25 m)"]


def test_a_measured_rows_average_never_mixes_in_the_papers_numbers(make_record):
    from vprbench.leaderboard.tables import group_table

    record = make_record("anyloc-vlad-dinov2", "baidu-mall", quality=0.9)
    record["provenance"].update(vocabulary={"source": "released", "fitted_on_evaluated_database": True},
                                learnt=["vocabulary"], fitted_on_evaluated_database=True)
    board = build_board([record])
    [cell] = board.cells.values()
    line = next(x for x in group_table(board, "II").splitlines() if x.startswith("| anyloc-vlad-dinov2 † "))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert "*" in cells[2]  # pitts30k etc. are the paper's numbers, in italics
    assert cells[-2] == "–" and cells[-1] == f"{cell.recall(1):.1f} / {cell.recall(5):.1f} (1 of 6)"


def test_a_paper_table_shows_the_default_protocols_run_not_a_variants(make_record):
    from vprbench.leaderboard.tables import group_table

    default = make_record("hog", "vp-air", n_database=12706, n_queries=2706, quality=0.3, seed=1)
    variant = make_record("hog", "vp-air", n_database=2706, n_queries=2706, protocol="no-distractors", quality=0.9,
                          seed=2, fingerprint="fp-vp-air-2706")
    board = build_board([default, variant])
    lines = [line for line in group_table(board, "III").splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    hog = next([c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith("| hog |"))
    shown = hog[next(i for i, h in enumerate(header) if h.startswith("[vp-air]"))].replace("**", "")
    assert shown == f"{default['recall']['1']:.1f} / {default['recall']['5']:.1f}"


def test_the_marks_note_counts_the_runs_left_out(make_record):
    from vprbench.leaderboard.tables import marks_note

    random = make_record("cosplace", weights={"source": "random"}, seed=2)
    note = marks_note(build_board([make_record(seed=1), random]))
    assert "1 run(s) are left out of every cell" in note


def test_a_paper_table_marks_a_contributed_cell(make_record):
    from vprbench.leaderboard.tables import group_table

    record = make_record(seed=1)
    record["_contribution"] = "a results repository"
    table = group_table(build_board([record]), "II")
    line = next(x for x in table.splitlines() if x.startswith("| hog |"))
    assert "<sup>c</sup>" in line and "<sup>c</sup> contributed to the results repository" in table


def test_a_run_searched_exactly_to_k_5_has_an_interval_at_r5(make_record):
    cell = _cell(build_board([make_record(ks=(1, 5), k=5, quality=0.5, seed=5)]))
    stats = cell_stats(cell)
    assert stats[5]["ci"] is not None and stats[5]["ci"][0] < stats[5]["value"] < stats[5]["ci"][1]


def test_a_variant_protocols_cell_is_never_set_against_the_papers_number(make_record):
    """The paper reports only the default protocol: a variant's cell gets no mark nor delta against it."""
    from vprbench.leaderboard.tables import comparisons

    paper = {"preprocess": "anyloc"}  # as the paper's plan runs CosPlace (VP-Air at its stored size)
    variant = make_record("cosplace", "vp-air", n_database=2706, n_queries=2706, protocol="no-distractors", seed=2,
                          fingerprint="fp-vp-air-2706", options=paper)
    assert comparisons(build_board([variant])) == []
    default = make_record("cosplace", "vp-air", n_database=12706, n_queries=2706, seed=1, options=paper)
    found = comparisons(build_board([default, variant]))
    assert [(c["dataset"], c["metric"], c["reported"], c["run_id"]) for c in found] == [
        ("vp-air", "R@1", 8.1, default["run_id"]), ("vp-air", "R@5", 14.2, default["run_id"])]


def test_a_paper_table_without_a_measured_row_says_every_value_is_reported(make_record):
    from vprbench.leaderboard.tables import group_table

    note = "No official run measured in this group yet: every value below is reported."
    board = build_board([make_record(seed=1)])  # corridor: none of Table III's datasets
    assert note in group_table(board, "III") and note not in group_table(board, "II")


def test_an_older_run_with_undeclared_weights_gives_way_to_a_later_declared_one(make_record):
    old = make_record(seed=1, created="2026-01-01T00:00:00+00:00")
    old["provenance"]["weights"] = {"source": "undeclared"}  # as provenance() recorded a method that declared none
    new = make_record(seed=2, created="2026-02-01T00:00:00+00:00")
    board = build_board([old, new])
    assert [r.name for r in board.rows] == ["hog"]
    assert [c.record["run_id"] for c in board.cells.values()] == [new["run_id"]]
    assert [(r["run_id"], why.split(";")[0]) for r, why in board.excluded] == [
        (old["run_id"], "its method did not declare its weights then")]
    alone = build_board([old])  # no declared run yet: it keeps its row, marked
    assert [r.name for r in alone.rows] == ["hog † weights undeclared"] and not alone.excluded


def test_runs_left_out_are_listed_with_the_single_image_track_only(make_record):
    random = make_record("cosplace", weights={"source": "random"}, seed=3)
    board = build_board([make_record(seed=1), make_record(seed=2, stages=[{"name": "diagonal", "length": 10}]), random])
    assert [r["run_id"] for r, _ in board.of_track("single-image").excluded] == [random["run_id"]]
    assert board.of_track("sequence").cells and board.of_track("sequence").excluded == []


def test_a_rows_search_is_named_apart_from_its_weights(make_record):
    from vprbench.leaderboard.shown import row_name

    board = build_board([make_record(seed=1, search={"index": "hnsw"})])
    [row] = board.rows
    [cell] = board.cells.values()
    assert (row.name, row.setting, row_name(row)) == ("hog † hnsw search", "hnsw search", "hog † hnsw search")
    assert weights_shown(row, cell.record) == "none (nothing learnt)"
    other = make_record(seed=2, search={"index": "hnsw"})
    other["spec"]["options"] = {"cells": 8}  # another version of the preset: the same label, told apart by key
    board = build_board([make_record(seed=1, search={"index": "hnsw"}), other])
    assert len({r.label for r in board.rows}) == 2
    for row in board.rows:
        assert row.setting == "hnsw search" and row_name(row).endswith(" † hnsw search")
        assert weights_shown(row, board.cells[(row, "corridor")].record) == "none (nothing learnt)"


def test_a_speed_claimed_by_a_run_served_from_stores_is_never_a_cells(make_record):
    measured = make_record(seed=1, created="2026-01-01T00:00:00+00:00")
    served = make_record(seed=1, created="2026-02-01T00:00:00+00:00")
    measured["images_per_second"], served["images_per_second"] = 211.0, 9999.0
    served.update(served_from_store=True, descriptors_computed={"database": 0, "queries": 0})
    cell = _cell(build_board([measured, served]))
    assert cell.record["run_id"] == served["run_id"] and cell.timed["run_id"] == measured["run_id"]
    assert cell.images_per_second == 211.0
    assert _cell(build_board([served])).images_per_second is None
