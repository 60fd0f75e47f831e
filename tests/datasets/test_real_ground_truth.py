"""Adapters checked against the real published ground truth of the big benchmarks."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from vprbench.datasets import load_dataset


@pytest.fixture
def gt(shared_data):
    return shared_data / "ground-truth"


def utm_name(easting: float, northing: float, original: str) -> str:
    # full precision, so positives can be compared exactly with the coordinates themselves
    return f"@{float(easting)!r}@{float(northing)!r}@17@T@@@{original.replace('/', '_')}@@@@@@@@.jpg"


@pytest.fixture(scope="module")
def pitts30k(shared_data, brute_force):
    """Real Pitts-30k test names and UTM coordinates, and the brute-force positives within 25 m."""
    base = shared_data / "ground-truth" / "patchnetvlad"
    data = np.load(base / "pitts30k_test.npz")
    assert int(data["posDistThr"]) == 25
    strip = lambda text: [n.removeprefix("./Pittsburgh250k/") for n in text.split()]  # noqa: E731
    db_names = strip((base / "pitts30k_imageNames_index.txt").read_text())
    q_names = strip((base / "pitts30k_imageNames_query.txt").read_text())
    return data["utmDb"], data["utmQ"], db_names, q_names, brute_force(data["utmQ"], data["utmDb"], 25.0)


def test_pitts30k_counts_and_25m_positives_match_real_coordinates(pitts30k, tmp_path, make_images):
    utm_db, utm_q, db_names, q_names, expected = pitts30k
    root = tmp_path / "pitts30k" / "images" / "test"
    db_files = [utm_name(*u, n) for u, n in zip(utm_db, db_names)]
    q_files = [utm_name(*u, n) for u, n in zip(utm_q, q_names)]
    make_images(root / "database", db_files)
    make_images(root / "queries", q_files)

    dataset = load_dataset("pitts30k", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (10000, 6816)
    assert dataset.layout == "utm-names"
    # map reader order back to the order of utmDb/utmQ, then compare with brute force at 25 m
    db_index = {name: i for i, name in enumerate(db_files)}
    q_index = {name: i for i, name in enumerate(q_files)}
    positives = dataset.positives
    for q, path in enumerate(dataset.queries):
        got = {db_index[dataset.database[d].name] for d in positives[q]}
        assert got == expected[q_index[path.name]], path.name
    summary = dataset.summary()
    assert summary["positive_pairs"] == sum(len(e) for e in expected)
    assert summary["queries_with_positives"] == sum(bool(e) for e in expected)
    assert (summary["unit"], summary["radius"], summary["domain"]) == ("metres", 25, "urban")
    assert (summary["queries_with_positives"], summary["positive_pairs"]) == (6816, 968448)


def test_pitts30k_netvlad_layout(pitts30k, tmp_path, make_images):
    """The original NetVLAD packaging: datasets/pitts30k_test.mat (named struct, 2 x N UTM) + image folders."""
    from scipy.io import savemat

    utm_db, utm_q, db_names, q_names, expected = pitts30k
    root = tmp_path / "pitts30k"
    make_images(root, db_names + q_names)
    (root / "datasets").mkdir()
    struct = {
        "whichSet": "test", "dbImageFns": np.array(db_names, dtype=object).reshape(-1, 1), "utmDb": utm_db.T,
        "qImageFns": np.array(q_names, dtype=object).reshape(-1, 1), "utmQ": utm_q.T,
        "numImages": 10000, "numQueries": 6816, "posDistThr": 25, "posDistSqThr": 625, "nonTrivPosDistSqThr": 100,
    }
    savemat(root / "datasets" / "pitts30k_test.mat", {"dbStruct": struct})
    dataset = load_dataset("pitts30k", tmp_path, strict=True)
    assert dataset.layout == "netvlad-mat"
    assert [p.relative_to(root).as_posix() for p in dataset.database[:2]] == db_names[:2]
    assert [set(p.tolist()) for p in dataset.positives] == expected


def test_st_lucia_counts_and_positives_from_utm_names(gt, tmp_path, make_images, brute_force):
    db = [str(n) for n in np.load(gt / "vlad-buff" / "st_lucia" / "st_lucia_dbImages.npy")]
    q = [str(n) for n in np.load(gt / "vlad-buff" / "st_lucia" / "st_lucia_qImages.npy")]
    root = tmp_path / "st_lucia" / "images" / "test"
    make_images(root, db + q)  # names are database/@...jpg and queries/@...jpg

    dataset = load_dataset("st-lucia", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (1549, 1464)
    utm = lambda names: np.array([[float(n.split("@")[1]), float(n.split("@")[2])] for n in names])  # noqa: E731
    db_order = {p.name: i for i, p in enumerate(dataset.database)}
    expected = brute_force(utm(q), utm(db), 25.0)
    by_name = dict(zip((n.split("/")[-1] for n in q), expected))
    db_names = [n.split("/")[-1] for n in db]
    for qi, path in enumerate(dataset.queries):
        assert {dataset.database[d].name for d in dataset.positives[qi]} == {db_names[i] for i in by_name[path.name]}
    assert all(name in db_order for name in db_names)
    assert dataset.summary()["positive_pairs"] == sum(len(e) for e in expected) == 21787
    assert dataset.summary()["queries_with_positives"] == 1464


@pytest.mark.parametrize("layout", ["release", "pose-folders"])
def test_baidu_mall_counts_and_10m_camera_centre_positives(gt, tmp_path, make_images, brute_force, layout):
    base = gt / "vlad-buff" / "baidu"
    db = [str(n) for n in np.load(base / "baidu_dbImages.npy")]
    q = [str(n) for n in np.load(base / "baidu_qImages.npy")]
    root = tmp_path / "baidu_datasets"
    folders = {"release": ("training_images_undistort", "query_images_undistort", "training_gt", "query_gt"),
               "pose-folders": ("database", "queries", "database_gt", "queries_gt")}[layout]
    make_images(root / folders[0], [n.split("/")[-1] for n in db])
    make_images(root / folders[1], [n.split("/")[-1] for n in q])
    rng = np.random.default_rng(0)
    # camera centres spread over a 60 m x 40 m mall, 3-D like the .camera files
    centres = {"db": rng.uniform([0, 0, 0], [60, 40, 3], (len(db), 3)), "q": rng.uniform([0, 0, 0], [60, 40, 3], (len(q), 3))}
    for folder, names, xyz in ((folders[2], db, centres["db"]), (folders[3], q, centres["q"])):
        (root / folder).mkdir()
        for name, c in zip(names, xyz):
            stem = name.split("/")[-1].rsplit(".", 1)[0]
            lines = ["camera", "1500 0 640", "0 1500 360", "0 0 1", "1 0 0", "0 1 0", "0 0 1", f"{float(c[0])!r} {float(c[1])!r} {float(c[2])!r}", "0"]
            (root / folder / f"{stem}.camera").write_text("\n".join(lines) + "\n")

    dataset = load_dataset("baidu-mall", tmp_path, strict=True)
    assert (len(dataset.database), len(dataset.queries)) == (689, 2292)
    db_names = [n.split("/")[-1] for n in db]
    expected = dict(zip((n.split("/")[-1] for n in q), brute_force(centres["q"], centres["db"], 10.0)))
    for qi, path in enumerate(dataset.queries):
        assert {dataset.database[d].name for d in dataset.positives[qi]} == {db_names[i] for i in expected[path.name]}
    assert dataset.summary()["radius"] == 10


def test_17places_positives_are_vpr_bench_lists_cut_to_the_references(gt, tmp_path, make_images):
    root = tmp_path / "17places"
    make_images(root / "ref", [f"{i:07d}.jpg" for i in range(406)])
    make_images(root / "query", [f"{i:07d}.jpg" for i in range(406)])
    real = gt / "vpr-bench" / "17places" / "ground_truth_new.npy"
    (root / "ground_truth_new.npy").symlink_to(real)

    dataset = load_dataset("17places", tmp_path, strict=True)
    rows = np.load(real, allow_pickle=True)
    expected = [sorted(p for p in row[1] if p < 406) for row in rows]
    assert [p.tolist() for p in dataset.positives] == expected
    # the real file names frames 406 and 407 for the last queries: dropped, as AnyLoc does
    assert max(max(row[1]) for row in rows) == 407
    assert dataset.positives[405].tolist() == [403, 404, 405]
    assert dataset.summary()["positive_pairs"] == 406 * 5 - (2 + 1) - (1 + 2)  # window of 5, cut at both ends
    # verify said 'OK, 2,024 positive pairs' and nothing of the 3 it dropped
    from vprbench.datasets import verify_dataset

    lines = verify_dataset("17places", tmp_path, sample=0).lines()
    assert "  note: 3 positives of the ground truth name references past the 406 there are: dropped, as AnyLoc " \
           "evaluates" in lines, lines


def test_gardens_point_release_and_vpr_bench_layouts_give_vpr_bench_positives(gt, tmp_path, make_images, save_rows):
    real = gt / "vpr-bench" / "GardensPointWalking" / "ground_truth_new.npy"
    rows = np.load(real, allow_pickle=True)
    clipped = [sorted(p for p in row[1] if p < 200) for row in rows]
    names = [f"Image{i:03d}.jpg" for i in range(200)]

    release = tmp_path / "release"
    make_images(release / "gardens" / "day_right", names)
    make_images(release / "gardens" / "night_right", names)
    make_images(release / "gardens" / "day_left", names)
    save_rows(release / "gardens" / "gardens_gt.npy", clipped)
    a = load_dataset("gardens-point", release, strict=True)
    assert a.layout == "folders"
    assert [p.tolist() for p in a.positives] == clipped
    assert a.database[0].parent.name == "day_right" and a.queries[0].parent.name == "night_right"

    vprbench_copy = tmp_path / "user-cache" / "vprbench"
    make_images(vprbench_copy / "gardens" / "ref", [f"{i:07d}.jpg" for i in range(200)])
    make_images(vprbench_copy / "gardens" / "query", [f"{i:07d}.jpg" for i in range(200)])
    (vprbench_copy / "gardens" / "ground_truth_new.npy").symlink_to(real)
    b = load_dataset("gardens-point", vprbench_copy, strict=True)
    assert b.layout == "vpr-bench"
    assert [p.tolist() for p in b.positives] == clipped
    # and both equal "within 2 frames" on 200 frames
    assert clipped == [list(range(max(0, i - 2), min(200, i + 3))) for i in range(200)]


def test_nordland_vpr_bench_layout_with_real_lists(gt, tmp_path, make_images):
    root = tmp_path / "Nordland"
    make_images(root / "ref", [f"{i:07d}.jpg" for i in range(27592)])
    make_images(root / "query", [f"{i:07d}.jpg" for i in range(2760)])
    real = gt / "vpr-bench" / "Nordland" / "ground_truth_new.npy"
    (root / "ground_truth_new.npy").symlink_to(real)
    dataset = load_dataset("nordland", tmp_path, strict=True)
    summary = dataset.summary()
    assert (summary["database"], summary["queries"], summary["queries_with_positives"]) == (27592, 2760, 2760)
    # the VLAD-BuFF copy of the Nordland ground truth is the same lists
    other = np.load(gt / "vlad-buff" / "Nordland" / "Nordland_gt.npy", allow_pickle=True)
    assert all(np.array_equal(p, np.asarray(o)) for p, o in zip(dataset.positives, other))
    assert summary["positive_pairs"] == 2760 * 3 - 1  # frame 10q +-1, the first query has no frame -1


def test_sped_vpr_bench_and_downloader_layouts(gt, tmp_path, make_images):
    root = tmp_path / "SPEDTEST"
    make_images(root / "ref", [f"{i:07d}.jpg" for i in range(607)])
    make_images(root / "query", [f"{i:07d}.jpg" for i in range(607)])
    (root / "ground_truth_new.npy").symlink_to(gt / "vpr-bench" / "SPEDTEST" / "ground_truth_new.npy")
    a = load_dataset("sped", tmp_path, strict=True)
    assert [p.tolist() for p in a.positives] == [[i] for i in range(607)]

    other = tmp_path / "other" / "SPEDTEST" / "images" / "test"
    names = [f"@0@{i * 1000}@@@@@{i:07d}@@@@@@@@.jpg" for i in range(607)]
    make_images(other / "database", names)
    make_images(other / "queries", names)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = load_dataset("sped", tmp_path / "other")
    assert b.layout == "utm-names"
    assert (b.summary()["unit"], b.summary()["radius"], b.summary()["radius_unit"]) == ("metres", 25, "metres")
    assert (a.summary()["unit"], a.summary()["radius"], a.summary()["radius_unit"]) == ("positives", 0, "frames")
    assert [p.tolist() for p in b.positives] == [[i] for i in range(607)]


def test_the_manifests_radius_wins_over_the_mat_files(pitts30k, tmp_path, make_images):
    """The paper's 25 m (the manifest's) is the protocol: a .mat whose posDistThr says 5 m changes no positive."""
    from scipy.io import savemat

    utm_db, utm_q, db_names, q_names, expected = pitts30k
    root = tmp_path / "pitts30k"
    make_images(root, db_names + q_names)
    (root / "datasets").mkdir()
    struct = {"dbImageFns": np.array(db_names, dtype=object).reshape(-1, 1), "utmDb": utm_db.T,
              "qImageFns": np.array(q_names, dtype=object).reshape(-1, 1), "utmQ": utm_q.T,
              "numImages": 10000, "numQueries": 6816, "posDistThr": 5}
    savemat(root / "datasets" / "pitts30k_test.mat", {"dbStruct": struct})
    dataset = load_dataset("pitts30k", tmp_path, strict=True)
    assert dataset.layout == "netvlad-mat"
    assert [set(p.tolist()) for p in dataset.positives] == expected
