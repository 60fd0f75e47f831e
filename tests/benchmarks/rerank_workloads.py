"""Re-ranking the top 100 of 1,000 Pitts-30k queries, in a fresh process (figures in docs/performance.md).

    python tests/benchmarks/rerank_workloads.py build SHARED_DATA DATA
    python tests/benchmarks/rerank_workloads.py run DATA CACHE STAGE [KEY=VALUE ...]

`build` writes the full-size Pitts-30k tree (tests/pitts30k_tree.py: the real 10,000 database and
6,816 query names and UTM positions) with photo-like images: each place is the 640x480 crop of a
real street photo (../shared/data/images/tokyo247-pair/tokyo_query.jpg, 3264x2448) at an offset of
4 pixels per metre of its position, so nearby places overlap as neighbouring street views do and
SIFT finds about as many keypoints as in a photo (its 2,000 cap on most crops).

`run` re-ranks, with stage STAGE and its options, the 100 database images nearest by position
to each of 1,000 queries spread evenly over the 6,816 (what a good retriever hands a re-ranker),
through the stage's own `apply` and feature store in CACHE, and prints one JSON line: the stage's
time per query, how many images' features it computed, the bytes it stores per database image (the
arrays, and the HDF5 file on disk), the process's RSS before the stage and its peak (VmHWM) at the end.
VPRBENCH_RERANK_FIRST=N re-ranks only the first N of those queries (a shorter warm run over the
features a full cold run stored).
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

DEPTH, PIXELS_PER_METRE, SIZE = 100, 4.0, (640, 480)
#: queries re-ranked (fewer for a quick check of the script)
QUERIES = int(os.environ.get("VPRBENCH_RERANK_QUERIES", "1000"))
#: re-rank only the first this many of those queries (the same ones: a shorter warm run)
FIRST = int(os.environ.get("VPRBENCH_RERANK_FIRST", str(QUERIES)))
PHOTO = Path("images") / "tokyo247-pair" / "tokyo_query.jpg"


def build(shared_data: Path, data: Path) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import pitts30k_tree

    from vprbench.images import load_rgb

    photo = load_rgb(shared_data / PHOTO)
    gt = np.load(shared_data / "ground-truth" / "patchnetvlad" / "pitts30k_test.npz")
    low = np.minimum(gt["utmDb"].min(0), gt["utmQ"].min(0))
    room = np.array([photo.shape[1] - SIZE[0], photo.shape[0] - SIZE[1]])

    def crop(easting: float, northing: float) -> np.ndarray:
        x, y = np.minimum(((np.array([easting, northing]) - low) * PIXELS_PER_METRE).astype(int), room)
        return np.ascontiguousarray(photo[y:y + SIZE[1], x:x + SIZE[0]])

    tree = pitts30k_tree.build(shared_data, data, image=crop)
    print(f"{tree.root}: {len(tree.db_names)} database and {len(tree.q_names)} query images")


def run(data: Path, cache: Path, name: str, options: dict) -> dict:
    from memory import rss_kb  # this folder is on sys.path (as a script and under pytest)
    from scipy.spatial import cKDTree

    from vprbench.datasets import load_dataset
    from vprbench.row_sources import ArrayRows
    from vprbench.stages import Candidates, StageContext, create_stage

    dataset = load_dataset("pitts30k", data, cache_dir=cache)
    every = np.linspace(0, len(dataset.queries) - 1, QUERIES).round().astype(int)
    truth = dataset.ground_truth
    # the dataset keeps all the chosen queries (its identity keys the feature store), candidates the first FIRST
    subset = dataclasses.replace(dataset, queries=[dataset.queries[i] for i in every],
                                 ground_truth=dataclasses.replace(truth, query_positions=truth.query_positions[every]))
    chosen = every[:FIRST]
    distances, nearest = cKDTree(truth.database_positions).query(truth.query_positions[chosen], DEPTH)
    candidates = Candidates(nearest.astype(np.int64), (-distances).astype(np.float32))
    stage = create_stage(name, {"k": DEPTH, **options})
    context = StageContext(dataset=subset, database=ArrayRows(np.zeros((len(dataset.database), 1), np.float32)),
                           queries=ArrayRows(np.zeros((len(every), 1), np.float32)), cache_dir=cache)
    subset.images_fingerprint(cache)  # content identity (hashing every file) is not the stage's time
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")  # reset the peak-RSS counter (VmHWM) to the current RSS
    base = rss_kb("VmRSS:")
    started = time.perf_counter()
    found = stage.apply(candidates, context)
    seconds = time.perf_counter() - started
    peak = rss_kb("VmHWM:")
    store, images = context.stores[0], len(np.unique(nearest))
    stored = sum(path.stat().st_size for path in store.files("database"))  # the split's segment files
    positives = dataset.positives
    at_1 = lambda found_rows: float(np.mean([row[0] in positives[q] for q, row in zip(chosen, found_rows)]))  # noqa: E731
    return {"stage": name, "options": stage.options.model_dump(mode="json"), "queries": len(chosen), "depth": DEPTH,
            "database_images_touched": images, "seconds": round(seconds, 1),
            "ms_per_query": round(1000 * seconds / len(chosen), 1), "features_computed": context.features_computed,
            "array_bytes_per_database_image": round(store.bytes_per_image("database")),
            "file_bytes_per_database_image": round(stored / images),
            "database_segment_files": len(store.files("database")),
            "rss_before_mb": round(base / 1024, 1), "peak_rss_mb": round(peak / 1024, 1),
            "mean_top_score": round(float(found.scores[:, 0].mean()), 1),
            "r1_before": round(100 * at_1(candidates.indices), 1), "r1_after": round(100 * at_1(found.indices), 1)}


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "build":
        build(Path(sys.argv[2]), Path(sys.argv[3]))
    elif len(sys.argv) >= 5 and sys.argv[1] == "run":
        from vprbench.cli.options import key_values

        print(json.dumps(run(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4], key_values(sys.argv[5:], "option"))))
    else:
        raise SystemExit(__doc__)
