"""torchrun with 2 gloo ranks: descriptors equal one process bit for bit; a killed rank resumes only its rows."""
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.distributed import Ranks
from vprbench.errors import VPRBenchError
from runs import evaluate_method as evaluate
from vprbench.store import StoreFolder, create_rows_file, method_fingerprint
from vprbench.store.rows_file import RowsIdentity

DRIVER = Path(__file__).with_name("dist_driver.py")


def torchrun(shared_data, cache, *extra, env=None, ranks=2):
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}", str(DRIVER),
               "evaluate", "--method", "fitted-test", "--dataset", "corridor", "--data-dir", str(shared_data),
               "--cache-dir", str(cache), "--json", *extra]
    return subprocess.run(command, capture_output=True, text=True, cwd=DRIVER.parent, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})


def stores(cache: Path) -> dict[str, np.ndarray]:
    found = {}
    for path in cache.rglob("*.h5"):
        with h5py.File(path) as f:
            found[path.name] = f["state"]["centre"][...] if path.name == "fit_state.h5" else f["descriptors"][...]
    return found


def record_of(done) -> dict:
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def one_process(shared_data, tmp_path_factory):
    """The same evaluation in one process: the reference, store by store."""
    cache = tmp_path_factory.mktemp("one")
    record = evaluate(vprbench.create_method("fitted-test"), load_dataset("corridor", shared_data), cache_dir=cache)
    return record, stores(cache)


def test_two_ranks_equal_one_process_bit_for_bit(shared_data, tmp_path, one_process):
    record = record_of(torchrun(shared_data, tmp_path))
    reference, reference_stores = one_process
    assert record["context"]["distributed"] == {"world_size": 2, "backend": "gloo", "computed_per_rank": [
        {"database": 55, "queries": 55}, {"database": 56, "queries": 56}]}
    assert record["descriptors_computed"] == {"database": 111, "queries": 111}
    found = stores(tmp_path)
    assert sorted(found) == ["database.h5", "fit_state.h5", "queries.h5"]  # shards merged, then removed
    for name, array in reference_stores.items():
        assert np.array_equal(found[name], array), name  # fitted on rank 0, shared, described by both: bit for bit
    assert record["recall"] == reference["recall"] and record["top_predictions"] == reference["top_predictions"]


def test_killed_rank_resumes_only_its_missing_rows(shared_data, tmp_path, one_process):
    killed = torchrun(shared_data, tmp_path, env={"KILL_RANK": "1", "KILL_AT_BATCH": "3"})
    assert killed.returncode != 0
    done = {}
    for path in tmp_path.rglob("*.partial.h5"):  # what each rank's shard holds after the kill
        with h5py.File(path) as f:
            done[path.name] = int(f["done"][...].sum())
    assert done["database.rank1-of-2.partial.h5"] == 20  # two batches of ten finished before the kill
    resumed = record_of(torchrun(shared_data, tmp_path, env={"LOG": str(tmp_path / "log")}))
    per_rank = resumed["context"]["distributed"]["computed_per_rank"]
    shard = {0: {"database": 55, "queries": 55}, 1: {"database": 56, "queries": 56}}
    for rank in (0, 1):
        for split in ("database", "queries"):
            left = shard[rank][split] - done.get(f"{split}.rank{rank}-of-2.partial.h5", 0)
            assert per_rank[rank][split] == left, (rank, split)
    rank1_log = (tmp_path / "log.rank1").read_text().split()
    assert len(rank1_log) == 36 + 56  # its 36 missing database rows and all its query rows, nothing more
    found = stores(tmp_path)
    for name, array in one_process[1].items():
        assert np.array_equal(found[name], array), name
    assert resumed["recall"] == one_process[0]["recall"]


def test_ranks_that_disagree_on_the_cache_folder_are_refused(shared_data, tmp_path):
    done = torchrun(shared_data, tmp_path / "cache-{rank}")
    assert done.returncode != 0
    assert "error: torchrun ranks disagree on the run (spec, cache folder, data root, run settings)" in done.stderr and "cache-0" in done.stderr and "cache-1" in done.stderr
    assert "VPRBenchError" not in done.stderr  # each rank printed one message and exited 1, no traceback
    assert not list(tmp_path.rglob("*.h5"))  # refused before any work


def test_disagreeing_options_name_both_values(monkeypatch):
    ranks = Ranks(rank=0, world_size=2)
    monkeypatch.setattr(ranks, "all_gather", lambda value: [value, {**value, "options": {"size": 6}}])
    with pytest.raises(VPRBenchError, match=r'disagree on options: rank 0 has .*"size": 8.*rank 1 has .*"size": 6'):
        ranks.agree({"options": {"size": 8}}, "options")


def test_a_shard_from_another_run_is_refused(shared_data, tmp_path):
    dataset = load_dataset("corridor", shared_data)
    method = vprbench.create_method("thumb-test")
    method.use_dataset("corridor")
    folder = StoreFolder(method.name, method_fingerprint(method), "corridor", dataset.images_fingerprint(), tmp_path)
    foreign = RowsIdentity(store="thumb-test-0000/other-0000/database", start=0, stop=111, total=111, fit_id="none",
                           dtype="float32", fingerprint="{}", names=[f"{i}.jpg" for i in range(111)])
    create_rows_file(folder.shard_path("database", 0, 1), foreign, 64)
    with pytest.raises(VPRBenchError, match=r"Shard .*database.rank0-of-1.partial.h5 is from another run"):
        evaluate(method, dataset, cache_dir=tmp_path)
    assert folder.shard_path("database", 0, 1).exists()  # not ours to delete
    assert not folder.store_path("database").exists()


def test_describe_under_torchrun_shards_the_images_and_writes_what_one_process_writes(shared_data, tmp_path):
    images = sorted(str(p) for p in (shared_data / "corridor" / "query").iterdir())[:30]
    fit_on = str(shared_data / "corridor" / "ref")

    def describe(cache, out, *launcher, env=None):
        command = [*launcher, str(DRIVER), "describe", "--method", "fitted-test", "--fit-on", fit_on,
                   "--cache-dir", str(cache), "--out", str(out), *images]
        return subprocess.run(command, capture_output=True, text=True, cwd=DRIVER.parent, timeout=300,
                              env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})

    alone = describe(tmp_path / "one", tmp_path / "one.npy", sys.executable)
    assert alone.returncode == 0, alone.stderr[-3000:]
    sharded = describe(tmp_path / "two", tmp_path / "two.npy", sys.executable, "-m", "torch.distributed.run",
                       "--standalone", "--nproc-per-node=2", env={"LOG": str(tmp_path / "log")})
    assert sharded.returncode == 0, sharded.stderr[-3000:]
    assert np.array_equal(np.load(tmp_path / "two.npy"), np.load(tmp_path / "one.npy"))
    assert sharded.stderr.count("Wrote 30 descriptors") == 1  # rank 0 writes --out
    described = {rank: len((tmp_path / f"log.rank{rank}").read_text().split()) for rank in (0, 1)}
    # each rank described its share of the fit-on images (111) and of the queries (30), once
    assert described == {0: 55 + 15, 1: 56 + 15}
