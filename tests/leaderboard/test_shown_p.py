"""The bound shown for a paired-bootstrap p-value of 0 is the least value above 0 that p can take."""
import numpy as np

from vprbench.leaderboard.stats import format_p, format_test, paired_test


def test_a_bootstrap_p_of_zero_is_shown_below_its_least_non_zero_value():
    # p = 2 x (the share of 10,000 resampled differences on the far side of 0): 0, 2/10,000 = 0.0002, 0.0004, ...
    # so 0 means p < 0.0002; "< 0.0001" claimed twice what the resamples can show
    assert format_p(2 / 10_000, 10_000) == "= 0.0002"
    a, b = np.ones(60, bool), np.zeros(60, bool)  # every query only A gets right: no resample reaches 0
    test = paired_test(a, b, seed=0)
    assert test["p_bootstrap"] == 0.0 and test["resamples"] == 10_000
    assert format_p(test["p_bootstrap"], test["resamples"]) == "< 0.0002"
    assert format_test(test) == "< 0.0002"
    assert format_p(0.0, 1_000) == "< 0.002"
