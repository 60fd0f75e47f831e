"""Exact search from stores on disk against the faster of numpy's and oneDNN's GEMM on the same matrices, at every
benchmark's shape (run: pytest tests/benchmarks/test_search_gemm.py --benchmark-enable -s).
Each shape runs in a fresh process (search_gemm.py): GEMM and search in turn, same threads
(all cores unless VPRBENCH_BENCH_THREADS is set), the ratio per round in extra_info.
Stores (about 12 GB) are kept in $VPRBENCH_BENCH_DATA/gemm (default /tmp/vprbench-bench-search/gemm).
Results: docs/performance.md.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("VPRBENCH_BENCH_DATA", "/tmp/vprbench-bench-search")) / "gemm"
ROUNDS = os.environ.get("VPRBENCH_BENCH_ROUNDS", "3")
#: database x queries x dim: Nordland-size hog, Pitts-30k hog and AnyLoc VLAD, MSLS-val, a million rows
SHAPES = ["3576x3576x35721", "10000x6816x35721", "10000x6816x49152", "18871x11084x8448", "1000000x1000x512"]


@pytest.mark.parametrize("shape", SHAPES)
def test_search_against_gemm(benchmark, shape):
    benchmark.group = "exact search vs the faster GEMM"
    threads = os.environ.get("VPRBENCH_BENCH_THREADS")
    env = {**os.environ, **({"OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads} if threads else {})}
    found = {}

    def once():
        out = subprocess.run([sys.executable, str(HERE / "search_gemm.py"), shape, str(DATA), ROUNDS],
                             capture_output=True, text=True, check=True, env=env)
        found.update(json.loads(out.stdout.strip().splitlines()[-1]))

    benchmark.pedantic(once, rounds=1, iterations=1)
    benchmark.extra_info.update(found)
    print(f"\n{shape}: numpy GEMM {found['gemm_gflops']} GFLOP/s, oneDNN {found['onednn_gflops']} GFLOP/s, "
          f"search {found['search_gflops']} GFLOP/s, "
          f"ratio {found['median_ratio']} (rounds {found['ratios']})")
    assert found["shape"] == shape and len(found["ratios"]) == int(ROUNDS)
