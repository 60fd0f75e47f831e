"""End to end at the real size of Pitts-30k test: 10,000 database and 6,816 query images under
their real names and positions (generated pictures), through the store, the loader and the CLI."""
import json

import h5py
import numpy as np

from vprbench import create_method
from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from runs import evaluate_method as evaluate

COUNTS = {"database": 10000, "queries": 6816, "queries_without_positives": 0, "positive_pairs": 968448,
          "all_zero_queries": 0, "all_zero_database": 0}


def test_oracle_scores_recall_at_1_of_100_at_full_size(pitts30k_tree, pitts30k_places):
    dataset = load_dataset("pitts30k", pitts30k_tree.data, strict=True)
    assert dataset.layout == "netvlad-mat"
    assert [p.relative_to(pitts30k_tree.root).as_posix() for p in dataset.database] == pitts30k_tree.db_names
    record = evaluate(create_method("oracle-test", places=pitts30k_places), dataset, ks=(1, 5))
    assert record["counts"] == COUNTS
    assert record["descriptors_computed"] == {"database": 10000, "queries": 6816}
    assert record["recall"] == {"1": 100.0, "5": 100.0}

    # a smaller radius re-scores the same stores: nothing is described again
    tighter = load_dataset("pitts30k", pitts30k_tree.data, strict=True)
    tighter.ground_truth.radius = 10
    again = evaluate(create_method("oracle-test", places=pitts30k_places), tighter, ks=(1, 5))
    assert again["descriptors_computed"] == {"database": 0, "queries": 0}
    assert again["counts"]["positive_pairs"] < COUNTS["positive_pairs"]
    assert again["dataset_fingerprint"] != record["dataset_fingerprint"]


def test_hog_through_the_cli_at_full_size(pitts30k_tree, capsys, tmp_path):
    args = ["evaluate", "--method", "hog", "--resize", "32", "32", "--dataset", "pitts30k",
            "--data-dir", str(pitts30k_tree.data), "--k", "1", "5", "10", "--json", "--strict"]
    assert main(args) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["counts"] == COUNTS
    assert record["descriptors_computed"] == {"database": 10000, "queries": 6816}
    assert record["descriptor_dim"] == 81  # 3 x 3 blocks of one 16-pixel cell, 9 bins
    assert 0 < record["recall"]["1"] <= record["recall"]["5"] <= record["recall"]["10"] <= 100

    (database,) = (tmp_path / "user-cache" / "vprbench" / "stores").rglob("database.h5")
    with h5py.File(database) as f:  # names far beyond HDF5's 64 KB attribute limit, in a dataset
        names = f["names"].asstr()[...].tolist()
        assert names == pitts30k_tree.db_names and f["done"][...].all() and int(f["complete"][()]) == 1
        assert f["descriptors"].shape == (10000, 81)
        np.testing.assert_allclose(np.linalg.norm(f["descriptors"][:100], axis=1), 1, rtol=1e-5)

    assert main(args) == 0
    warm = json.loads(capsys.readouterr().out)
    assert warm["descriptors_computed"] == {"database": 0, "queries": 0}
    assert warm["recall"] == record["recall"]
