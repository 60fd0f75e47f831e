"""Uncertainty of a cell and the difference between two methods, over the same queries.

Recall@K is a mean of per-query successes (0/1). The bootstrap resamples units of queries with
replacement: single queries, blocks of consecutive queries along a traverse, or places
(`vprbench/evaluation/blocks.py` says which, and why). A resample is then fixed by how many times
each kind of unit was drawn (kind = its query count and its successes, per method), and those
counts are exactly Multinomial(draws, shares of each kind): drawing them IS the bootstrap,
without materialising resamples x units indices, so 11,000 queries x 10,000 resamples take
milliseconds. Seeded: the same records give the same intervals. A paired test draws the same
units for both methods.
"""
from __future__ import annotations

import hashlib
from numbers import Integral

import numpy as np

from ..errors import VPRBenchError
from ..evaluation.blocks import Resampling
from ..evaluation.metrics import percent_true

RESAMPLES = 10_000
LEVEL = 0.95
SEED = 0
#: intervals already drawn, by the successes, the units, the seed and the resamples
_INTERVALS: dict[tuple, tuple[float, float]] = {}


def check_k_and_seed(k, seed) -> tuple[int, int]:
    """The K of Recall@K compared (>= 1) and the bootstrap's seed (>= 0), as whole numbers: R@0,
    R@-1 or R@1.5 would compare nothing without a word, and a bad seed was a numpy traceback."""
    wrong = [f"--{name} takes a whole number >= {least} ({what}); got {value!r}"  # only what was wrong: --k may be unset
             for name, value, least, what in (("k", k, 1, "the K of Recall@K compared"), ("seed", seed, 0, "the bootstrap's"))
             if not (isinstance(value, Integral) and not isinstance(value, bool) and value >= least)]
    if wrong:
        raise VPRBenchError("; ".join(wrong) + ".")
    return int(k), int(seed)


def per_query(n: int) -> Resampling:
    return Resampling("queries", n)


def resample_means(values: np.ndarray, resampling: Resampling | None, rng: np.random.Generator,
                   resamples: int = RESAMPLES) -> np.ndarray:
    """(resamples, c): the mean of each column of `values` (queries x c, whole numbers) over the
    queries of each bootstrap resample, in percent: 100 x sum / count, rounded once like a recall
    (metrics.percent_true); 100 x (sum / count) put an interval's end at 23 / 80 as 28.749999999999996,
    shown 28.7 beside a recall of 23 / 80 shown 28.8."""
    values = np.asarray(values).reshape(len(values), -1)
    sizes, sums, draws = (resampling or per_query(len(values))).units(values)
    kinds, counts = np.unique(np.column_stack([sizes, sums]), axis=0, return_counts=True)
    # the multinomial counts of each kind, one kind at a time (the binomial of what is left),
    # each draw vectorised over the resamples: exact, and fast for hundreds of kinds
    drawn = np.empty((resamples, len(kinds)), dtype=np.int64)
    left = np.full(resamples, draws, dtype=np.int64)
    rest = int(counts.sum())
    for i, count in enumerate(counts[:-1]):
        drawn[:, i] = rng.binomial(left, min(1.0, count / rest))
        left -= drawn[:, i]
        rest -= int(count)
    drawn[:, -1] = left
    totals = drawn @ kinds
    return 100 * totals[:, 1:] / np.maximum(totals[:, :1], 1)


def _interval(draws: np.ndarray, level: float) -> tuple[float, float]:
    low, high = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2])
    return (float(low), float(high))


def bootstrap_ci(success: np.ndarray, resampling: Resampling | None = None, *, seed: int = SEED,
                 resamples: int = RESAMPLES, level: float = LEVEL) -> tuple[float, float]:
    """Percentile bootstrap interval of the recall (percent); `resampling` None: per query."""
    success = np.asarray(success, dtype=bool)
    if len(success) == 0:
        return (float("nan"), float("nan"))
    units = resampling or per_query(len(success))
    key = (hashlib.sha256(np.packbits(success).tobytes()).hexdigest(), len(success), units.key(), seed, resamples, level)
    if key not in _INTERVALS:  # a published board asks for one cell's interval from several tables
        draws = resample_means(success, units, np.random.default_rng(seed), resamples)[:, 0]
        if len(_INTERVALS) > 10_000:
            _INTERVALS.clear()
        _INTERVALS[key] = _interval(draws, level)
    return _INTERVALS[key]


def bootstrap_mean_ci(successes_per_dataset: list[np.ndarray], resamplings: list | None = None, *, seed: int = SEED,
                      resamples: int = RESAMPLES, level: float = LEVEL) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean recall (percent) over several datasets, each
    dataset's queries resampled on their own (a paper table's per-domain average)."""
    rng = np.random.default_rng(seed)
    draws = np.zeros(resamples)
    for success, resampling in zip(successes_per_dataset, resamplings or [None] * len(successes_per_dataset)):
        success = np.asarray(success, dtype=bool)
        if len(success) == 0:
            return (float("nan"), float("nan"))
        draws += resample_means(success, resampling, rng, resamples)[:, 0]
    return _interval(draws / len(successes_per_dataset), level)


def paired_test(a: np.ndarray, b: np.ndarray, resampling: Resampling | None = None, *, seed: int = SEED,
                resamples: int = RESAMPLES, level: float = LEVEL) -> dict:
    """A against B on the same queries: the difference of recalls (percentage points) with its
    paired-bootstrap interval and p-value (the same units drawn for both), and McNemar's exact
    test on the queries they disagree on (which takes the queries as independent). With no query
    they disagree on ("identical": e.g. one method with a float16 store), there is nothing to test:
    its p-values are 1 and pages show "same queries right" instead (`format_test`)."""
    from scipy.stats import binomtest

    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"paired test needs the same queries: {a.shape} vs {b.shape}")
    n = len(a)
    counts = np.array([np.sum(a & b), np.sum(a & ~b), np.sum(~a & b), np.sum(~a & ~b)])
    # the difference alone is resampled: units of one size and one difference are one kind
    diff = resample_means(a.astype(np.int64) - b, resampling, np.random.default_rng(seed), resamples)[:, 0]
    low, high = _interval(diff, level)
    p_boot = min(1.0, 2 * min(np.mean(diff <= 0), np.mean(diff >= 0))) if counts[1] != counts[2] else 1.0
    discordant = int(counts[1] + counts[2])
    p_mcnemar = binomtest(int(counts[1]), discordant, 0.5).pvalue if discordant else 1.0
    return {
        "queries": n, "a": percent_true(a), "b": percent_true(b),
        "difference": float(100 * (counts[1] - counts[2]) / n), "ci": (low, high),
        "p_bootstrap": float(p_boot), "only_a": int(counts[1]), "only_b": int(counts[2]),
        "both": int(counts[0]), "neither": int(counts[3]), "p_mcnemar": float(p_mcnemar),
        "resamples": resamples, "seed": seed, "level": level,
        "resampling": (resampling or per_query(n)).describe(), "identical": discordant == 0,
        # called a difference when the shown interval excludes 0: the p-value can sit at 0.05 while
        # the interpolated interval already excludes 0, and the verdict must not contradict it
        "significant": bool(low > 0 or high < 0),
    }


def overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def format_p(p: float, resamples: int = RESAMPLES) -> str:
    """A bootstrap p-value of 0 means below the resolution of the resamples, not zero: the p-value is
    twice a tail's share of the resamples, so its least value above 0 is 2 / resamples."""
    return f"< {2 / resamples:g}" if p == 0 else f"= {p:.3g}"


#: what a paired test between runs with the same success on every query shows instead of p = 1
IDENTICAL = "same queries right"


def format_test(test: dict) -> str:
    """A paired test's bootstrap p-value as shown ('0.034', '< 0.0002'), or IDENTICAL when the two
    runs succeed on exactly the same queries: no test is meaningful then, and p = 1 would read as one."""
    return IDENTICAL if test.get("identical") else format_p(test["p_bootstrap"], test.get("resamples", RESAMPLES)).lstrip("= ")
