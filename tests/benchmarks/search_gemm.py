"""Exact search from descriptor stores on disk against the machine's GEMM on the same matrices.

`python tests/benchmarks/search_gemm.py SHAPE DATA_DIR [ROUNDS]` (SHAPE as "3576x3576x35721":
database x queries x dim) writes seeded stores of that shape into DATA_DIR/SHAPE when they
are missing (the real store format, unit vectors), then, ROUNDS times in turn: numpy's
`Q @ D.T` (its BLAS) and oneDNN's (vprbench.gemm.products) on the whole matrices in memory,
and `exact_search` (top 20, default 1 GB budget) reading the stores from disk, in the same
process with the same threads. Prints one JSON line: times, GFLOP/s, ratios of the search's
time to the faster GEMM's, and the time of checking every row's checksum (as an evaluation
does before it searches).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

K = 20


def make_store(path: Path, split: str, rows: int, dim: int, seed: int):
    from vprbench.store import DescriptorStore, RowsIdentity, RowWriter, create_rows_file

    identity = RowsIdentity(store=f"bench/{split}", start=0, stop=rows, total=rows, fit_id="none", dtype="float32",
                            fingerprint="{}", names=[f"{i:07d}.jpg" for i in range(rows)])
    if not path.is_file():
        partial = path.with_suffix(".partial")
        create_rows_file(partial, identity, dim)
        writer = RowWriter(partial, identity)
        block = max(1, (64 << 20) // (4 * dim))
        for i, start in enumerate(range(0, rows, block)):
            stop = min(rows, start + block)
            x = np.random.default_rng([seed, i]).standard_normal((stop - start, dim), dtype=np.float32)
            writer.write(np.arange(start, stop), x / np.linalg.norm(x, axis=1, keepdims=True))
        writer.finish()
        writer.close()
        partial.replace(path)
    return DescriptorStore(path, identity)


def run(shape: str, folder: Path, rounds: int) -> dict:
    import threadpoolctl

    from vprbench.search.exact import SCORE_TOLERANCE, exact_search
    from vprbench.gemm import onednn_on, products

    n, q, dim = (int(x) for x in shape.split("x"))
    folder = folder / shape
    folder.mkdir(parents=True, exist_ok=True)
    database, queries = make_store(folder / "database.h5", "database", n, dim, 1), make_store(
        folder / "queries.h5", "queries", q, dim, 2)
    verify_s = {}
    for split, store in (("database", database), ("queries", queries)):
        started = time.perf_counter()
        store.verify()
        verify_s[split] = round(time.perf_counter() - started, 2)
    flop = 2.0 * n * q * dim
    D, Q = database.read_rows(0, n), queries.read_rows(0, q)
    gemm, onednn, search = [], [], []
    for _ in range(rounds):
        started = time.perf_counter()
        scores = Q @ D.T
        gemm.append(time.perf_counter() - started)
        best = scores.max(axis=1)
        del scores
        if onednn_on():
            started = time.perf_counter()
            scores = products(Q, D)
            onednn.append(time.perf_counter() - started)
            del scores
        started = time.perf_counter()
        result = exact_search(database, queries, K)
        search.append(time.perf_counter() - started)
        # the search's best score is numpy's best on the score grid (within one step: rounding)
        assert np.abs(result.scores[:, 0] - best).max() <= SCORE_TOLERANCE, "search disagrees with numpy"
    fastest = [min(times) for times in zip(gemm, onednn or gemm)]  # each round's faster GEMM
    ratios = [g / s for g, s in zip(fastest, search)]
    return {"shape": shape, "flop": flop, "threads": threadpoolctl.threadpool_info()[0]["num_threads"],
            "gemm_s": [round(t, 2) for t in gemm], "onednn_s": [round(t, 2) for t in onednn],
            "search_s": [round(t, 2) for t in search], "gemm_gflops": round(flop / np.median(gemm) / 1e9, 1),
            "onednn_gflops": round(flop / np.median(onednn) / 1e9, 1) if onednn else None,
            "search_gflops": round(flop / np.median(search) / 1e9, 1),
            "ratios": [round(r, 3) for r in ratios], "median_ratio": round(float(np.median(ratios)), 3),
            "verify_s": verify_s, "store_gb": round(4 * (n + q) * dim / 1e9, 2),
            "plan": {k: v for k, v in result.info.items() if k not in ("tie_order", "index")}}


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit("usage: search_gemm.py DBxQxDIM DATA_DIR [ROUNDS]")
    print(json.dumps(run(sys.argv[1], Path(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 3)))
