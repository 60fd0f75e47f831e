"""Opt-in benchmarks of the store, the loader and torchrun at Pitts-30k size (figures in docs/performance.md).

    pytest tests/benchmarks/test_store_scale.py --benchmark-enable -s

The Pitts-30k tree is the full-size generated one of tests/conftest.py (real names and
positions, 64x48 generated JPEGs): recalls on it only show that the pipeline works.
"""
import json
import os
import re
import statistics
import subprocess
import sys
import time

import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.datasets.identity import images_key
from vprbench.loader import describe_batches

ROUNDS = int(os.environ.get("VPRBENCH_BENCH_ROUNDS", "3"))


def timed_run(command, env=None) -> dict:
    """Wall time and peak RSS of a command (GNU time), and its JSON record."""
    done = subprocess.run(["/usr/bin/time", "-v", *command], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=7200)
    assert done.returncode == 0, done.stderr[-3000:]
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", done.stderr)
    hours, minutes, seconds = (float(g) if g else 0.0 for g in wall.groups())
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr).group(1))
    return {"wall_s": hours * 3600 + minutes * 60 + seconds, "peak_rss_gb": rss_kb / 2**20,
            "record": json.loads(done.stdout)}


def evaluate_command(tree, cache, *extra):
    return [sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--dataset", "pitts30k",
            "--data-dir", str(tree.data), "--cache-dir", str(cache), "--json", *extra]


def test_pitts30k_hog_end_to_end_under_6_gb(pitts30k_tree, tmp_path, benchmark):
    """`vprbench evaluate --method hog --dataset pitts30k` (hog's defaults: 512x512, 35,721-D), cold
    (a fresh cache each round), then once warm (served from the stores)."""
    runs = []
    caches = iter(tmp_path / f"cold-{i}" for i in range(ROUNDS))
    benchmark.pedantic(lambda: runs.append(timed_run(evaluate_command(pitts30k_tree, next(caches)))),
                       rounds=ROUNDS, iterations=1)
    warm = timed_run(evaluate_command(pitts30k_tree, tmp_path / "cold-0"))
    record = runs[0]["record"]
    assert record["counts"]["database"] == 10000 and record["counts"]["positive_pairs"] == 968448
    assert warm["record"]["descriptors_computed"] == {"database": 0, "queries": 0}
    figures = {"cold_wall_s": [r["wall_s"] for r in runs], "cold_peak_rss_gb": [r["peak_rss_gb"] for r in runs],
               "warm_wall_s": warm["wall_s"], "warm_peak_rss_gb": warm["peak_rss_gb"],
               "recall": record["recall"], "descriptor_dim": record["descriptor_dim"],
               "timings": [r["record"]["timings"] for r in runs], "search": record["search"]}
    benchmark.extra_info.update(figures)
    print("\n" + json.dumps(figures, indent=1))
    assert max(r["peak_rss_gb"] for r in runs + [warm]) < 6.0


def images_per_second(method, paths, workers, benchmark) -> float:
    def extract():
        for _ in describe_batches(method, paths, workers=workers):
            pass

    benchmark.pedantic(extract, rounds=ROUNDS, warmup_rounds=1)
    rate = len(paths) / benchmark.stats.stats.median
    benchmark.extra_info["images_per_second"] = round(rate, 1)
    return rate


@pytest.mark.parametrize("workers", [0, 2])
def test_hog_extraction_with_loader_workers(pitts30k_tree, workers, benchmark):
    """hog at its default 512x512: decoding and resizing in the workers, HOG in the main process."""
    paths = load_dataset("pitts30k", pitts30k_tree.data).database[:2000]
    rate = images_per_second(vprbench.create_method("hog"), paths, workers, benchmark)
    print(f"\nhog, {workers} workers: {rate:.1f} images/s")


@pytest.mark.parametrize("workers", [0, 2])
def test_anyloc_extraction_with_loader_workers(pitts30k_tree, workers, benchmark, tmp_path):
    """AnyLoc GeM on a random-initialised ViT-S/14 (block 9): decoding and preprocessing in the
    workers, the network in the main process."""
    import torch

    from vprbench.features.backbones import backbone_spec, create_model
    from release_formats import official_state_dict

    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    weights = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), weights)
    method = vprbench.create_method("anyloc", backbone="dinov2_vits14", weights=str(weights), layer=9,
                                    aggregation="gem", batch_size=16, resize=(224, 224))
    method.extractor  # the model is loaded before timing, as in a long run
    paths = load_dataset("pitts30k", pitts30k_tree.data).database[:256]
    rate = images_per_second(method, paths, workers, benchmark)
    print(f"\nanyloc gem ViT-S/14 224x224, {workers} workers: {rate:.1f} images/s")


@pytest.mark.parametrize("ranks", [1, 2])
def test_torchrun_images_per_second(pitts30k_tree, tmp_path, ranks, benchmark):
    """hog at 256x256 (8,649-D, to keep the search short) on all 16,816 images, 1 or 2 gloo ranks,
    a fresh cache each round; timed: the whole torchrun command."""
    runs = []
    caches = iter(tmp_path / f"cache-{i}" for i in range(ROUNDS))

    def run():
        command = evaluate_command(pitts30k_tree, next(caches), "--device", "cpu", "--resize", "256", "256")
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}",
                   "-m", *command[2:]]
        runs.append(timed_run(command, env={"OMP_NUM_THREADS": "1"}))

    benchmark.pedantic(run, rounds=ROUNDS, iterations=1)
    # rank 0's describe + merge time: with balanced shards, the time the job's extraction took
    rates = [16816 / (r["record"]["timings"]["database_s"] + r["record"]["timings"]["queries_s"]) for r in runs]
    benchmark.extra_info.update({"extraction_images_per_second": rates, "wall_s": [r["wall_s"] for r in runs]})
    print(f"\ntorchrun {ranks} rank(s): extraction {statistics.median(rates):.1f} images/s, "
          f"whole command {statistics.median(r['wall_s'] for r in runs):.1f} s")


def test_image_identity_memo_at_pitts30k_size(pitts30k_tree, tmp_path, benchmark):
    dataset = load_dataset("pitts30k", pitts30k_tree.data)
    paths = dataset.database + dataset.queries
    cache = tmp_path / "memo"
    started = time.perf_counter()
    cold = images_key(paths, pitts30k_tree.root, cache)
    cold_s = time.perf_counter() - started
    benchmark.pedantic(lambda: images_key(paths, pitts30k_tree.root, cache), rounds=ROUNDS, warmup_rounds=0)
    warm_s = benchmark.stats.stats.median
    assert images_key(paths, pitts30k_tree.root, cache) == cold
    total_mb = sum(p.stat().st_size for p in paths) / 2**20
    import hashlib

    block = os.urandom(2**28)  # sha256 speed on 256 MB, for images of real size
    started = time.perf_counter()
    hashlib.sha256(block).hexdigest()
    sha_mb_s = 256 / (time.perf_counter() - started)
    benchmark.extra_info.update({"files": len(paths), "megabytes": round(total_mb, 1), "cold_s": cold_s,
                                 "warm_s": warm_s, "sha256_mb_per_s": sha_mb_s})
    print(f"\n{len(paths)} files ({total_mb:.1f} MB): cold {cold_s:.2f} s, warm (memo) {warm_s:.2f} s; "
          f"sha256 {sha_mb_s:.0f} MB/s")
