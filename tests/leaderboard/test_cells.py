"""One run per cell, by the stated rule: the cases that used to mix runs, own data named like a
benchmark, other protocols and data copies, and weights that are not the authors'."""
import pytest

from vprbench.evaluation import read_results, save_result
from vprbench.leaderboard import build_board, grid
from vprbench.evaluation.metrics import successes


def board_of(*records):
    for record in records:
        save_result(record)
    return build_board(read_results())


def only_cell(board, label="hog", dataset="corridor"):
    [row] = [r for r in board.rows if r.label == label and r.official]
    [column] = [c for c in board.columns if c.key == dataset]
    return board.cell(row, column)


def test_newest_run_with_k_1_10_gives_its_own_r5_not_an_older_runs(make_record):
    """0.1: groupby().last() showed the new run's R@1 beside the old run's R@5."""
    old = make_record(quality=0.9, seed=1, created="2026-01-01T00:00:00+00:00")
    new = make_record(ks=(1, 10), k=10, quality=0.2, seed=2, created="2026-02-01T00:00:00+00:00")
    cell = only_cell(board_of(old, new))
    assert cell.record["run_id"] == new["run_id"] and cell.passed_over == 1
    assert cell.recall(1) == new["recall"]["1"]
    first = cell.arrays["first_positive_rank"]
    assert cell.recall(5) == pytest.approx(100 * successes(first, 5).mean())  # from the same run's ranks
    assert cell.recall(5) != pytest.approx(old["recall"]["5"])


def test_a_shallow_newest_run_never_lends_its_r1_to_an_older_runs_r5(make_record):
    old = make_record(quality=0.9, seed=1, created="2026-01-01T00:00:00+00:00")
    shallow = make_record(ks=(1, 3), k=3, quality=0.1, seed=2, created="2026-02-01T00:00:00+00:00")
    cell = only_cell(board_of(old, shallow))
    assert cell.record["run_id"] == old["run_id"]
    assert (cell.recall(1), cell.recall(5)) == (old["recall"]["1"], old["recall"]["5"])


def test_a_shallow_run_alone_shows_no_r5(make_record):
    cell = only_cell(board_of(make_record(ks=(1, 3), k=3)))
    assert cell.recall(1) is not None and cell.recall(5) is None
    assert grid(build_board(read_results())).loc["hog", "corridor"].endswith("/ –")


def test_own_data_named_like_a_benchmark_gets_its_own_column(make_record):
    """0.1: an own folder named "corridor" showed Nordland's numbers under Corridor."""
    benchmark = make_record(quality=0.5, seed=1, created="2026-01-01T00:00:00+00:00")
    own = make_record(kind="own", n_database=111, n_queries=111, quality=1.0, seed=2, fingerprint="ownfolder1",
                      created="2026-03-01T00:00:00+00:00")
    board = board_of(benchmark, own)
    assert only_cell(board).record["run_id"] == benchmark["run_id"]
    [mine] = [c for c in board.columns if c.kind == "own"]
    assert mine.key == f"corridor (own {own['protocol']['hash'][:8]})" and mine.title == "corridor (own data)"
    table = grid(board)
    assert table.loc["hog", "corridor"] == f"{benchmark['recall']['1']:.1f} / {benchmark['recall']['5']:.1f}"
    assert table.loc["hog", "corridor (own data)"] == "100.0 / 100.0"


def test_other_protocol_and_other_copy_never_land_in_the_benchmark_cell(make_record):
    good = [make_record(seed=s, created=f"2026-01-0{s}T00:00:00+00:00") for s in (1, 2)]
    partial = make_record(n_database=110, seed=3, created="2026-02-01T00:00:00+00:00")  # 110 of 111 images
    other_copy = make_record(fingerprint="another-copy", seed=4, created="2026-03-01T00:00:00+00:00")
    board = board_of(*good, partial, other_copy)
    assert only_cell(board).record["run_id"] == good[1]["run_id"]
    reasons = {r["run_id"]: why for r, why in board.excluded}
    assert "110 database images, but protocol corridor:vpr-bench has 111" in reasons[partial["run_id"]]
    assert "another-copy differs from the fp-corridor-111" in reasons[other_copy["run_id"]]


def test_each_protocol_of_a_benchmark_is_its_own_column_and_unknown_ones_none(make_record):
    default = make_record(dataset="vp-air", n_database=12706, n_queries=2706, seed=1)
    variant = make_record(dataset="vp-air", n_database=2706, n_queries=2706, protocol="no-distractors", seed=2,
                          fingerprint="fp-vp-air-2706")
    edited = make_record(seed=3, created="2026-05-01T00:00:00+00:00")
    edited["protocol"] = {**edited["protocol"], "hash": "0123456789abcdef"}  # e.g. another radius
    hand_made = make_record(seed=4)
    hand_made["protocol"] = {"id": "corridor:provisional", "hash": "fedcba9876543210", "provisional": True}
    board = board_of(default, variant, edited, hand_made)
    assert {c.key: (c.protocol, c.default) for c in board.columns} == {
        "vp-air": ("with-distractors", True), "vp-air [no-distractors]": ("no-distractors", False)}
    reasons = {r["run_id"]: why for r, why in board.excluded}
    assert "is none of corridor's: vpr-bench (" in reasons[edited["run_id"]]
    assert "recorded before protocols existed" in reasons[hand_made["run_id"]]


def test_user_weights_get_a_marked_row_and_random_weights_fill_no_cell(make_record):
    official = make_record("cosplace", weights={"source": "official", "url": "https://x"}, seed=1,
                           created="2026-01-01T00:00:00+00:00")
    user = make_record("cosplace", weights={"source": "user", "sha256": "ab" * 32}, quality=1.0, seed=2,
                       created="2026-02-01T00:00:00+00:00")
    random = make_record("cosplace", weights={"source": "random"}, quality=0.0, seed=3,
                         created="2026-03-01T00:00:00+00:00")
    random_option = make_record("anyloc", options={"weights": "random"}, seed=4)
    board = board_of(official, user, random, random_option)
    assert only_cell(board, "cosplace").record["run_id"] == official["run_id"]
    names = {r.name for r in board.rows}
    assert names == {"cosplace", "cosplace † user weights sha256:abababababab"}
    assert board.marked["marked_rows"] == 1
    reasons = {r["run_id"]: why for r, why in board.excluded}
    assert set(reasons) == {random["run_id"], random_option["run_id"]}
    assert all("numbers from random initialisation never fill a cell" in why for why in reasons.values())
    table = grid(board).reset_index()
    assert table.set_index("weights").loc["official", "corridor"].startswith(f"{official['recall']['1']:.1f} /")
    assert set(table["weights"]) == {"official", "user weights sha256:abababababab"}


def test_options_label_rows_and_device_does_not(make_record):
    a = make_record(options={"resize": [64, 64], "device": "cpu"}, seed=1)
    b = make_record(options={"resize": [128, 128]}, seed=2)
    board = board_of(a, b)
    assert {r.label for r in board.rows} == {"hog [resize=64x64]", "hog [resize=128x128]"}


def test_many_records_each_cell_is_the_newest_complete_one(make_record, tmp_path):
    """2,000 stored runs (40 methods x 5 datasets x 10 repeats): 200 cells, each its row's newest run."""
    import json

    from vprbench.evaluation.results import run_folder
    from vprbench.spec import RunSpec

    base = make_record(k=5, ks=(1, 5), n_database=50, n_queries=40, kind="own")  # per-query arrays inline
    template = RunSpec.model_validate(base["spec"])
    for m in range(40):
        for d in range(5):
            protocol = {**base["protocol"], "hash": f"{d:016x}", "id": f"own{d}:own"}
            dataset = template.dataset.model_copy(update={"name": f"own{d}", "protocol_hash": protocol["hash"],
                                                          "protocol_id": protocol["id"]})
            spec = template.model_copy(update={"method": f"m{m}", "dataset": dataset})
            folder = run_folder(protocol["hash"], spec.row_key)
            folder.mkdir(parents=True)
            for repeat in range(10):
                run = f"2026{repeat:02d}01T000000Z-m{m}d{d}"
                record = {**base, "method": f"m{m}", "dataset": f"own{d}", "dataset_fingerprint": f"fp{d}",
                          "protocol": protocol, "spec": spec.to_json(), "spec_key": spec.key, "row_key": spec.row_key,
                          "run_id": run, "created": f"2026-{repeat + 1:02d}-01T00:00:00+00:00"}
                (folder / f"{run}.json").write_text(json.dumps(record))
    records = read_results()
    board = build_board(records)
    assert len(records) == 2000 and len(board.cells) == 200 and len(board.columns) == 5
    assert {c.record["run_id"][:8] for c in board.cells.values()} == {"20260901"}
    assert {c.recall(1) for c in board.cells.values()} == {base["recall"]["1"]}
    assert {c.passed_over for c in board.cells.values()} == {9}


def test_a_vocabulary_fitted_on_the_evaluated_database_is_marked_and_never_nothing_learnt(make_record):
    """dense-vlad with its vocabulary fitted on the database it is evaluated on (transductive) and
    with one fitted elsewhere: two rows, the first marked, neither labelled 'nothing learnt'."""
    from vprbench.leaderboard.shown import weights_shown

    own = make_record("dense-vlad", options={"vocabulary": "map"}, quality=0.9, seed=1)
    foreign = make_record("dense-vlad", options={"vocabulary": "tokyo-pair"}, quality=0.7, seed=2)
    for record, where, leaks in ((own, "the database of corridor", True), (foreign, "2 images in tokyo-pair", False)):
        record["provenance"].update(vocabulary={"source": "fitted", "fitted_on": where, "fitted_on_evaluated_database": leaks},
                                    learnt=["vocabulary"], fitted_on_evaluated_database=leaks)
    hog = make_record("hog", seed=3)
    board = board_of(own, foreign, hog)
    shown = {c.row.name: weights_shown(c.row, c.record) for c in board.cells.values()}
    assert shown == {"dense-vlad [vocabulary=map] † fitted on the evaluated database": "fitted on the evaluated database",
                     "dense-vlad [vocabulary=tokyo-pair]": "vocabulary fitted on 2 images in tokyo-pair",
                     "hog": "none (nothing learnt)"}
    assert board.marked["marked_rows"] == 1
    assert only_cell(board, "dense-vlad [vocabulary=tokyo-pair]").record["run_id"] == foreign["run_id"]


def test_a_stage_on_random_weights_fills_no_cell(make_record):
    """The method's weights are the authors', a re-ranking stage's are random: no cell either."""
    stage = {"name": "patch-mnn", "k": 5, "backbone": "dinov2_vits14", "weights": "random"}
    plain = make_record(seed=1)
    reranked = make_record(stages=[stage], seed=2)
    board = board_of(plain, reranked)
    reasons = {r["run_id"]: why for r, why in board.excluded}
    assert list(reasons) == [reranked["run_id"]]
    assert "numbers from random initialisation never fill a cell" in reasons[reranked["run_id"]]
    assert only_cell(board).record["run_id"] == plain["run_id"]


def test_two_copies_with_as_many_runs_go_to_the_newest_copy(make_record):
    older = make_record(fingerprint="first-copy", seed=1, created="2026-01-01T00:00:00+00:00")
    newer = make_record(fingerprint="second-copy", seed=2, created="2026-02-01T00:00:00+00:00")
    board = board_of(older, newer)
    assert only_cell(board).record["run_id"] == newer["run_id"]
    reasons = {r["run_id"]: why for r, why in board.excluded}
    assert list(reasons) == [older["run_id"]] and "first-copy differs from the second-copy" in reasons[older["run_id"]]


def test_the_python_leaderboard_shows_one_track_at_a_time(make_record):
    """vprbench.leaderboard.leaderboard(records) put a re-ranked run in the single-image table, as the
    command line never does (each track is a table of its own)."""
    from vprbench.errors import VPRBenchError
    from vprbench.leaderboard import leaderboard

    plain, reranked = make_record(seed=1), make_record(stages=[{"name": "aqe", "k": 10}], seed=2)
    with pytest.warns(UserWarning, match="NOT re-scored"):  # rescore=False: said, not silent
        single = leaderboard([plain, reranked], rescore=False)
        again = leaderboard([plain, reranked], rescore=False, track="re-ranked")
    assert list(single.index) == ["hog"]
    assert len(again.index) == 1 and again.index[0] != "hog" and "aqe" in again.index[0]
    with pytest.raises(VPRBenchError, match="track takes one of single-image, re-ranked, sequence; got 'reranked'"):
        leaderboard([plain], rescore=False, track="reranked")
