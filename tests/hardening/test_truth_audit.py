"""The numbers vprbench reports, checked against the real ground-truth files and recomputed
independently (plain numpy on the raw files and stored descriptors, not vprbench's own metrics)."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from vprbench.datasets import dataset_manifests, load_dataset
from vprbench.datasets.protocol import find_protocol
from vprbench.errors import VPRBenchError


def _rows(path) -> dict[int, list[int]]:
    return {int(r[0]): [int(x) for x in np.asarray(r[1]).ravel()] for r in np.load(path, allow_pickle=True)}


@pytest.fixture
def corridor_rows_copy(shared_data, tmp_path):
    """<tmp>/data/corridor with the real images (symlinks) and a ground-truth file the test writes."""
    root = tmp_path / "data" / "corridor"
    root.mkdir(parents=True)
    for split in ("ref", "query"):
        os.symlink(shared_data / "corridor" / split, root / split)
    real = np.load(shared_data / "corridor" / "ground_truth_new.npy", allow_pickle=True)

    def write(rows) -> None:
        np.save(root / "ground_truth_new.npy", np.asarray(rows, dtype=object), allow_pickle=True)

    return tmp_path / "data", real, write


def test_corridor_positives_are_the_raw_rows(shared_data):
    """Row r of the real file is query r; its list, as read, is the references within 2 frames."""
    rows = _rows(shared_data / "corridor" / "ground_truth_new.npy")
    dataset = load_dataset("corridor", shared_data, strict=True)
    assert [set(p.tolist()) for p in dataset.positives] == [set(rows[q]) for q in range(111)]
    assert [set(rows[q]) for q in range(111)] == [set(range(max(0, q - 2), min(111, q + 3))) for q in range(111)]
    assert dataset.summary()["positive_pairs"] == 549


def _renumbered(real: np.ndarray, row: int, query: int) -> np.ndarray:
    rows = real.copy()
    rows[row, 0] = query
    return rows


@pytest.mark.parametrize("damage, expected", [
    (lambda real: real[:100], "no row for 11 of the 111 query images"),               # truncated file
    (lambda real: np.concatenate([real[:-1], real[5:6]]), "two rows for query 5"),   # a row twice, one missing
    (lambda real: _renumbered(real, 110, -1), "query -1"),                           # would wrap to the last query
])
def test_vpr_bench_rows_must_cover_every_query_once(corridor_rows_copy, damage, expected):
    """Before: a truncated or duplicated ground_truth_new.npy was read silently, its uncovered
    queries scored as failures under the same protocol (hog R@1 48.6 -> 41.4 for 100 of 111 rows)."""
    data_dir, real, write = corridor_rows_copy
    write(damage(real))
    with pytest.raises(VPRBenchError, match=expected) as error:
        load_dataset("corridor", data_dir)
    assert "ground_truth_new.npy" in str(error.value) and "re-download" in str(error.value)
    write(real)  # the real rows still read
    assert load_dataset("corridor", data_dir).summary()["positive_pairs"] == 549


def test_truncated_ground_truth_is_one_clear_cli_error(cli, corridor_rows_copy, tmp_path):
    data_dir, real, write = corridor_rows_copy
    write(real[:100])
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(data_dir),
                       "--cache-dir", str(tmp_path / "cache"))
    assert code != 0 and "Traceback" not in err
    assert "no row for 11 of the 111 query images" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "cache" / "results").exists() or not list((tmp_path / "cache" / "results").rglob("*.json"))


def test_nordland_tolerance_10_is_not_patchnetvlads_nordland_npz(shared_data):
    """The real nordland.npz places frame i at (i, i) with posDistThr 10: +-7 frames, not the
    +-10 of protocol tolerance-10, whose source must not claim it (it did)."""
    data = np.load(shared_data / "ground-truth" / "patchnetvlad" / "nordland.npz")
    db, q = data["utmDb"].astype(float), data["utmQ"].astype(float)
    assert len(q) == 27592 and np.array_equal(db[:, 0], db[:, 1]) and np.array_equal(db[:, 0], np.arange(27592))
    middle = 13800
    within = np.flatnonzero(np.hypot(*(db - q[middle]).T) <= float(data["posDistThr"]))
    assert (within - middle).tolist() == list(range(-7, 8))

    protocol = find_protocol(dataset_manifests()["nordland"], "tolerance-10")
    assert protocol.tolerance == 10 and protocol.hash == "8847a02450e4070b"
    assert "+-7 frames" in protocol.source and "Not Patch-NetVLAD's" in protocol.source


def test_recall_of_hog_on_corridor_recomputed_from_its_store(cli, shared_data, tmp_path):
    """R@K, first-positive ranks and top-1 PR recomputed by brute force from the stored
    descriptors and the raw rows: equal to the record's (hog's scores have no ties on the grid
    that could reorder a positive)."""
    import h5py

    data = tmp_path / "data"
    shutil.copytree(shared_data / "corridor", data / "corridor", copy_function=os.symlink)
    cache = tmp_path / "cache"
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(data),
                       "--cache-dir", str(cache))
    assert code == 0, err
    (record_path,) = (cache / "results").glob("*/*/*.json")
    record = json.loads(record_path.read_text())
    (database,) = (cache / "stores").glob("hog-*/corridor-database-*")
    (queries,) = (cache / "stores").glob("hog-*/corridor-queries-*")
    with h5py.File(database / "database.h5") as f:
        db = f["descriptors"][:].astype(np.float64)
    with h5py.File(queries / "queries.h5") as f:
        q = f["descriptors"][:].astype(np.float64)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    order = np.argsort(-(q @ db.T), axis=1, kind="stable")
    rows = _rows(shared_data / "corridor" / "ground_truth_new.npy")
    hit = np.array([[order[i, j] in rows[i] for j in range(20)] for i in range(111)])
    for k in (1, 5, 10, 20):
        assert record["recall"][str(k)] == round(100 * hit[:, :k].any(axis=1).mean(), 6)
    assert (record["recall"]["1"], record["recall"]["5"], record["recall"]["10"]) == (48.648649, 75.675676, 81.981982)
    arrays = np.load(record_path.with_suffix(".npz"))
    mine = np.where(hit.any(axis=1), hit.argmax(axis=1) + 1, 0)
    assert np.array_equal(arrays["first_positive_rank"], mine)
    assert arrays["positives"].tolist() == [len(rows[i]) for i in range(111)]
    assert record["counts"] == {"database": 111, "queries": 111, "positive_pairs": 549, "queries_without_positives": 0,
                                "all_zero_queries": 0, "all_zero_database": 0}


@pytest.mark.parametrize("name, folder", [("17places", "17places"), ("gardens-point", "GardensPointWalking"),
                                          ("corridor", None)])
def test_a_list_datasets_radius_is_what_its_released_lists_hold(shared_data, name, folder):
    """17 Places said 'within 5 frames' (the paper's words) while its lists hold the query frame
    +-2; the radius is shown beside its results and sizes its bootstrap blocks (11 queries, not 7)."""
    path = (shared_data / "corridor" if folder is None else shared_data / "ground-truth" / "vpr-bench" / folder)
    rows = _rows(path / "ground_truth_new.npy")
    manifest = dataset_manifests()[name]
    n = manifest.database_count
    farthest = max(abs(p - q) for q, positives in rows.items() for p in positives if p < n)
    assert manifest.radius == farthest, (name, manifest.radius, farthest)
