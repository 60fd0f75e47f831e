"""Re-ranking the top 100 of 1,000 queries of the full-size Pitts-30k tree, features on disk (run:
pytest tests/benchmarks/test_rerank_scale.py --benchmark-enable -s). Each run is a fresh process
(rerank_workloads.py): cold (the stage computes the features of every image it meets) then warm
(every feature read from the store); figures in docs/performance.md. Long: tens of minutes per run
on 2 shared cores."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
THREADS = os.environ.get("VPRBENCH_BENCH_THREADS", "1")
LIMIT_MB = 6 * 1024


@pytest.fixture(scope="module")
def photo_tree(shared_data, tmp_path_factory) -> Path:
    """The Pitts-30k tree with photo crops (rerank_workloads.build); returns the data root."""
    sys.path.insert(0, str(HERE))
    from rerank_workloads import build

    data = tmp_path_factory.mktemp("photo-tree")
    build(shared_data, data)
    return data


def workload(data: Path, cache: Path, stage: str, *options: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": THREADS, "OPENBLAS_NUM_THREADS": THREADS}
    done = subprocess.run([sys.executable, str(HERE / "rerank_workloads.py"), "run", str(data), str(cache), stage,
                           *options], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("stage, options", [
    ("sift-ransac", ()),
    # speed and memory only: a random-initialised ViT-S/14 (no pretrained weights here); its ranking means nothing
    ("patch-mnn", ("backbone=dinov2_vits14", "weights=random", "resize=240x320")),
])
def test_rerank_top_100_of_1000_pitts30k_queries(photo_tree, tmp_path, benchmark, stage, options):
    benchmark.group = "re-ranking the top 100 of 1,000 Pitts-30k queries"
    runs = []
    benchmark.pedantic(lambda: runs.extend(workload(photo_tree, tmp_path, stage, *options) for _ in ("cold", "warm")),
                       rounds=1, iterations=1)
    cold, warm = runs
    benchmark.extra_info.update({"cold": cold, "warm": warm})
    print("\n" + json.dumps({"cold": cold, "warm": warm}, indent=1))
    assert cold["features_computed"] == cold["database_images_touched"] + cold["queries"]
    assert warm["features_computed"] == 0
    assert max(cold["peak_rss_mb"], warm["peak_rss_mb"]) < LIMIT_MB
