"""Opt-in benchmark: what proving stores by content costs at Pitts-30k size (docs/performance.md).

    pytest tests/benchmarks/test_content_identity_cost.py --benchmark-enable -s

A full-size Pitts-30k tree (10,000 + 6,816 real names) of 640x480 JPEGs of about 86 KB each.
Measured: the images' identities taken from scratch (sha256 of every file), taken again from
the memo (what a run served from its stores pays), and hog's describe rate with and without the
loader's check of the bytes it decodes.
"""
import statistics
import time

import pytest

import pitts30k_tree as tree_module
import vprbench
from vprbench.datasets import load_dataset
from vprbench.datasets.identity import content_hashes
from vprbench.loader import describe_batches

SAMPLE = 1000  # images described each way (hog at 512x512 is ~10 ms an image on one core)


@pytest.fixture(scope="module")
def photo_tree(shared_data, tmp_path_factory):
    return tree_module.build(shared_data, tmp_path_factory.mktemp("photos"), size=(640, 480), grain=8)


def seconds(job, rounds=3) -> float:
    taken = []
    for _ in range(rounds):
        started = time.perf_counter()
        job()
        taken.append(time.perf_counter() - started)
    return statistics.median(taken)


def test_content_identity_cost_at_pitts30k_size(photo_tree, tmp_path, benchmark):
    dataset = load_dataset("pitts30k", photo_tree.data)
    paths = dataset.database + dataset.queries
    size_mb = sum(p.stat().st_size for p in paths) / 2**20
    caches = iter(tmp_path / f"cache-{i}" for i in range(100))
    cold = seconds(lambda: content_hashes(paths, next(caches)))
    memo = tmp_path / "memo"
    content_hashes(paths, memo)
    warm = seconds(lambda: content_hashes(paths, memo))
    hog = vprbench.create_method("hog")
    sample = paths[:SAMPLE]
    digests = content_hashes(sample, memo)

    def describe(with_digests):
        for _ in describe_batches(hog, sample, digests=digests if with_digests else None):
            pass

    benchmark.pedantic(lambda: describe(True), rounds=1, iterations=1)
    plain_s, checked_s = seconds(lambda: describe(False)), seconds(lambda: describe(True))
    figures = {"images": len(paths), "megabytes": round(size_mb), "identities_cold_s": round(cold, 2),
               "identities_from_memo_s": round(warm, 2), "hog_describe_s_per_1000_plain": round(plain_s, 2),
               "hog_describe_s_per_1000_checked": round(checked_s, 2),
               "check_overhead_percent": round(100 * (checked_s - plain_s) / plain_s, 1),
               "cold_evaluation_estimate_s": round(plain_s * len(paths) / SAMPLE, 1)}
    benchmark.extra_info.update(figures)
    print("\n", figures)
    assert digests == content_hashes(sample, tmp_path / "fresh")  # the memo gives what hashing gives
