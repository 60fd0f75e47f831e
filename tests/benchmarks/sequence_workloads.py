"""SeqSLAM at Nordland's size, each direction in a fresh process (synthetic descriptors).

`python tests/benchmarks/sequence_workloads.py NAME` runs one workload and prints one JSON line:
its time, the RSS when it starts (interpreter, libraries and the seeded descriptors) and its
peak RSS (VmHWM, reset just before it runs), and the share of queries matched within one database frame of their place.

The traverses mimic VPR-Bench's Nordland: 27,592 summer frames and every 10th winter frame
(2,760), descriptors drifting along the route (a seeded AR(1), 256 dims, unit rows), both seasons
noisy (winter more). `nordland` matches the 2,760 winter queries against the 27,592 summer frames,
`nordland-swapped` the 27,592 summer queries against the 2,760 winter frames. The database
moves 10 (or 0.1) frames per query frame, so the velocities are OpenSeqSLAM's 0.8..1.2 scaled
by that ratio; everything else is OpenSeqSLAM's default (length 10, enhancement window 10).
"""
from __future__ import annotations

import json
import sys

import numpy as np
from memory import measured  # this folder is on sys.path (as a script and under pytest)

FRAMES, STEP, DIM, K = 27_592, 10, 256, 5
BUDGET = 1_000_000_000
CORRELATION = 0.9


def traverses(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from scipy.signal import lfilter

    rng = np.random.default_rng(seed)
    # the place's appearance: a unit-variance AR(1) along the route (correlation 0.9 from frame to frame)
    noise = rng.standard_normal((FRAMES, DIM), dtype=np.float32)
    route = lfilter([np.sqrt(1 - CORRELATION ** 2)], [1, -CORRELATION], noise, axis=0).astype(np.float32)
    summer = route + rng.standard_normal((FRAMES, DIM), dtype=np.float32)
    winter = route[::STEP] + rng.standard_normal((len(route[::STEP]), DIM), dtype=np.float32) * np.float32(1.5)
    for rows in (summer, winter):
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    return summer, winter


def workload(name: str):
    from vprbench.stages.sequence.search import sequence_search

    summer, winter = traverses()
    if name == "nordland":
        database, queries, speed = summer, winter, STEP
        truth = np.arange(len(winter)) * STEP
    elif name == "nordland-swapped":
        database, queries, speed = winter, summer, 1 / STEP
        truth = np.arange(FRAMES) / STEP
    else:
        raise SystemExit(f"unknown workload {name!r}")

    def run() -> dict:
        found = sequence_search(database, queries, K, score="seqslam", length=10, v_min=0.8 * speed,
                                v_max=1.2 * speed, v_step=0.1 * speed, memory_budget=BUDGET)
        matched = np.abs(found.indices[:, 0] - truth) <= 1  # within one database frame of the true place
        return {"queries": len(queries), "database": len(database), "dim": DIM, "block_rows": found.info["block_rows"],
                "blocks": found.info["blocks"], "trajectories": found.info["trajectories"],
                "matched_within_1_frame": round(float(matched.mean()), 4), "memory_budget": BUDGET}
    return run


def probe(name: str) -> dict:
    details, seconds, base, peak = measured(workload(name))
    return {"workload": name, "seconds": round(seconds, 3), "baseline_mb": round(base / 1024, 1),
            "peak_mb": round(peak / 1024, 1), "peak_above_baseline_mb": round((peak - base) / 1024, 1), **details}


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: sequence_workloads.py nordland | nordland-swapped")
    print(json.dumps(probe(sys.argv[1])))
