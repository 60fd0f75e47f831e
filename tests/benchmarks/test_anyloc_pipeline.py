"""AnyLoc pipeline speed and memory on CPU (run: pytest tests/benchmarks --benchmark-enable).

Each benchmark times a workload from workloads.py in this process (pytest-benchmark) and
records, in extra_info, images per second and the peak resident memory the same workload
takes in a fresh process (see workloads.probe). Results: docs/performance.md.
"""
import json
import subprocess
import sys
from pathlib import Path

import pytest

import workloads

HERE = Path(__file__).resolve().parent
#: one torch thread: on a shared, oversubscribed machine a 2-thread pool makes small ops
#: 100x slower and the figures meaningless; the same setting is used for the reference code
THREADS = "1"


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(int(THREADS))
    yield
    torch.set_num_threads(before)


def peak_memory(name: str) -> dict:
    out = subprocess.run([sys.executable, str(HERE / "workloads.py"), name, THREADS], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure(benchmark, name: str, images: int, rounds: int):
    run = workloads.workload(name)
    benchmark.pedantic(run, rounds=rounds, warmup_rounds=1, iterations=1)
    benchmark.extra_info["images"] = images
    benchmark.extra_info["images_per_second"] = round(images / benchmark.stats.stats.mean, 2)
    benchmark.extra_info.update(peak_memory(name))


@pytest.mark.parametrize("name", ["extract-anyloc-batch8", "extract-anyloc-batch1"])
def test_extraction(benchmark, name):
    """vprbench's AnyLoc describe() on 8 PNG files, 224x224: ViT-S/14 value facet of block 9
    + GeM, batches of 8 vs one by one."""
    benchmark.group = "extraction (AnyLoc describe, ViT-S/14, 224x224, 8 images)"
    measure(benchmark, name, workloads.EXTRACT_IMAGES, rounds=3)


@pytest.mark.parametrize("name", ["vlad-ours-vits", "vlad-naive-vits", "vlad-ours-vitg", "vlad-naive-vitg"])
def test_hard_vlad(benchmark, name):
    """Hard VLAD of 8 images, 32 clusters: ours (per-cluster sums) vs residual-tensor loop."""
    benchmark.group = "hard VLAD (8 images, 32 clusters)"
    measure(benchmark, name, 8, rounds=5)


@pytest.mark.parametrize("name", ["fit-sampled", "fit-exact"])
def test_vocabulary_fit(benchmark, name):
    """32-cluster cosine k-means on 600 images x 256 patches x 384 dims, features streamed per
    image (generation included): 20k-feature sample vs all."""
    benchmark.group = "vocabulary fit (600 images x 256 patches x 384)"
    measure(benchmark, name, workloads.FIT_IMAGES, rounds=2)
