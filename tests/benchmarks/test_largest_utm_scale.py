"""Opt-in benchmark: `vprbench evaluate` end to end at the full size of the largest datasets served
(Pitts-250k test, 92,232 images; Tokyo 24/7, 76,299), cold then warm.

    pytest tests/benchmarks/test_largest_utm_scale.py --benchmark-enable -s -k pitts250k

The trees are the generated ones of tests/utm_trees.py (64x48 JPEGs; Pitts-250k at synthetic
positions, Tokyo 24/7 at its real ones): recalls on them only show that the pipeline works.
"""
import json
import os
import sys

import pytest

from test_store_scale import timed_run  # wall time and peak RSS of a command, and its JSON record

ROUNDS = int(os.environ.get("VPRBENCH_BENCH_ROUNDS", "1"))  # a cold run of 92k images takes minutes
COUNTS = {"pitts250k": (83952, 8280), "tokyo247": (75984, 315)}


@pytest.mark.parametrize("name", ["pitts250k", "tokyo247"])
def test_hog_64_end_to_end_at_full_size(name, request, tmp_path, benchmark):
    """hog at 64x64 (a cheap describe, so the pipeline's own cost shows): cold (a fresh cache each
    round), then once warm (served from the stores)."""
    tree = request.getfixturevalue(f"{name}_tree")
    command = lambda cache: [sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--resize", "64", "64",  # noqa: E731
                             "--dataset", name, "--data-dir", str(tree.data), "--cache-dir", str(cache), "--json", "--strict"]
    runs = []
    caches = iter(tmp_path / f"cold-{i}" for i in range(ROUNDS))
    benchmark.pedantic(lambda: runs.append(timed_run(command(next(caches)))), rounds=ROUNDS, iterations=1)
    warm = timed_run(command(tmp_path / "cold-0"))
    database, queries = COUNTS[name]
    record = runs[0]["record"]
    assert (record["counts"]["database"], record["counts"]["queries"]) == (database, queries)
    assert record["descriptors_computed"] == {"database": database, "queries": queries}
    assert warm["record"]["descriptors_computed"] == {"database": 0, "queries": 0}
    assert warm["record"]["recall"] == record["recall"]
    figures = {"cold_wall_s": [r["wall_s"] for r in runs], "cold_peak_rss_gb": [r["peak_rss_gb"] for r in runs],
               "warm_wall_s": warm["wall_s"], "warm_peak_rss_gb": warm["peak_rss_gb"],
               "counts": record["counts"], "descriptors_computed": record["descriptors_computed"],
               "recall": record["recall"], "descriptor_dim": record["descriptor_dim"],
               "timings": [r["record"]["timings"] for r in runs], "warm_timings": warm["record"]["timings"],
               "search": record["search"]}
    benchmark.extra_info.update(figures)
    print("\n" + json.dumps(figures, indent=1))
