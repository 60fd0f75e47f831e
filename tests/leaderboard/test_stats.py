"""Bootstrap intervals and paired tests: equal to resampling queries explicitly, seeded, and at the
size of the largest query set served (MSLS-val with all its queries: 11,000 x K = 20)."""
import numpy as np
import pytest
from scipy.stats import binomtest

from vprbench.evaluation import per_query, read_results, save_result
from vprbench.leaderboard import build_board
from vprbench.leaderboard.compare import compare, describe
from vprbench.evaluation.metrics import successes
from vprbench.leaderboard.stats import bootstrap_ci, paired_test
from vprbench.leaderboard.tables import cell_stats


def explicit_bootstrap(values, resamples, seed, statistic=np.mean):
    rng = np.random.default_rng(seed)
    n = len(values)
    return np.array([statistic(values[rng.integers(0, n, n)]) for _ in range(resamples)])


def test_interval_equals_resampling_the_queries():
    rng = np.random.default_rng(7)
    wins = rng.random(300) < 0.62
    low, high = bootstrap_ci(wins, seed=1, resamples=20_000)
    draws = 100 * explicit_bootstrap(wins.astype(float), 20_000, seed=2)
    assert low == pytest.approx(np.quantile(draws, 0.025), abs=0.7)
    assert high == pytest.approx(np.quantile(draws, 0.975), abs=0.7)
    assert low < 100 * wins.mean() < high
    assert bootstrap_ci(wins, seed=1) == bootstrap_ci(wins, seed=1)  # seeded: reproducible
    assert bootstrap_ci(wins, seed=1) != bootstrap_ci(wins, seed=3)
    narrow = bootstrap_ci(np.tile(wins, 30), seed=1)
    assert narrow[1] - narrow[0] < (high - low) / 4  # 30x the queries: about 1/sqrt(30) the width


def test_paired_test_equals_resampling_query_pairs_and_mcnemar():
    rng = np.random.default_rng(3)
    a = rng.random(400) < 0.7
    b = np.where(rng.random(400) < 0.8, a, ~a)  # mostly agree
    test = paired_test(a, b, seed=0, resamples=20_000)
    pairs = np.stack([a, b], axis=1).astype(float)
    diffs = 100 * explicit_bootstrap(pairs, 20_000, seed=5, statistic=lambda p: p[:, 0].mean() - p[:, 1].mean())
    assert test["ci"][0] == pytest.approx(np.quantile(diffs, 0.025), abs=0.6)
    assert test["ci"][1] == pytest.approx(np.quantile(diffs, 0.975), abs=0.6)
    assert test["difference"] == pytest.approx(100 * (a.mean() - b.mean()))
    assert test["only_a"] == np.sum(a & ~b) and test["only_b"] == np.sum(~a & b)
    assert test["p_mcnemar"] == pytest.approx(binomtest(test["only_a"], test["only_a"] + test["only_b"]).pvalue)
    same = paired_test(a, a)
    assert same["difference"] == 0 and same["ci"] == (0.0, 0.0) and same["p_mcnemar"] == 1.0 == same["p_bootstrap"]
    with pytest.raises(ValueError, match="same queries"):
        paired_test(a, b[:-1])


def test_msls_size_records_statistics_and_compare(make_record):
    """11,000 queries, K = 20: record, store, read back, intervals, paired test, compare."""
    big = dict(dataset="own-msls", kind="own", n_database=18_871, n_queries=11_000, fingerprint="msls-all")
    a = make_record("method-a", quality=0.70, seed=1, **big)
    b = make_record("method-b", quality=0.68, seed=2, **big)
    assert np.asarray(a["per_query"]["database_indices"]).shape == (11_000, 20)
    for record in (a, b):
        path = save_result(record)
        assert path.stat().st_size < 1_000_000, "the JSON stays small: per-query arrays live in the .npz"
    records = read_results()
    arrays = per_query(records[0])
    assert arrays["database_indices"].shape == (11_000, 20) and arrays["database_indices"].dtype == np.int32
    board = build_board(records)
    [column] = board.columns
    stats = {c.row.label: cell_stats(c) for c in board.column_cells(column)}
    for label, record in (("method-a", a), ("method-b", b)):
        low, high = stats[label][1]["ci"]
        assert low < record["recall"]["1"] < high and high - low < 2.0  # +-0.9 pp at 11,000 queries
    result = compare(board, "method-a", "method-b", "own-msls")
    wins = [successes(np.asarray(r["per_query"]["first_positive_rank"]), 1) for r in (a, b)]
    assert result["test"]["only_a"] == np.sum(wins[0] & ~wins[1])
    text = describe(result)
    assert "11000 queries" in text and "McNemar" in text and "method-a - method-b" in text
