"""Which datasets are traverses: capture orders from manifests and own frame numbers, and one
clear refusal for the rest (Pitts-30k, Tokyo 24/7)."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from vprbench.datasets import Dataset, GroundTruth, dataset_manifest, dataset_manifests, load_dataset
from vprbench.datasets.manifest import DatasetManifest
from vprbench.datasets.traverse import traverse_orders
from vprbench.errors import VPRBenchError

TRAVERSES = {"corridor": "listing", "nordland": "listing", "gardens-point": "listing", "st-lucia": "file-name-frame"}


def test_manifests_name_the_traverses_and_nothing_else():
    found = {name: m.sequence_order for name, m in dataset_manifests().items() if m.sequence_order}
    assert found == TRAVERSES
    assert dataset_manifest("pitts30k").sequence_order == "" and dataset_manifest("tokyo247").sequence_order == ""
    with pytest.raises(VPRBenchError, match="sequence_order must be one of"):
        DatasetManifest.from_toml('name = "x"\ntitle = "x"\nlayout = "own"\ndirectory = "x"\ndomain = "x"\n'
                                  'unit = "metres"\nsequence_order = "shuffled"\n', "x.toml")


def test_corridor_is_a_traverse_as_listed(shared_data):
    orders = traverse_orders(load_dataset("corridor", shared_data))
    assert orders["database"].tolist() == list(range(111)) == orders["queries"].tolist()


def fake(name, order, database, queries, kind="benchmark", unit="positives"):
    gt = GroundTruth(unit="positives", positive_lists=[np.array([0])] * len(queries)) if unit == "positives" else \
        GroundTruth(unit=unit, radius=1, database_positions=np.zeros((len(database), 2)),
                    query_positions=np.zeros((len(queries), 2)))
    return Dataset(name=name, database=database, queries=queries, ground_truth=gt, kind=kind, sequence_order=order)


def test_st_lucia_is_ordered_by_the_frame_in_its_file_names():
    names = ["@0499637.67@6958017.95@56@J@-27.50149@0152.99633@210809_1210_02647@@@@@@@@.jpg",
             "@0499638.33@6958010.19@56@J@-27.50156@0152.99633@210809_1210_02673@@@@@@@@.jpg",
             "@0499639.15@6958018.87@56@J@-27.50148@0152.99634@210809_1210_00582@@@@@@@@.jpg"]
    paths = [Path("queries") / n for n in names]
    orders = traverse_orders(fake("st-lucia", "file-name-frame", paths, paths))
    assert orders["queries"].tolist() == [2, 0, 1]
    broken = [Path("queries/@0499637.67@6958017.95@56@J@-27.5@152.9@@@@.jpg")]
    with pytest.raises(VPRBenchError, match="has no frame number in its 7th '@' field"):
        traverse_orders(fake("st-lucia", "file-name-frame", broken, broken))


@pytest.mark.parametrize("name", ["pitts30k", "tokyo247"])
def test_unordered_benchmarks_are_refused_saying_why(name):
    dataset = fake(name, dataset_manifest(name).sequence_order, [Path("a.jpg")], [Path("b.jpg")])
    with pytest.raises(VPRBenchError) as error:
        traverse_orders(dataset, "Sequence stage 'seqslam'")
    message = str(error.value)
    assert message.startswith("Sequence stage 'seqslam' needs a dataset whose database and queries are ordered traverses")
    assert f"{name!r} is not one" in message and "separate photographs" in message and "\n" not in message


def write_images(folder: Path, names):
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.fromarray(np.full((8, 8, 3), 10 * i + 5, np.uint8)).save(folder / name)


def test_own_data_is_a_traverse_in_frame_order_only_with_frame_numbers(tmp_path):
    root = tmp_path / "mine"
    write_images(root / "database", ["a.jpg", "b.jpg", "c.jpg"])
    write_images(root / "queries", ["x.jpg", "y.jpg"])
    images = ["database/a.jpg", "database/b.jpg", "database/c.jpg", "queries/x.jpg", "queries/y.jpg"]
    pd.DataFrame({"image": images, "frame": [2, 0, 1, 7, 3]}).to_csv(root / "positions.csv", index=False)
    (root / "dataset.toml").write_text("radius = 1\n")
    orders = traverse_orders(load_dataset(str(root)))
    assert orders["database"].tolist() == [1, 2, 0] and orders["queries"].tolist() == [1, 0]
    pd.DataFrame({"image": images, "x": [0, 1, 2, 0, 1], "y": [0] * 5}).to_csv(root / "positions.csv", index=False)
    with pytest.raises(VPRBenchError, match="'mine' is not one \\(its positions are not frame numbers\\)"):
        traverse_orders(load_dataset(str(root)))
