"""Intervals that respect correlated queries: blocks along a traverse, places for geo-tagged queries.

The counting shortcut of stats.py is checked against resampling the units explicitly; a strongly
correlated sequence gets a wider interval by blocks than by queries; places are right on a tiny
example; a record keeps its units and the leaderboard draws the same ones for both runs of a
comparison."""
import numpy as np
import pytest

from vprbench.evaluation import per_query, read_results, save_result
from vprbench.evaluation.blocks import Resampling, block_length, for_dataset, for_record, place_groups
from vprbench.leaderboard import build_board
from vprbench.leaderboard.compare import compare, describe
from vprbench.leaderboard.stats import bootstrap_ci, paired_test


def correlated(n=600, run=30, seed=0, rate=0.6):
    """Successes in runs of `run` consecutive queries (a traverse where neighbours fail together)."""
    rng = np.random.default_rng(seed)
    return np.repeat(rng.random(n // run + 1) < rate, run)[:n]


def explicit_blocks(values, length, resamples, seed):
    """The circular block bootstrap by hand: round(n / L) random starts, L queries from each."""
    rng = np.random.default_rng(seed)
    n = len(values)
    blocks = max(1, round(n / length))
    starts = rng.integers(0, n, size=(resamples, blocks))
    picked = (starts[:, :, None] + np.arange(length)) % n
    return values[picked].reshape(resamples, -1, *values.shape[1:]).mean(axis=1)


def test_block_rule():
    assert block_length(111, 2) == 5      # Corridor: round(111^(1/3)) = 5 = 2 * 2 + 1
    assert block_length(2760, 1) == 14    # Nordland: the n^(1/3) term
    assert block_length(200, 10) == 21    # a wide positive window wins
    assert block_length(3, 10) == 3       # never longer than the queries
    assert block_length(1000, 0) == 10


def test_block_interval_equals_resampling_blocks_and_is_wider_on_a_correlated_sequence():
    wins = correlated()
    units = Resampling("blocks", len(wins), block_length=40)
    low, high = bootstrap_ci(wins, units, seed=1, resamples=20_000)
    draws = 100 * explicit_blocks(wins.astype(float), 40, 20_000, seed=2)
    assert low == pytest.approx(np.quantile(draws, 0.025), abs=1.0)
    assert high == pytest.approx(np.quantile(draws, 0.975), abs=1.0)
    q_low, q_high = bootstrap_ci(wins, seed=1)
    assert (high - low) > 2.5 * (q_high - q_low)  # runs of 30: about sqrt(30) wider; per query is far too narrow
    # on independent queries, blocks change little
    rng = np.random.default_rng(5)
    free = rng.random(600) < 0.6
    b_low, b_high = bootstrap_ci(free, Resampling("blocks", 600, block_length=40), seed=1)
    f_low, f_high = bootstrap_ci(free, seed=1)
    assert abs((b_high - b_low) - (f_high - f_low)) < 0.25 * (f_high - f_low)


def test_seeded():
    wins = correlated()
    units = Resampling("blocks", len(wins), block_length=9)
    assert bootstrap_ci(wins, units, seed=4) == bootstrap_ci(wins, units, seed=4)
    assert bootstrap_ci(wins, units, seed=4) != bootstrap_ci(wins, units, seed=5)
    b = correlated(seed=3)
    assert paired_test(wins, b, units, seed=4) == paired_test(wins, b, units, seed=4)


def test_paired_blocks_equal_resampling_the_same_blocks_for_both():
    a = correlated(seed=1)
    b = np.where(np.random.default_rng(2).random(len(a)) < 0.85, a, correlated(seed=7))
    units = Resampling("blocks", len(a), block_length=30)
    test = paired_test(a, b, units, seed=0, resamples=20_000)
    diffs = explicit_blocks(np.stack([a, b], axis=1).astype(float), 30, 20_000, seed=9)
    diffs = 100 * (diffs[:, 0] - diffs[:, 1])
    assert test["ci"][0] == pytest.approx(np.quantile(diffs, 0.025), abs=1.0)
    assert test["ci"][1] == pytest.approx(np.quantile(diffs, 0.975), abs=1.0)
    assert test["resampling"]["scheme"] == "blocks" and test["resampling"]["block_length"] == 30
    plain = paired_test(a, b, seed=0)
    assert test["ci"][1] - test["ci"][0] > 1.5 * (plain["ci"][1] - plain["ci"][0])


def test_places_on_a_tiny_example():
    # three clumps along a road, one query alone; radius 10 m
    positions = np.array([[0, 0], [4, 0], [100, 0], [9, 0], [104, 3], [300, 0], [18, 0]], dtype=float)
    places = place_groups(positions, 10)
    # query 0 founds place 0 with 1 and 3 (within 10 m of it); 6 is 18 m from 0, so it founds its own
    assert places.tolist() == [0, 0, 1, 0, 1, 2, 3]
    assert place_groups(positions[:0], 10).tolist() == []
    # exactly at the radius counts, as for positives
    assert place_groups(np.array([[0.0], [10.0]]), 10).tolist() == [0, 0]


def test_place_interval_equals_resampling_places():
    rng = np.random.default_rng(0)
    places = np.repeat(np.arange(60), rng.integers(1, 12, 60))
    wins = np.repeat(rng.random(60) < 0.55, np.bincount(places))
    units = Resampling("places", len(wins), places=places, radius=25)
    low, high = bootstrap_ci(wins, units, seed=0, resamples=20_000)
    rng = np.random.default_rng(3)
    members = [np.flatnonzero(places == p) for p in range(60)]
    draws = []
    for _ in range(20_000):
        chosen = np.concatenate([members[p] for p in rng.integers(0, 60, 60)])
        draws.append(100 * wins[chosen].mean())
    assert low == pytest.approx(np.quantile(draws, 0.025), abs=1.2)
    assert high == pytest.approx(np.quantile(draws, 0.975), abs=1.2)


def test_units_from_the_ground_truth(make_record):
    from vprbench.datasets import dataset_manifest  # noqa: F401 - the benchmarks' rules below

    corridor = make_record("a", "corridor")
    assert corridor["resampling"]["scheme"] == "blocks" and corridor["resampling"]["block_length"] == 5
    assert "place" not in corridor["per_query"] and "order" not in corridor["per_query"]
    st_lucia = make_record("a", "st-lucia")
    assert st_lucia["resampling"]["scheme"] == "places"
    places = np.asarray(st_lucia["per_query"]["place"])
    assert places.shape == (1464,) and st_lucia["resampling"]["places"] == places.max() + 1 < 1464
    nardo = make_record("a", "nardo-air")  # positive lists in metres, no positions: nothing says who is near whom
    assert nardo["resampling"]["scheme"] == "queries"
    # stored, read back, derived again from the record (never from its stated length)
    path = save_result(st_lucia)
    [stored] = read_results(path.parents[3])
    arrays = per_query(stored)
    assert np.array_equal(arrays["place"], places)
    assert for_record(stored, arrays).same_as(Resampling("places", 1464, places=places))
    corridor["resampling"]["block_length"] = 1  # a record edited to narrow its intervals
    assert for_record(corridor, None).block_length == 5


def test_frames_out_of_order_are_blocked_in_frame_order():
    from vprbench.datasets.model import Dataset, GroundTruth

    frames = np.array([3, 0, 2, 1, 5, 4], dtype=float)[:, None]
    gt = GroundTruth("frames", radius=0, database_positions=frames, query_positions=frames)
    data = Dataset("d", [], [f"q{i}" for i in range(6)], gt, radius_unit="frames")
    found = for_dataset(data)
    assert found.scheme == "blocks" and found.order.tolist() == [1, 3, 2, 0, 5, 4]
    sizes, sums, draws = found.units(np.arange(6)[:, None])
    # block of 2 (round(6^(1/3)) = 2) starting at frame 0 holds queries 1 and 3
    assert found.block_length == 2 and sums[0, 0] == 1 + 3 and draws == 3


def test_hostile_units_in_a_record_are_not_used(make_record):
    record = make_record("a", "st-lucia")
    arrays = {"first_positive_rank": np.asarray(record["per_query"]["first_positive_rank"])}
    for bad in (np.arange(5), np.full(1464, -1), np.full(1464, 7), np.arange(1464) + 1, np.zeros(1464, float)):
        assert for_record(record, {**arrays, "place": bad}).scheme == "queries"
    assert for_record(record, {**arrays, "place": np.zeros(1464, np.int32)}).place_count == 1


def test_compare_pairs_the_same_blocks_and_shows_per_query_beside(make_record, tmp_path):
    a = make_record("method-a", "corridor", quality=0.7, seed=1)
    b = make_record("method-b", "corridor", quality=0.5, seed=2)
    for record in (a, b):
        save_result(record)
    board = build_board(read_results())
    result = compare(board, "method-a", "method-b", "corridor")
    assert result["resampling"].scheme == "blocks" and result["test"]["resampling"]["block_length"] == 5
    wins = [np.asarray(r["per_query"]["first_positive_rank"]) == 1 for r in (a, b)]
    assert result["test"]["ci"] == paired_test(*wins, result["resampling"])["ci"]
    assert result["per_query"]["test"]["ci"] == paired_test(*wins)["ci"]
    text = describe(result)
    assert "blocks of 5 consecutive queries" in text and "per query [" in text


def test_verify_refuses_units_that_are_not_the_protocols(make_record):
    from synthetic_runs import synthetic_ground_truth

    from vprbench.evaluation.rescore import Truth, rescore

    record = make_record("a", "st-lucia")
    gt = synthetic_ground_truth(1549, 1464, "metres", 25)  # the fixture's ground truth
    truth = Truth("st-lucia:vg-benchmark", 1549, gt.positives(),
                  Resampling("places", 1464, places=place_groups(gt.query_positions, 25), radius=25))
    arrays = per_query(record)
    problems = []
    rescore(record, arrays, truth, problems)
    assert problems == []
    narrowed = {**arrays, "place": np.arange(1464, dtype=np.int32)}  # every query its own place: narrower intervals
    assert for_record(record, narrowed).place_count == 1464
    rescore(record, narrowed, truth, problems)
    assert len(problems) == 1 and "its bootstrap units (by place (1,464 places" in problems[0] \
        and "are not those of protocol st-lucia:vg-benchmark" in problems[0]


def test_verify_refuses_a_current_record_without_the_unit_arrays_its_units_need(make_record):
    """Records before unit arrays existed kept none (and no `resampling`): checked as before. One that
    states its resampling but drops the places its units need would have its intervals drawn per query."""
    from synthetic_runs import synthetic_ground_truth

    from vprbench.evaluation.rescore import Truth, rescore

    record = make_record("a", "st-lucia")
    gt = synthetic_ground_truth(1549, 1464, "metres", 25)
    truth = Truth("st-lucia:vg-benchmark", 1549, gt.positives(),
                  Resampling("places", 1464, places=place_groups(gt.query_positions, 25), radius=25))
    dropped = {k: v for k, v in per_query(record).items() if k != "place"}
    assert record["resampling"]["scheme"] == "places"
    problems = []
    rescore(record, dropped, truth, problems)
    assert len(problems) == 1 and "its bootstrap units (per query" in problems[0], problems
    older = {k: v for k, v in record.items() if k != "resampling"}  # as written before unit arrays
    problems = []
    rescore(older, dropped, truth, problems)
    assert problems == []
