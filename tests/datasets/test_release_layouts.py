"""Miniatures of the authors' release layouts (as their loaders read them), with hand-checked positives."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pandas as pd
import pytest

from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError


def test_hawkins_uses_rows_of_pose_topic_list(tmp_path, make_images):
    root = tmp_path / "hawkins_long_corridor"
    make_images(root / "db_images", [f"{i}.png" for i in range(127)])  # natural order: 0, 1, ..., 10, 11
    make_images(root / "q_images", [f"{i}.png" for i in range(118)])
    make_images(root / "images", [f"{i}.png" for i in range(3)])  # all frames: not used
    poses = np.zeros((250, 7))
    poses[:127, 0] = np.arange(127)  # database every metre along x
    poses[127:245, 0] = 200 - np.arange(118)  # queries walk back, from x = 200 to x = 83
    poses[245:, 0] = 5  # rows past 245 are not queries
    np.save(root / "pose_topic_list.npy", poses)

    dataset = load_dataset("hawkins", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (127, 118)
    assert dataset.database[10].name == "10.png"
    positives = dataset.positives
    assert positives[0].tolist() == []  # x = 200: far past the database (x <= 126)
    assert positives[117].tolist() == list(range(75, 92))  # x = 83: database x in [75, 91]
    # queries x = 200..83; those with x <= 134 have a positive: x = 134..83 -> 52 queries
    assert dataset.summary()["queries_with_positives"] == 52
    assert dataset.summary()["domain"] == "degraded"


def test_hawkins_folder_short_of_pose_rows_names_the_mismatch(tmp_path, make_images):
    root = tmp_path / "hawkins_long_corridor"
    make_images(root / "db_images", [f"{i}.png" for i in range(126)])
    make_images(root / "q_images", [f"{i}.png" for i in range(118)])
    np.save(root / "pose_topic_list.npy", np.zeros((245, 2)))
    with pytest.raises(Exception, match=r"rows 0:127 \(127 poses\) but 126 database images"):
        load_dataset("hawkins", tmp_path)


def test_laurel_caverns_skips_rows_141_to_228(tmp_path, make_images):
    root = tmp_path / "laurel_caverns"
    make_images(root / "db_images", [f"{i:04d}.png" for i in range(141)])
    make_images(root / "q_images", [f"{i:04d}.png" for i in range(112)])
    poses = np.full((341, 3), 1000.0)
    poses[:141, :2] = np.stack([np.arange(141) * 2.0, np.zeros(141)], 1)  # database every 2 m
    poses[229:341, :2] = np.stack([np.arange(112) * 2.0 + 1.0, np.full(112, 3.0)], 1)  # 3 m to the side
    # an object array with a topic-name column: only the first two columns are read
    table = np.empty((341, 4), dtype=object)
    table[:, :3], table[:, 3] = poses, "/camera/image"
    np.save(root / "pose_topic_list.npy", table, allow_pickle=True)

    dataset = load_dataset("laurel-caverns", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (141, 112)
    # query 10 at (21, 3): database x within sqrt(64 - 9) = 7.42 m of 21 -> x = 14..28 -> indices 7..14
    assert dataset.positives[10].tolist() == list(range(7, 15))
    assert dataset.summary()["domain"] == "subt"


@pytest.mark.parametrize("name,folder", [("nardo-air", "test_40_midref_rot0"), ("nardo-air-r", "test_40_midref_rot90")])
def test_nardo_air_top5_columns_are_positives(tmp_path, make_images, name, folder):
    root = tmp_path / folder
    make_images(root / "reference_images", [f"{i:05d}.png" for i in range(102)])
    make_images(root / "query_images", [f"{i:05d}.png" for i in range(71)])
    table = {"query_ind": np.arange(71)}
    for k in range(1, 6):
        table[f"top_{k}_ref_ind"] = (np.arange(71) + k - 1) % 102
    pd.DataFrame(table).to_csv(root / "gt_matches.csv", index=False)
    (root / "reference.csv").write_text("")
    (root / "query.csv").write_text("")

    dataset = load_dataset(name, tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (102, 71)
    assert dataset.positives[70].tolist() == [70, 71, 72, 73, 74]
    assert dataset.summary()["positive_pairs"] == 71 * 5
    assert dataset.summary()["domain"] == "aerial"


def test_vp_air_appends_10000_distractors_to_the_database(tmp_path, make_images, save_rows):
    root = tmp_path / "VPAir"
    make_images(root / "reference_views", [f"{i:05d}.png" for i in range(1, 2707)])
    make_images(root / "distractors", [f"{i:05d}.png" for i in range(10000)])
    make_images(root / "queries", [f"{i:05d}.png" for i in range(1, 2707)])
    (root / "distractors_temp").mkdir()
    save_rows(root / "vpair_gt.npy", [range(max(0, i - 3), min(2706, i + 4)) for i in range(2706)])

    dataset = load_dataset("vp-air", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (12706, 2706)
    assert dataset.database[2705].parent.name == "reference_views"
    assert dataset.database[2706].parent.name == "distractors"
    assert dataset.positives[0].tolist() == [0, 1, 2, 3]
    assert max(int(p.max()) for p in dataset.positives) == 2705  # positives are references only
    assert dataset.summary()["positive_pairs"] == 2706 * 7 - 2 * (3 + 2 + 1)


def test_mid_atlantic_ridge_reads_rows_from_101(tmp_path, make_images, save_rows):
    root = tmp_path / "eiffel"
    make_images(root / "db_images", [f"{i:03d}.png" for i in range(65)])
    make_images(root / "q_images", [f"{i:03d}.png" for i in range(101)])
    # 101 rows the loader skips, then one row per query
    save_rows(root / "eiffel_gt.npy", [[64]] * 101 + [[r % 65] for r in range(101)])

    dataset = load_dataset("mid-atlantic-ridge", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (65, 101)
    assert [int(p[0]) for p in dataset.positives[:3]] == [0, 1, 2]
    assert dataset.positives[100].tolist() == [35]
    assert (dataset.summary()["domain"], dataset.summary()["radius"]) == ("underwater", 0.3)


def test_oxford_netvlad_mat(tmp_path, make_images):
    from scipy.io import savemat

    root = tmp_path / "Oxford_Robotcar"
    make_images(root / "oxDataPart" / "2-s", ["0.png", "1.png", "2.png", "10.png"])
    make_images(root / "oxDataPart" / "1-m", [f"{i}.png" for i in range(3)])
    # the release stores a 1x8 cell array; names are a space-padded char matrix, locations N x 2
    db_names = np.array([f"2-s/{i}.png" for i in range(3)] + ["2-s/10.png"])  # others padded to its length
    q_names = np.array(["1-m/0.png", "1-m/1.png", "1-m/2.png"])
    loc_db = np.array([[0.0, 0], [20, 0], [40, 0], [60, 0]])
    loc_q = np.array([[0.0, 10], [45, 0], [200, 0]])
    struct = np.empty((1, 8), dtype=object)
    for k, value in enumerate((db_names, loc_db, q_names, loc_q, 4, 3, 25, 625)):
        struct[0, k] = value
    savemat(root / "oxdatapart.mat", {"dbStruct": struct})

    with pytest.warns(UserWarning) as caught:
        dataset = load_dataset("oxford", tmp_path)
    said = " | ".join(str(w.message) for w in caught)  # a miniature: both splits differ from the manifest
    assert "4 database images" in said and "expects 213" in said and "3 query images" in said and "expects 251" in said
    assert [p.name for p in dataset.database] == ["0.png", "1.png", "2.png", "10.png"]
    assert [p.tolist() for p in dataset.positives] == [[0, 1], [1, 2, 3], []]


@pytest.mark.parametrize("name,split,counts", [("tokyo247", "test", (75984, 315)), ("pitts250k", "test", (83952, 8280)), ("msls-val", "val", (18871, 740))])
def test_downloader_layout_miniatures(tmp_path, make_images, name, split, counts):
    from vprbench.datasets import dataset_manifest

    manifest = dataset_manifest(name)
    assert (manifest.database_count, manifest.query_count, manifest.radius) == (*counts, 25)
    base = tmp_path / manifest.directory / "images" / split
    make_images(base / "database", [f"@{500000 + 10 * i:.2f}@{4000000:.2f}@54@S@@@db{i}@@@@@@@@.jpg" for i in range(10)])
    make_images(base / "queries", ["@500024.00@4000000.00@54@S@@@q0@@@@@@@@.jpg", "@600000.00@4000000.00@54@S@@@q1@@@@@@@@.jpg"])
    with pytest.warns(UserWarning) as caught:
        dataset = load_dataset(name, tmp_path)
    said = " | ".join(str(w.message) for w in caught)
    assert "10 database images" in said and f"expects {counts[0]}" in said and "2 query images" in said and f"expects {counts[1]}" in said
    assert [p.tolist() for p in dataset.positives] == [[0, 1, 2, 3, 4], []]  # 24 m from x = 0..40, not 50


def test_corridor_real_data(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dataset = load_dataset("corridor", shared_data, strict=True)
    summary = dataset.summary()
    assert (summary["database"], summary["queries"], summary["queries_with_positives"]) == (111, 111, 111)


@pytest.mark.parametrize("db_names, q_names, said", [
    (["a.png", "b.png", "a.png"], ["q.png"], "'a.png' twice (in the database and in the database)"),
    (["a.png", "b.png"], ["q.png", "./b.png"], "'b.png' twice (in the database and in the queries)"),
])
def test_oxford_netvlad_mat_refuses_an_image_named_twice(tmp_path, make_images, db_names, q_names, said):
    # counted twice it weighs double; a query among the database would retrieve itself
    from scipy.io import savemat

    root = tmp_path / "Oxford_Robotcar"
    make_images(root / "oxDataPart", ["a.png", "b.png", "q.png"])
    struct = np.empty((1, 8), dtype=object)
    values = (np.array(db_names, dtype=object).reshape(-1, 1), np.zeros((len(db_names), 2)),
              np.array(q_names, dtype=object).reshape(-1, 1), np.zeros((len(q_names), 2)), len(db_names), len(q_names), 25, 625)
    for k, value in enumerate(values):
        struct[0, k] = value
    savemat(root / "oxdatapart.mat", {"dbStruct": struct})
    with pytest.raises(VPRBenchError, match=re.escape(f"oxdatapart.mat names {said}")):
        load_dataset("oxford", tmp_path)


def test_vpr_bench_layout_lists_unpadded_frame_names_in_natural_order(tmp_path, make_images, save_rows):
    """ground_truth_new.npy numbers images in natural order (2.jpg before 10.jpg): a plain sort of
    either folder would pair the lists with other images."""
    root = tmp_path / "corridor"
    names = [f"{i}.jpg" for i in range(111)]
    make_images(root / "ref", names)
    make_images(root / "query", names)
    save_rows(root / "ground_truth_new.npy", [[i] for i in range(111)])
    dataset = load_dataset("corridor", tmp_path)
    assert [p.name for p in dataset.queries] == names and [p.name for p in dataset.database] == names
    assert [dataset.database[p[0]].name for p in dataset.positives] == names
