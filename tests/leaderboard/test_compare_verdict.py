"""`leaderboard compare` calls a difference by the interval it shows, so the two never contradict."""
from types import SimpleNamespace

import numpy as np

from vprbench.leaderboard.cells import MEASURED
from vprbench.leaderboard.compare import describe
from vprbench.leaderboard.stats import bootstrap_ci, paired_test, per_query


def _pair():
    # 60 queries, 12 only A gets right, 4 only B: with seed 1, exactly 2.5 % of the resampled differences
    # are <= 0, so p = 0.05 while the interpolated 95 % interval is [+1.6, +26.7]
    a, b = np.zeros(60, bool), np.zeros(60, bool)
    a[:12], b[12:16] = True, True
    return a, b


def test_a_difference_whose_interval_excludes_zero_is_called_one():
    a, b = _pair()
    test = paired_test(a, b, seed=1)
    assert round(test["ci"][0], 3) == 1.625 and test["p_bootstrap"] == 0.05
    assert test["significant"] is True
    cells = [SimpleNamespace(row=SimpleNamespace(name=n), record={"run_id": n}, source=MEASURED) for n in ("A", "B")]
    wins = (a, b)
    result = {"dataset": "d", "k": 1, "cells": cells, "intervals": [bootstrap_ci(w, seed=1) for w in wins],
              "overlap": True, "test": test, "resampling": per_query(60),
              "per_query": {"intervals": [bootstrap_ci(w, seed=1) for w in wins], "test": test}}
    text = describe(result)
    assert "95 % CI [+1.6, +26.7]" in text
    assert "A difference at the 5 % level" in text and "No difference" not in text
    assert "excludes 0" in text


def test_an_interval_that_holds_zero_is_no_difference():
    a, b = np.zeros(60, bool), np.zeros(60, bool)
    a[:7], b[7:12] = True, True  # 7 only A, 5 only B
    test = paired_test(a, b, seed=0)
    assert test["ci"][0] < 0 < test["ci"][1] and test["significant"] is False


def test_the_verdict_names_its_units_in_words_that_read_for_every_scheme():
    """The verdict's units read after "resampled": 'over by place (...)' or 'over per query' did not."""
    from vprbench.evaluation.blocks import Resampling

    a, b = np.zeros(60, bool), np.zeros(60, bool)
    a[:7], b[7:12] = True, True
    cells = [SimpleNamespace(row=SimpleNamespace(name=n), record={"run_id": n}, source=MEASURED) for n in ("A", "B")]
    for units, said in ((per_query(60), "resampled per query,"),
                        (Resampling("places", 60, places=np.arange(60) // 3, radius=25), "resampled by place (20 places")):
        test = paired_test(a, b, units, seed=0)
        result = {"dataset": "d", "k": 1, "cells": cells, "intervals": [bootstrap_ci(w, units, seed=0) for w in (a, b)],
                  "overlap": True, "test": test, "resampling": units,
                  "per_query": {"intervals": [bootstrap_ci(w, seed=0) for w in (a, b)], "test": paired_test(a, b, seed=0)}}
        verdict = describe(result).splitlines()[-1]
        assert f"(the paired-bootstrap interval, {said}" in verdict and "over by" not in verdict \
            and "over per" not in verdict, verdict
