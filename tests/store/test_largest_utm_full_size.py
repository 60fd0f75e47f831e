"""At the real size of the largest datasets vprbench serves (layout "utm-names"): Pitts-250k test,
92,232 images (synthetic positions), through the loader, the ground truth, the store and the
search; Tokyo 24/7, 75,984 + 315 images at its real positions, through the loader and the
ground truth. Expected values are computed here from the trees' positions, not by vprbench."""
import h5py
import numpy as np
from scipy.spatial import cKDTree

from pitts30k_tree import oracle_places
from vprbench import create_method
from vprbench.datasets import load_dataset
from runs import evaluate_method as evaluate


def names(paths, root) -> list[str]:
    return [p.relative_to(root).as_posix() for p in paths]


def radius_positives(where: dict, db_names, q_names, radius=25.0) -> list[list[int]]:
    """Database rows within `radius` metres of each query, from positions keyed by name."""
    db = np.array([where[n] for n in db_names])
    return [sorted(p) for p in cKDTree(db).query_ball_point(np.array([where[n] for n in q_names]), radius)]


def test_pitts250k_oracle_scores_recall_at_1_of_100_at_full_size(pitts250k_tree, tmp_path):
    tree = pitts250k_tree
    dataset = load_dataset("pitts250k", tree.data, strict=True)
    db_names, q_names = names(dataset.database, tree.root), names(dataset.queries, tree.root)
    assert (len(db_names), len(q_names)) == (83952, 8280)
    assert sorted(db_names) == sorted(tree.db_names) and sorted(q_names) == sorted(tree.q_names)

    where = dict(zip(tree.db_names + tree.q_names, np.vstack([tree.utm_db, tree.utm_q])))
    expected = radius_positives(where, db_names, q_names)
    pairs = sum(map(len, expected))
    assert [p.tolist() for p in dataset.positives] == expected
    assert pairs == 1144320 and min(map(len, expected)) > 0

    places = oracle_places(tree)
    record = evaluate(create_method("oracle-test", places=places, folder="pitts250k"), dataset, ks=(1, 5))
    assert record["counts"] == {"database": 83952, "queries": 8280, "queries_without_positives": 0,
                                "positive_pairs": pairs, "all_zero_queries": 0, "all_zero_database": 0}
    assert record["descriptors_computed"] == {"database": 83952, "queries": 8280}
    assert record["recall"] == {"1": 100.0, "5": 100.0}

    (store,) = (tmp_path / "user-cache" / "vprbench" / "stores").rglob("database.h5")
    codes = create_method("oracle-test", places=places).codes
    with h5py.File(store) as f:  # row i is database image i, described by its own place's code
        assert f["names"].asstr()[...].tolist() == db_names and f["done"][...].all()
        np.testing.assert_array_equal(f["descriptors"][...], codes[[places[n] for n in db_names]])


def test_tokyo247_loads_strict_with_real_positives_at_full_size(tokyo247_tree, shared_data):
    tree = tokyo247_tree
    dataset = load_dataset("tokyo247", tree.data, strict=True)
    assert dataset.layout == "utm-names"
    db_names, q_names = names(dataset.database, tree.root), names(dataset.queries, tree.root)
    assert (len(db_names), len(q_names)) == (75984, 315)
    assert sorted(db_names) == sorted(tree.db_names) and sorted(q_names) == sorted(tree.q_names)

    # the positions of the Patch-NetVLAD ground truth, not those parsed back from the names
    gt = np.load(shared_data / "ground-truth" / "patchnetvlad" / "tokyo247.npz")
    where = dict(zip(tree.db_names + tree.q_names, np.vstack([gt["utmDb"], gt["utmQ"]])))
    expected = radius_positives(where, db_names, q_names, float(gt["posDistThr"]))
    assert [p.tolist() for p in dataset.positives] == expected
    assert sum(map(len, expected)) == 37260 and min(map(len, expected)) > 0
    summary = dataset.summary()
    assert (summary["database"], summary["queries"], summary["queries_with_positives"]) == (75984, 315, 315)
