"""A recall shown at one decimal is the recall's own rounding, and `leaderboard compare` shows the number
the board shows. Expected values by exact arithmetic (fractions.Fraction):
1330 / 2706 = 0.491500369549... -> R@1 49.150037 %, one decimal 49.2; 23 / 80 = 0.2875 exactly -> 28.75 %,
one decimal 28.8 by round-half-even and round-half-up alike; 836 / 1003 = 0.833499501495... -> R@100%P
83.3 %."""
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation import read_results, save_result
from vprbench.evaluation.metrics import kept_metrics, percent_true, top1_precision_recall
from vprbench.leaderboard import build_board
from vprbench.leaderboard.compare import compare, describe
from vprbench.leaderboard.stats import bootstrap_ci, paired_test
from vprbench.leaderboard.tables import fmt, with_ci
from vprbench.text import percent


def _board(*records):
    for record in records:
        save_result(record)
    return build_board(read_results())


def test_a_recall_just_above_a_half_is_not_shown_rounded_down(make_record):
    # seed 34: 1330 of 2706 queries (VP-Air's count) right at R@1; kept to 4 decimals it was 49.15, shown 49.1
    record = make_record("method-a", dataset="own-2706", kind="own", n_database=2706, n_queries=2706, quality=0.4915,
                         seed=34, k=5, ks=(1, 5))
    assert np.count_nonzero(np.asarray(record["per_query"]["first_positive_rank"]) == 1) == 1330
    assert f"{record['recall']['1']:.1f}" == "49.2"
    [cell] = _board(record).cells.values()
    assert fmt(cell.recall(1)) == "49.2"


def test_compare_shows_the_boards_recall(make_record):
    # seeds 8 and 16: 23 and 40 of 80 queries right at R@1; compare printed 28.7 (100 x 23/80 in floats is
    # 28.749999999999996) beside the board's 28.8
    first = make_record("method-a", dataset="own-80", kind="own", n_database=80, n_queries=80, quality=23 / 80, seed=8,
                        k=5, ks=(1, 5))
    second = make_record("method-b", dataset="own-80", kind="own", n_database=80, n_queries=80, quality=0.5, seed=16,
                         k=5, ks=(1, 5))
    assert first["recall"]["1"] == 28.75 and second["recall"]["1"] == 50.0
    board = _board(first, second)
    shown = {cell.row.label: fmt(cell.recall(1)) for cell in board.cells.values()}
    assert shown == {"method-a": "28.8", "method-b": "50.0"}
    result = compare(board, "method-a", "method-b", "own-80")
    assert result["test"]["a"] == 28.75
    lines = describe(result).splitlines()
    assert "R@1  28.8 %" in lines[1] and "R@1  50.0 %" in lines[2], lines


def test_compare_finds_an_own_folder_by_the_path_evaluate_was_given(make_record, tmp_path, monkeypatch):
    """Was: `leaderboard compare A B --dataset ./mydata`, the path `evaluate` took, was 'No run on dataset
    './mydata' fills a cell': the folder is now found by the one its runs' records name."""
    (tmp_path / "mydata").mkdir()
    own = dict(dataset="mycorr", kind="own", n_database=80, n_queries=80, k=5, ks=(1, 5), root=tmp_path / "mydata")
    board = _board(make_record("method-a", quality=23 / 80, seed=8, **own),
                   make_record("method-b", quality=0.5, seed=16, **own))
    monkeypatch.chdir(tmp_path)
    result = compare(board, "method-a", "method-b", "./mydata")
    assert result["dataset"].startswith("mycorr (own") and result["test"]["a"] == 28.75
    with pytest.raises(VPRBenchError, match="No run on dataset './other' fills a cell"):
        compare(board, "method-a", "method-b", "./other")


def test_a_recall_at_full_precision_just_below_a_half_is_not_shown_rounded_up():
    # 1100 top-1 matches by falling similarity: 836 right, 1 wrong, 167 right, 96 wrong: R@100%P = 836 / 1003;
    # kept to 6 decimals it was 0.8335, shown 83.4
    correct = np.r_[np.ones(836), 0, np.ones(167), np.zeros(96)].astype(bool)
    metrics = kept_metrics({1: 0.0}, top1_precision_recall(np.linspace(1, 0, len(correct), endpoint=False), correct))
    assert metrics["recall_at_100_precision"] == 0.8334995
    assert percent(metrics["recall_at_100_precision"]) == "83.3"


def test_recall_at_full_precision_reads_as_a_recall_of_the_same_fraction():
    # 23 (49) of 80 right top-1 matches before the first wrong one: R@100%P 0.2875 (0.6125), shown as an R@1
    # of 23 (49) of 80 queries is, 28.8 (61.2); 100 x the fraction is 28.749999999999996 (61.25000000000001),
    # which showed 28.7 (61.3)
    for right, shown in ((23, "28.8"), (49, "61.2")):
        correct = np.r_[np.ones(right), 0, np.ones(80 - right)].astype(bool)
        metrics = kept_metrics({1: percent_true(np.arange(80) < right)},
                               top1_precision_recall(np.linspace(1, 0, 81, endpoint=False), correct))
        assert metrics["recall_at_100_precision"] == right / 80
        assert percent(metrics["recall_at_100_precision"]) == fmt(metrics["recall"]["1"]) == shown


def test_interval_ends_read_as_the_recalls_they_equal():
    # 31 of 80 queries right: the interval's low end is a resample with 23 right, 28.75 %, shown 28.8 like an R@1
    # of 23 of 80; 100 x (23 / 80) made it 28.749999999999996, shown 28.7. A paired difference's end alike.
    wins = np.arange(80) < 31
    assert with_ci({"value": percent_true(wins), "ci": bootstrap_ci(wins)}) == "38.8 [28.8, 50.0]"
    test = paired_test(np.zeros(80, dtype=bool), np.arange(80) >= 64)  # only B right on 16 of 80
    assert test["ci"][0] == -28.75 and f"{test['ci'][0]:+.1f}" == "-28.8"
