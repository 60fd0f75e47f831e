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


def test_store_checksums_cost_at_pitts30k_size(pitts30k_tree, tmp_path, benchmark):
    """What the crc32 of each store row costs on `vprbench evaluate --method hog --dataset pitts30k`
    (hog's defaults: 35,721-D float32, stores of 2.4 GB): computing them as rows are written, and
    verifying both stores whole, which every evaluation that finds them complete does before it
    searches; beside the same blocks read without a check, and the cold and warm commands."""
    import h5py
    import numpy as np
    import test_store_scale as scale

    from vprbench.store import run_store
    from vprbench.store.rows_file import BLOCK_BYTES, row_checksums

    cache = tmp_path / "cache"
    cold = scale.timed_run(scale.evaluate_command(pitts30k_tree, cache))
    record = cold["record"]
    paths = {split: run_store(record, split, cache).path for split in ("database", "queries")}

    def blocks(path):
        with h5py.File(path, "r") as f:
            data = f["descriptors"]
            step = max(1, BLOCK_BYTES // (data.shape[1] * data.dtype.itemsize))
            raw = np.empty((step, data.shape[1]), dtype=data.dtype)
            for start in range(0, data.shape[0], step):
                stop = min(start + step, data.shape[0])
                data.read_direct(raw, np.s_[start:stop], np.s_[:stop - start])
                yield raw[:stop - start]

    def read_only():
        for path in paths.values():
            for _ in blocks(path):
                pass

    def crc_only() -> float:  # the writer's extra work: one crc32 per row, timed alone
        taken = 0.0
        for path in paths.values():
            for rows in blocks(path):
                started = time.perf_counter()
                row_checksums(rows)
                taken += time.perf_counter() - started
        return taken

    def verify():  # a fresh reader per round: nothing checked yet
        for split in paths:
            run_store(record, split, cache).verify()

    benchmark.pedantic(verify, rounds=1, iterations=1)
    verify_s, read_s = seconds(verify), seconds(read_only)
    crc_s = statistics.median(crc_only() for _ in range(3))
    warm = [scale.timed_run(scale.evaluate_command(pitts30k_tree, cache)) for _ in range(scale.ROUNDS)]
    assert all(w["record"]["descriptors_computed"] == {"database": 0, "queries": 0} for w in warm)
    warm_s = statistics.median(w["wall_s"] for w in warm)
    figures = {"store_gb": round(sum(p.stat().st_size for p in paths.values()) / 1e9, 2),
               "rows": record["counts"]["database"] + record["counts"]["queries"],
               "crc32_of_every_row_s": round(crc_s, 2), "verify_both_stores_s": round(verify_s, 2),
               "read_both_stores_unchecked_s": round(read_s, 2),
               "cold_evaluation_s": round(cold["wall_s"], 1), "warm_evaluation_s": [round(w["wall_s"], 1) for w in warm],
               "crc32_percent_of_cold": round(100 * crc_s / cold["wall_s"], 1),
               "verify_percent_of_warm": round(100 * verify_s / warm_s, 1),
               "timings_cold": record["timings"], "timings_warm": [w["record"]["timings"] for w in warm]}
    benchmark.extra_info.update(figures)
    print("\n", figures)
