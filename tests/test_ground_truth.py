import numpy as np
import pytest
from PIL import Image

from vprbench.datasets import GroundTruth, load_dataset
from vprbench.errors import VPRBenchError


def test_metres_radius_is_inclusive():
    gt = GroundTruth(unit="metres", radius=25, database_positions=np.array([[0, 0], [25, 0], [26, 0]]),
                     query_positions=np.array([[0, 0], [100, 100]]))
    assert [p.tolist() for p in gt.positives()] == [[0, 1], []]


def test_frames_radius():
    gt = GroundTruth(unit="frames", radius=2, database_positions=np.arange(10)[:, None],
                     query_positions=np.array([[0], [5]]))
    assert [p.tolist() for p in gt.positives()] == [[0, 1, 2], [3, 4, 5, 6, 7]]


def test_explicit_lists_are_sorted_unique():
    gt = GroundTruth(unit="positives", positive_lists=[[3, 1, 1], []])
    assert [p.tolist() for p in gt.positives()] == [[1, 3], []]


def test_unit_needs_its_data():
    with pytest.raises(ValueError):
        GroundTruth(unit="metres", radius=25)
    with pytest.raises(ValueError):
        GroundTruth(unit="feet", positive_lists=[])


def _tree(tmp_path, db_names, q_names):
    for folder, names in (("database", db_names), ("queries", q_names)):
        (tmp_path / folder).mkdir(parents=True, exist_ok=True)
        for name in names:
            Image.new("RGB", (8, 8), (10, 20, 30)).save(tmp_path / folder / name)
    return tmp_path


def test_own_data_with_xy_csv(tmp_path):
    root = _tree(tmp_path / "mine", ["a.jpg", "b.jpg"], ["q.jpg"])
    (root / "positions.csv").write_text("image,x,y\ndatabase/a.jpg,0,0\ndatabase/b.jpg,31,0\nqueries/q.jpg,5,0\n")
    dataset = load_dataset(str(root))
    assert dataset.summary()["positive_pairs"] == 1
    assert [p.tolist() for p in dataset.positives] == [[0]]


def test_own_data_latitude_longitude_in_metres(tmp_path):
    root = _tree(tmp_path / "gps", ["a.jpg", "b.jpg"], ["q.jpg"])
    # 0.0002 deg of latitude is about 22 m; 0.001 deg about 111 m
    (root / "positions.csv").write_text(
        "image,latitude,longitude\ndatabase/a.jpg,40.4400,-79.9900\ndatabase/b.jpg,40.4410,-79.9900\n"
        "queries/q.jpg,40.4402,-79.9900\n")
    assert [p.tolist() for p in load_dataset(str(root)).positives] == [[0]]


def test_own_data_frames_need_radius(tmp_path):
    root = _tree(tmp_path / "frames", ["a.jpg", "b.jpg"], ["q.jpg"])
    (root / "positions.csv").write_text("image,frame\ndatabase/a.jpg,0\ndatabase/b.jpg,10\nqueries/q.jpg,1\n")
    with pytest.raises(VPRBenchError, match="radius"):
        load_dataset(str(root))
    (root / "dataset.toml").write_text("radius = 1\nname = 'frames-demo'\n")
    dataset = load_dataset(str(root))
    assert dataset.name == "frames-demo" and [p.tolist() for p in dataset.positives] == [[0]]


def test_own_data_utm_names(tmp_path):
    root = _tree(tmp_path / "utm", ["@0585000.00@4477000.00@17@T@.jpg", "@0585100.00@4477000.00@17@T@.jpg"],
                 ["@0585010.00@4477000.00@17@T@.jpg"])
    assert [p.tolist() for p in load_dataset(str(root)).positives] == [[0]]


def test_own_data_missing_rows_named(tmp_path):
    root = _tree(tmp_path / "gaps", ["a.jpg", "b.jpg"], ["q.jpg"])
    (root / "positions.csv").write_text("image,x,y\ndatabase/a.jpg,0,0\nqueries/q.jpg,5,0\n")
    with pytest.raises(VPRBenchError, match="database/b.jpg"):
        load_dataset(str(root))


def test_own_data_missing_folder_named(tmp_path):
    (tmp_path / "half" / "database").mkdir(parents=True)
    with pytest.raises(VPRBenchError, match="'queries'"):
        load_dataset(str(tmp_path / "half"))


def test_corridor_counts(shared_data):
    dataset = load_dataset("corridor", shared_data)
    summary = dataset.summary()
    assert (summary["database"], summary["queries"], summary["queries_with_positives"], summary["positive_pairs"]) == (111, 111, 111, 549)
