import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation.metrics import (correct_at, first_positive_rank, ks_within_database, recall_at_k,
                                         top1_precision_recall)
from vprbench.search.exact import SCORE_TOLERANCE, search


def test_search_ranks_by_inner_product():
    db = np.eye(4, dtype=np.float32)
    q = np.array([[0.1, 0.9, 0.3, 0.0]], dtype=np.float32)
    scores, idx = search(db, q, 3)
    assert idx.tolist() == [[1, 2, 0]]
    np.testing.assert_allclose(scores, [[0.9, 0.3, 0.1]], rtol=0, atol=SCORE_TOLERANCE)  # scores on the stated grid


def test_recall_counts_queries_without_positives_as_failures():
    indices = np.array([[0, 1, 2], [2, 0, 1], [1, 2, 0], [0, 1, 2]])
    positives = [np.array([0]), np.array([1]), np.array([0, 5]), np.array([], dtype=np.int64)]
    # q0 hit at 1; q1 at 3; q2 at 3; q3 never (no positives)
    first = first_positive_rank(correct_at(indices, positives))
    assert first.tolist() == [1, 3, 3, 0]
    assert recall_at_k(first, (1, 2, 3)) == {1: 25.0, 2: 25.0, 3: 75.0}
    assert recall_at_k(np.zeros(0, dtype=int), (1,)) == {1: 0.0}


def test_precision_recall_follows_vpr_bench():
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    correct = np.array([True, True, False, True])
    pr = top1_precision_recall(scores, correct)
    # the two most confident matches are right: precision 1 up to recall 2/3
    assert pr["recall_at_100_precision"] == pytest.approx(2 / 3)
    # trapezoids over recall 0 -> 1/3 -> 2/3 at precision 1, then 2/3 -> 1 from 2/3 to 3/4
    assert pr["auc_pr"] == pytest.approx(2 / 3 + (2 / 3 + 3 / 4) / 2 / 3, abs=1e-9)
    # F1 is 0.8 at (P 1, R 2/3) and 6/7 at (P 3/4, R 1): the largest is taken
    assert pr["max_f1"] == pytest.approx(6 / 7, abs=1e-9)


def test_precision_recall_thresholds_tied_scores_together_and_counts_queries_without_positives_as_wrong():
    # as VPR-Bench (sklearn's curve over each query's best score): the two top matches tie at 0.9, one wrong,
    # so no threshold has precision 1; queries without positives are wrong matches, and recall is over the
    # 2 correct matches (not the 5 queries): accepting all is recall 1, precision 2/5
    scores = np.array([0.9, 0.9, 0.5, 0.4, 0.3])
    correct = correct_at(np.array([[0], [1], [2], [3], [4]]), [np.array([0]), np.array([]), np.array([2]),
                                                               np.array([], dtype=np.int64), np.array([7])])[:, 0]
    pr = top1_precision_recall(scores, correct)
    assert pr["recall_at_100_precision"] == 0.0
    assert pr["max_f1"] == pytest.approx(2 * (2 / 3) * 1 / (2 / 3 + 1))  # P 2/3, R 1 at threshold 0.5
    # trapezoids: (R 0, P 1) -> (1/2, 1/2) -> (1, 2/3); lower thresholds stay at recall 1
    assert pr["auc_pr"] == pytest.approx((1 + 1 / 2) / 4 + (1 / 2 + 2 / 3) / 4)


def test_most_confident_match_wrong_gives_zero_recall_at_full_precision():
    pr = top1_precision_recall(np.array([0.9, 0.5]), np.array([False, True]))
    assert pr["recall_at_100_precision"] == 0.0
    assert pr["max_f1"] == pytest.approx(2 / 3)  # everything accepted: P 1/2, R 1


@pytest.mark.parametrize("ks", [(0,), (-1, 5), (), (200,)])
def test_invalid_k_is_refused(ks):
    with pytest.raises(VPRBenchError):
        ks_within_database(ks, 100)


def test_ks_sorted_and_unique():
    assert ks_within_database([5, 1, 5], 10) == (1, 5)


def test_k_beyond_a_database_of_one_image_is_said_in_the_singular():
    with pytest.raises(VPRBenchError, match=r"^K = 5 exceeds the 1 database image of own: give --k with values up to 1"):
        ks_within_database([1, 5], 1, "own")


def test_k_equal_to_the_database_is_kept_and_one_more_is_refused():
    assert ks_within_database([1, 10], 10) == (1, 10)
    with pytest.raises(VPRBenchError, match=r"^K = 11 exceeds the 10 database images"):
        ks_within_database([1, 11], 10)


def test_pr_thresholds_merge_best_matches_on_one_grid_point_not_all_within_one_step():
    # the PR metrics rank the search's scores on its grid of 2^-16: a right and a wrong best match
    # merge into one threshold only when they round to the same point. HOG on Corridor has a pair
    # 7e-6 apart that does and one 1.0e-5 apart (< 2^-16) that does not; docs/evaluation.md said
    # "within 2^-16 of each other are one threshold", which the second pair contradicts
    from pathlib import Path

    from vprbench.search.exact import rounded_scores

    g = SCORE_TOLERANCE
    correct = np.array([True, False, True])
    apart = rounded_scores(np.array([(52000 - 0.2) * g, (52000 - 0.86) * g, 0.5]))  # 1.0e-5 apart, a boundary between
    assert apart[0] - apart[1] == g
    assert top1_precision_recall(apart, correct)["recall_at_100_precision"] == pytest.approx(0.5, abs=1e-12)
    merged = rounded_scores(np.array([(52000 + 0.2) * g, (52000 - 0.27) * g, 0.5]))  # 7.2e-6 apart, one grid point
    assert merged[0] == merged[1]
    assert top1_precision_recall(merged, correct)["recall_at_100_precision"] == 0.0
    doc = " ".join((Path(__file__).resolve().parents[1] / "docs" / "evaluation.md").read_text().split())
    assert "best matches within 2^-16 of each other are one threshold" not in doc
    assert "round to the same multiple of 2^-16 are one threshold" in doc
