"""Uncertainty of a cell and the difference between two methods, over the same queries.

Recall@K is a mean of per-query successes (0/1). Resampling n queries with replacement
(the nonparametric bootstrap) then gives a number of successes that is exactly
Binomial(n, observed recall), and for two methods on the same queries the four kinds of
query (both right, only A, only B, neither) exactly Multinomial(n, observed shares):
drawing those counts IS the bootstrap, without materialising n x resamples indices, so
11,000 queries x 10,000 resamples take milliseconds. Seeded: the same records give the
same intervals.
"""
from __future__ import annotations

import numpy as np


RESAMPLES = 10_000
LEVEL = 0.95
SEED = 0


def bootstrap_ci(success: np.ndarray, *, seed: int = SEED, resamples: int = RESAMPLES, level: float = LEVEL) -> tuple[float, float]:
    """Percentile bootstrap interval of the recall (percent) over queries."""
    success = np.asarray(success, dtype=bool)
    n = len(success)
    if n == 0:
        return (float("nan"), float("nan"))
    rng = np.random.default_rng(seed)
    draws = rng.binomial(n, success.mean(), size=resamples) / n
    low, high = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2])
    return (float(100 * low), float(100 * high))


def bootstrap_mean_ci(successes_per_dataset: list[np.ndarray], *, seed: int = SEED, resamples: int = RESAMPLES,
                      level: float = LEVEL) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean recall (percent) over several datasets, each
    dataset's queries resampled on their own (a paper table's per-domain average)."""
    rng = np.random.default_rng(seed)
    draws = np.zeros(resamples)
    for success in successes_per_dataset:
        success = np.asarray(success, dtype=bool)
        if len(success) == 0:
            return (float("nan"), float("nan"))
        draws += rng.binomial(len(success), success.mean(), size=resamples) / len(success)
    draws /= len(successes_per_dataset)
    low, high = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2])
    return (float(100 * low), float(100 * high))


def paired_test(a: np.ndarray, b: np.ndarray, *, seed: int = SEED, resamples: int = RESAMPLES,
                level: float = LEVEL) -> dict:
    """A against B on the same queries: the difference of recalls (percentage points) with its
    paired-bootstrap interval and p-value, and McNemar's exact test on the queries they disagree on."""
    from scipy.stats import binomtest

    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"paired test needs the same queries: {a.shape} vs {b.shape}")
    n = len(a)
    counts = np.array([np.sum(a & b), np.sum(a & ~b), np.sum(~a & b), np.sum(~a & ~b)])
    rng = np.random.default_rng(seed)
    draws = rng.multinomial(n, counts / n, size=resamples)
    diff = 100 * (draws[:, 1] - draws[:, 2]) / n
    low, high = np.quantile(diff, [(1 - level) / 2, (1 + level) / 2])
    p_boot = min(1.0, 2 * min(np.mean(diff <= 0), np.mean(diff >= 0))) if counts[1] != counts[2] else 1.0
    discordant = int(counts[1] + counts[2])
    p_mcnemar = binomtest(int(counts[1]), discordant, 0.5).pvalue if discordant else 1.0
    return {
        "queries": n, "a": float(100 * a.mean()), "b": float(100 * b.mean()),
        "difference": float(100 * (counts[1] - counts[2]) / n), "ci": (float(low), float(high)),
        "p_bootstrap": float(p_boot), "only_a": int(counts[1]), "only_b": int(counts[2]),
        "both": int(counts[0]), "neither": int(counts[3]), "p_mcnemar": float(p_mcnemar),
        "resamples": resamples, "seed": seed, "level": level,
    }


def overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def format_p(p: float, resamples: int = RESAMPLES) -> str:
    """A bootstrap p-value of 0 means below the resolution of the resamples, not zero."""
    return f"< {1 / resamples:g}" if p == 0 else f"= {p:.3g}"
