"""Sequence matching on a block of a query-by-database cost matrix (both splits in traverse order).

A query is matched with its neighbours in the query traverse: for a database image d, the cost
of a trajectory is the mean of the costs C[t + k, d + o(k)] over the query offsets k of the
window (offline: centred on the query; causal: the query and the frames before it) and the
database offsets o(k) = round(v * k) of a velocity v. The score of (t, d) is the best
trajectory's. Where a trajectory leaves either traverse its missing terms are dropped (the
mean is over the terms that exist; the k = 0 term always does), so every query is matched,
the ends of a traverse with shorter sequences.

SeqSLAM (Milford & Wyeth, ICRA 2012) with the defaults of OpenSeqSLAM (Sünderhauf et al., ICRA
workshops 2013; MATLAB code, `defaultParameters.m`): cost = the difference matrix after local
contrast enhancement over a window of R = 10 database images (`contrastEnhancement.R`),
velocities 0.8 to 1.2 in steps of 0.1 (`matching.vmin/vmax/vskip`), trajectories of ds = 10
(`matching.ds`: OpenSeqSLAM sums ds + 1 frames, 0..ds, centred on the query; here `length` counts
frames, so OpenSeqSLAM's default is length 11), and the match's quality is its cost over the best
cost outside a window of Rwindow = 10 database images around it (`matching.Rwindow`), after
shifting the enhanced matrix so its minimum is 0.

The descriptor-sequence score is the same search with one velocity (1: the matching diagonal),
no enhancement, and cost = -similarity: the mean similarity along the diagonal.
"""
from __future__ import annotations

from fractions import Fraction
from math import floor

import numpy as np

#: OpenSeqSLAM's defaults (see the module's docstring)
SEQSLAM_DEFAULTS = {"length": 10, "enhance_window": 10, "v_min": 0.8, "v_max": 1.2, "v_step": 0.1,
                    "uniqueness_window": 10}
MODES = ("offline", "causal")
#: a window of equal differences has no contrast: its deviation is taken as this, not 0
MIN_DEVIATION = 1e-6


def query_offsets(length: int, mode: str) -> np.ndarray:
    """Offsets of the frames of a query's sequence from the query: centred (offline, the later
    half one longer for an even length) or ending at the query (causal, past frames only)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode == "causal":
        return np.arange(-(length - 1), 1, dtype=np.int64)
    return np.arange(-((length - 1) // 2), length // 2 + 1, dtype=np.int64)


def velocities(v_min: float, v_max: float, v_step: float) -> list[Fraction]:
    """v_min, v_min + v_step, ... up to v_max, as exact fractions of the decimals given (so the
    rounding of v * k is the same on every machine)."""
    low, high, step = (Fraction(str(v)) for v in (v_min, v_max, v_step))
    count = int(floor((high - low) / step)) + 1
    return [low + i * step for i in range(count)]


def trajectories(offsets: np.ndarray, speeds: list[Fraction]) -> np.ndarray:
    """(T, L) database offsets round(v * k) (half away from zero), one row per distinct trajectory."""
    rows = {tuple(int(floor(abs(v * int(k)) + Fraction(1, 2))) * (1 if k >= 0 else -1) for k in offsets)
            for v in speeds}
    return np.array(sorted(rows), dtype=np.int64).reshape(len(rows), len(offsets))


def enhance(differences: np.ndarray, window: int) -> np.ndarray:
    """OpenSeqSLAM's local contrast enhancement of each query's row of differences: entry d
    minus the mean of the database entries d - window/2 .. d + window/2 (cut at the ends), over
    their standard deviation (n - 1 in the denominator, as MATLAB's std). float32 out."""
    rows, n = differences.shape
    half = window // 2
    values = differences.astype(np.float64)
    mean, deviation = np.empty_like(values), np.empty_like(values)
    sums = np.zeros((rows, n + 1))
    squares = np.zeros((rows, n + 1))
    np.cumsum(values, axis=1, out=sums[:, 1:])
    np.square(values, out=deviation)
    np.cumsum(deviation, axis=1, out=squares[:, 1:])
    # window d - half .. d + half cut to 0 .. n - 1: the sums of its entries from the running sums
    low = np.maximum(np.arange(n) - half, 0)
    high = np.minimum(np.arange(n) + half + 1, n)
    count = (high - low).astype(np.float64)
    edges = np.r_[0:min(half, n), max(n - half, min(half, n)):n]
    for out, running in ((mean, sums), (deviation, squares)):
        if n > 2 * half:  # the full windows, by slices
            np.subtract(running[:, 2 * half + 1:], running[:, :n - 2 * half], out=out[:, half:n - half])
        out[:, edges] = running[:, high[edges]] - running[:, low[edges]]
    # deviation holds the sums of squares, mean the sums: variance = (sq - sum * mean) / (count - 1)
    np.divide(mean, count, out=mean)
    np.multiply(mean, mean, out=squares[:, 1:])
    squares[:, 1:] *= count
    np.subtract(deviation, squares[:, 1:], out=deviation)
    np.divide(deviation, np.maximum(count - 1, 1), out=deviation)
    np.sqrt(np.maximum(deviation, 0.0, out=deviation), out=deviation)
    np.maximum(deviation, MIN_DEVIATION, out=deviation)
    np.subtract(values, mean, out=values)
    np.divide(values, deviation, out=values)
    return values.astype(np.float32)


def trajectory_costs(costs: np.ndarray, first_row: int, start: int, stop: int, n_queries: int,
                     offsets: np.ndarray, paths: np.ndarray) -> np.ndarray:
    """(stop - start, N) float32: for queries start..stop (traverse positions), the mean cost of
    the best trajectory through each database image. `costs` holds the cost rows of
    queries first_row .. first_row + len(costs), which must cover every frame the windows reach."""
    block, n = stop - start, costs.shape[1]
    best = np.full((block, n), np.inf, dtype=np.float32)
    total = np.empty((block, n), dtype=np.float32)
    terms = np.empty((block, n), dtype=np.float32)  # how many frames of the trajectory exist (small integers)
    for path in paths:
        total.fill(0)
        terms.fill(0)
        for k, o in zip(offsets.tolist(), path.tolist()):
            t_lo, t_hi = max(start, -k), min(stop, n_queries - k)  # the query frame t + k exists
            d_lo, d_hi = max(0, -o), min(n, n - o)                  # the database frame d + o exists
            if t_lo >= t_hi or d_lo >= d_hi:
                continue
            lo = t_lo + k - first_row
            total[t_lo - start:t_hi - start, d_lo:d_hi] += costs[lo:lo + t_hi - t_lo, d_lo + o:d_hi + o]
            terms[t_lo - start:t_hi - start, d_lo:d_hi] += 1
        np.divide(total, terms, out=total)
        np.minimum(best, total, out=best)
    return best


def top_k(costs: np.ndarray, k: int, ties: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(indices, costs) of the k lowest costs per row, lowest first, ties to the lower `ties` key of
    the column (default: the lower column)."""
    n = costs.shape[1]
    k = min(k, n)
    ties = np.arange(n) if ties is None else np.asarray(ties)
    part = np.argpartition(costs, k - 1, axis=1)[:, :k] if k < n else np.tile(np.arange(n), (len(costs), 1))
    values = np.take_along_axis(costs, part, axis=1)
    order = np.lexsort((ties[part], values), axis=1)
    part, values = np.take_along_axis(part, order, axis=1), np.take_along_axis(values, order, axis=1)
    # argpartition keeps any of the rows tied with the k-th: where it left one out, sort that row whole
    kth = values[:, -1:]
    for row in np.flatnonzero((costs == kth).sum(axis=1) > (values == kth).sum(axis=1)):
        part[row] = np.lexsort((ties, costs[row]))[:k]
        values[row] = costs[row, part[row]]
    return part, values


def second_best(costs: np.ndarray, best: np.ndarray, window: int) -> np.ndarray:
    """Per row, the lowest cost outside best - window/2 .. best + window/2 (OpenSeqSLAM's
    Rwindow); inf when the window covers the whole row."""
    n = costs.shape[1]
    columns = np.arange(n)
    inside = np.abs(columns[None, :] - best[:, None]) <= window // 2
    return np.where(inside, np.inf, costs).min(axis=1)
