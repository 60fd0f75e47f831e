"""Bundles and publishing at scale (run: pytest tests/benchmarks/test_bundle_scale.py --benchmark-enable -s).

Verifying and importing the bundle of an MSLS-val-size run (11,000 queries, top-100) and
publishing a store of 200 runs over 17 benchmarks, each round in a fresh process
(bundle_workloads.py), which reports the workload's seconds and the process's peak RSS. Inputs
(about 70 MB) are kept in $VPRBENCH_BENCH_DATA (default /tmp/vprbench-bench-bundles).
The targets: under a minute and 2 GB each. Results: docs/performance.md.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("VPRBENCH_BENCH_DATA", "/tmp/vprbench-bench-bundles"))
ROUNDS = int(os.environ.get("VPRBENCH_BENCH_ROUNDS", "3"))
SECONDS, PEAK_MB = 60, 2048


def script(*args) -> dict:
    out = subprocess.run([sys.executable, str(HERE / "bundle_workloads.py"), *args], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1]) if out.stdout.strip() else {}


@pytest.fixture(scope="module", autouse=True)
def inputs():
    script("make", str(DATA))


@pytest.mark.parametrize("name", ["verify", "import", "publish"])
def test_bundle_scale(benchmark, name):
    runs = []
    benchmark.pedantic(lambda: runs.append(script(name, str(DATA))), rounds=ROUNDS, iterations=1)
    benchmark.extra_info["runs"] = runs
    print(json.dumps(runs))
    assert all(r["peak_rss_mb"] < PEAK_MB for r in runs)
    assert min(r["seconds"] for r in runs) < SECONDS, runs
