"""Bundles and publishing at scale, each workload in a fresh process.

`python tests/benchmarks/bundle_workloads.py make DATA_DIR` writes the inputs when missing:
- msls/: a results store with one run of MSLS-val size (11,000 queries, 18,871 database images,
  top-100 kept), and its bundle msls.tar.gz;
- board/: a results store of 200 runs over 17 benchmarks at their real image counts (12 methods,
  the last on 13 of them; top-20); its results/ folder is laid out as a results repository is, and
  is published as one (`leaderboard publish --results`).
Records are built by the real record builder from a synthetic search on synthetic ground truth
(the helpers of tests/leaderboard/synthetic_runs.py); the ground truth the verifier checks against is
the same synthetic one, passed as `truth` (nothing of a real dataset is needed).

`... NAME DATA_DIR` runs one workload and prints one JSON line: its seconds, and the peak RSS of
the whole process (the kernel's VmHWM: interpreter, libraries and the workload).
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

from memory import rss_kb  # this folder is on sys.path (as a script and under pytest)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "leaderboard"))
from synthetic_runs import FakeMethod, synthetic_ground_truth, synthetic_search, synthetic_spec  # noqa: E402

MSLS = {"dataset": "msls-val", "database": 18_871, "queries": 11_000, "k": 100}
#: 17 benchmarks (their default protocols and image counts; MSLS with GSV-Cities' 740 queries)
BOARD_DATASETS = ("17places", "baidu-mall", "corridor", "gardens-point", "hawkins", "laurel-caverns",
                  "mid-atlantic-ridge", "msls-val", "nardo-air", "nordland", "oxford", "pitts250k", "pitts30k",
                  "sped", "st-lucia", "tokyo247", "vp-air")
BOARD_RUNS, BOARD_METHODS = 200, 12


def dataset_of(name: str, n_database: int | None = None, n_queries: int | None = None):
    """A benchmark's synthetic copy under its default protocol (as the leaderboard tests make it)."""
    from vprbench.datasets import apply_protocol, dataset_manifest, find_protocol
    from vprbench.datasets.model import Dataset

    manifest = dataset_manifest(name)
    n_database = n_database or manifest.database_count
    n_queries = n_queries or manifest.query_count
    gt = synthetic_ground_truth(n_database, n_queries, manifest.unit, manifest.radius)
    images = Path("/nonexistent") / name
    data = Dataset(name, [images / f"db{i}.jpg" for i in range(n_database)], [images / f"q{i}.jpg" for i in range(n_queries)],
                   gt, domain=manifest.domain, root=images, layout="vpr-bench", kind="benchmark")
    return apply_protocol(data, find_protocol(manifest, None))


def record_of(method: str, data, k: int, seed: int, quality: float) -> dict:
    from vprbench.evaluation.record import result_record

    positives = data.positives
    scores, indices, positives = synthetic_search(positives, len(data.database), k, quality, seed)
    ks = tuple(x for x in (1, 5, 10, 20) if x <= k)
    return result_record(
        spec=synthetic_spec(method, {}, {}, data, ks, {}), method=FakeMethod(method, {}, {"source": "none"}),
        fingerprint={"method": method}, dataset=data, dataset_key=f"fp-{data.name}", ks=ks, scores=scores,
        indices=indices, positives=positives, descriptor_dim=512,
        computed={"database": len(data.database), "queries": len(data.queries)},
        timings={"fit_s": 0.0, "database_s": 1.0, "queries_s": 1.0, "search_s": 0.1, "total_s": 2.1})


def msls_data():
    return dataset_of(MSLS["dataset"], MSLS["database"], MSLS["queries"])


def make_inputs(folder: Path) -> None:
    from vprbench.bundles.export import export_bundle
    from vprbench.evaluation import read_results, save_result

    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "msls.tar.gz").is_file():
        shutil.rmtree(folder / "msls", ignore_errors=True)
        save_result(record_of("msls-method", msls_data(), MSLS["k"], seed=1, quality=0.7), folder / "msls")
        export_bundle(read_results(folder / "msls"), folder / "msls.tar.gz", contributor="benchmark")
    if not (folder / "board.done").is_file():
        shutil.rmtree(folder / "board", ignore_errors=True)
        runs = 0
        for name in BOARD_DATASETS:
            data = dataset_of(name, n_queries=740 if name == "msls-val" else None)
            for m in range(BOARD_METHODS):
                if runs >= BOARD_RUNS or (m == BOARD_METHODS - 1 and BOARD_DATASETS.index(name) >= 13):
                    continue
                save_result(record_of(f"method-{m:02d}", data, 20, seed=m, quality=0.3 + 0.05 * m), folder / "board")
                runs += 1
        assert runs == BOARD_RUNS, runs
        (folder / "board.done").write_text(str(runs))


def msls_truth():
    """The synthetic ground truth the MSLS-size run was scored on, as `verify_bundle`'s truth."""
    from vprbench.evaluation.rescore import Truth
    from vprbench.evaluation.blocks import for_dataset

    data = msls_data()
    found = Truth(data.protocol["id"], len(data.database), data.positives, for_dataset(data))  # as DataGroundTruth

    def truth(dataset, protocol_hash):
        assert (dataset, protocol_hash) == (data.name, data.protocol["hash"])
        return found

    return truth


def verify(folder: Path) -> dict:
    from vprbench.bundles.verify import verify_bundle

    report = verify_bundle(folder / "msls.tar.gz", msls_truth())
    assert report.ok, report.lines()
    return {"records": len(report.verdicts), "bundle_mb": round((folder / "msls.tar.gz").stat().st_size / 2**20, 2)}


def import_into_repository(folder: Path) -> dict:
    from vprbench.bundles import import_bundles

    repository = folder / "repository"
    shutil.rmtree(repository, ignore_errors=True)
    [report] = import_bundles([folder / "msls.tar.gz"], repository, msls_truth())
    assert report.ok and len(report.added) == 1, report.lines()
    return {"added": len(report.added)}


def publish_board(folder: Path) -> dict:
    """`leaderboard publish --results DIR`: the 200 runs read as a results repository (an empty cache beside it)."""
    from vprbench.leaderboard.site import publish

    docs, cache = folder / "docs", folder / "empty-cache"
    shutil.rmtree(docs, ignore_errors=True)
    section = publish(docs, cache, results=folder / "board" / "results")
    return {"pages": len(list(section.glob("*.md"))), "figures": len(list((section / "figures").glob("*")))}


WORKLOADS = {"verify": verify, "import": import_into_repository, "publish": publish_board}


def probe(name: str, folder: Path) -> dict:
    start = time.perf_counter()
    details = WORKLOADS[name](folder)
    return {"workload": name, "seconds": round(time.perf_counter() - start, 3),
            "peak_rss_mb": round(rss_kb("VmHWM:") / 1024, 1), **details}


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: bundle_workloads.py make|verify|import|publish DATA_DIR")
    command, where = sys.argv[1], Path(sys.argv[2])
    if command == "make":
        make_inputs(where)
    else:
        print(json.dumps(probe(command, where)))
