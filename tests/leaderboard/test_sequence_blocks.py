"""A sequence stage makes a query's outcome depend on its window of neighbouring queries: the
bootstrap's blocks cover that window (evaluation/blocks.py), in the record and again on the board,
a paired comparison with a single-image run draws the same, longer blocks for both, and a plain
run's intervals are the numbers they were before."""
import numpy as np
import pytest

from vprbench.evaluation import read_results, save_result
from vprbench.evaluation.blocks import Resampling, block_length, for_record, query_window, record_window
from vprbench.leaderboard import build_board
from vprbench.leaderboard.compare import compare, describe
from vprbench.leaderboard.stats import bootstrap_ci, paired_test

DIAGONAL = {"name": "diagonal", "length": 10}


def test_the_window_is_the_span_of_the_queries_a_score_reads():
    assert query_window([]) == 1 and query_window(None) == 1
    assert query_window([{"name": "aqe", "options": {}}]) == 1                       # re-ranking reads no neighbour
    assert query_window([{"name": "diagonal", "options": {"length": 5, "mode": "causal"}}]) == 5   # t-4 .. t
    assert query_window([{"name": "diagonal", "options": {"length": 4, "mode": "offline"}}]) == 4  # t-1 .. t+2
    assert query_window([{"name": "seqslam", "options": {}}]) == 10                  # OpenSeqSLAM's default length
    assert query_window([{"name": "diagonal", "options": {"length": "ten"}}]) == 10  # an edited record: the defaults
    assert query_window([{"name": "a-plugin-gone", "options": {"length": 7}}]) == 7
    # 2r + w: with r = 2 and a window of 10 on Corridor's 111 queries
    assert block_length(111, 2, 10) == 14 and block_length(111, 2) == 5 and block_length(20, 2, 30) == 20


@pytest.mark.parametrize("mode", ["offline", "causal"])
def test_a_sequence_record_gets_blocks_covering_its_window(make_record, mode):
    record = make_record("a", "corridor", stages=[{**DIAGONAL, "mode": mode}])
    assert record["track"] == "sequence" and record_window(record) == 10
    stated = record["resampling"]
    assert stated["block_length"] == 14 >= 10 and stated["query_window"] == 10 and stated["blocks_per_resample"] == 8
    found = for_record(record, None)
    assert found.block_length == 14 and "covering a sequence window of 10" in found.text()
    record["resampling"]["block_length"] = 5  # a stored length (an older record's) is not what is drawn
    assert for_record(record, None).block_length == 14
    nordland = make_record("a", "nordland", stages=[{"name": "seqslam", "length": 20}])
    assert nordland["resampling"]["block_length"] == 22  # 2 * 1 + 20 beats round(2760^(1/3)) = 14


def test_a_sequence_run_on_places_keeps_the_places(make_record):
    plain, sequence = make_record("a", "st-lucia"), make_record("a", "st-lucia", stages=[DIAGONAL])
    assert sequence["resampling"] == plain["resampling"]
    assert sequence["per_query"]["place"] == plain["per_query"]["place"]


def test_a_sequence_run_and_a_plain_run_are_paired_over_the_same_longer_blocks(make_record):
    a = make_record("method-a", "corridor", quality=0.7, seed=1)
    b = make_record("method-b", "corridor", quality=0.5, seed=2, stages=[DIAGONAL])
    for record in (a, b):
        save_result(record)
    board = build_board(read_results())
    result = compare(board, "method-a", "method-b + diagonal", "corridor")
    units = result["resampling"]
    assert units.scheme == "blocks" and units.block_length == 14
    assert result["test"]["resampling"]["block_length"] == 14
    wins = [np.asarray(r["per_query"]["first_positive_rank"]) == 1 for r in (a, b)]
    longer = Resampling("blocks", 111, block_length=14)
    assert result["test"]["ci"] == paired_test(*wins, longer)["ci"]
    assert result["intervals"] == [bootstrap_ci(w, longer) for w in wins]  # the plain run's too
    assert result["test"]["ci"] != paired_test(*wins, Resampling("blocks", 111, block_length=5))["ci"]
    assert "blocks of 14 consecutive queries" in describe(result)


def test_a_plain_runs_intervals_are_unchanged():
    """The numbers these records gave before sequence windows were covered, bit for bit (since resamples are
    100 x sum / count, rounded once: stats.resample_means; before, some ends were a last bit off)."""
    rng = np.random.default_rng(0)
    a, b = rng.random(111) < 0.6, rng.random(111) < 0.5
    record = {"counts": {"queries": 111}, "ground_truth": {"unit": "positives", "radius": 2, "radius_unit": "frames"},
              "spec": {"stages": [{"name": "aqe", "options": {}}]}}
    units = for_record(record, None)
    assert units.block_length == 5 and "query_window" not in units.describe()
    assert bootstrap_ci(a, units, seed=0) == (41.81818181818182, 60.90909090909091)
    assert paired_test(a, b, units, seed=0)["ci"] == (-6.363636363636363, 17.272727272727273)
    own = {"counts": {"queries": 300}, "ground_truth": {"unit": "frames", "radius": 3, "radius_unit": "frames"},
           "resampling": {"block_length": 6}}
    units = for_record(own, None)
    assert units.block_length == 7 and bootstrap_ci(rng.random(300) < 0.4, units, seed=3) == \
        (29.568106312292358, 40.199335548172755)


def test_verify_derives_a_sequence_records_units_from_its_stages(make_record):
    from synthetic_runs import synthetic_ground_truth

    from vprbench.evaluation.rescore import Truth, rescore
    from vprbench.evaluation import per_query

    order = np.random.default_rng(0).permutation(111)  # a protocol whose queries are listed out of frame order
    protocol_units = Resampling("blocks", 111, 5, order=order, radius=2, unit="frames", radius_steps=2.0)
    truth = Truth("corridor:vpr-bench", 111, synthetic_ground_truth(111, 111, "positives", 2).positives(),
                  protocol_units)
    record = make_record("a", "corridor", stages=[{**DIAGONAL, "mode": "causal"}])
    arrays = {**per_query(record), "order": order.astype(np.int32)}
    problems = []
    rescore(record, arrays, truth, problems)
    assert problems == []  # blocks of 14 in the protocol's order: its units
    rescore(record, {**arrays, "order": np.arange(111, dtype=np.int32)}, truth, problems)  # another order: refused
    assert len(problems) == 1 and "(blocks of 14 consecutive queries, covering a sequence window of 10) are not" \
        in problems[0]


def test_a_page_names_each_runs_block_length(make_record):
    from types import SimpleNamespace

    from vprbench.leaderboard.site import _units

    runs = [make_record("a", "corridor", stages=[{"name": "diagonal", "length": n}]) for n in (10, 3)]
    cells = [SimpleNamespace(record=r, arrays=None) for r in runs]
    assert _units(cells).startswith("blocks of 7, 14 consecutive queries (per run, by its sequence window): "
                                    "circular blocks")
    assert _units(cells[:1]).startswith("blocks of 14 consecutive queries, covering a sequence window of 10: ")
