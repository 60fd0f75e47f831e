"""SeqSLAM on a Nordland-size traverse, both directions, within a 1 GB budget (run: pytest
tests/benchmarks -k sequence --benchmark-enable). Every round is a fresh process
(sequence_workloads.py) reporting its time and peak RSS; figures in docs/performance.md."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
THREADS = os.environ.get("VPRBENCH_BENCH_THREADS", "1")


def script(name: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": THREADS, "OPENBLAS_NUM_THREADS": THREADS}
    out = subprocess.run([sys.executable, str(HERE / "sequence_workloads.py"), name], capture_output=True, text=True,
                         check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("name", ["nordland", "nordland-swapped"])
def test_seqslam_nordland_size(benchmark, name):
    """27,592 x 2,760 and the swapped 2,760 x 27,592: the whole matrix (300 MB, several times that
    with its temporaries) is never held; peak memory stays under the 1 GB budget."""
    benchmark.group = "SeqSLAM, Nordland size (length 10, 1 GB budget)"
    runs = []
    benchmark.pedantic(lambda: runs.append(script(name)), rounds=1, iterations=1)
    benchmark.extra_info["runs"] = runs
    assert all(r["peak_above_baseline_mb"] < 1000 for r in runs)
    assert all(r["matched_within_1_frame"] > 0.5 for r in runs)
