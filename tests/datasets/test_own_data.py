"""The user's own data: folders + positions.csv (metres, lat/lon, frames) or UTM file names."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError


@pytest.fixture
def mydata(tmp_path, make_images):
    root = tmp_path / "mydata"
    make_images(root / "database", [f"{i:03d}.jpg" for i in range(5)])
    make_images(root / "queries", ["q0.jpg", "q1.jpg"])
    return root


def images(root):
    return [f"database/{i:03d}.jpg" for i in range(5)] + ["queries/q0.jpg", "queries/q1.jpg"]


def test_latitude_longitude_become_metres(mydata):
    # database every 0.0001 degree of latitude (about 11.1 m) north of 48.85 N; queries at 0 and 15 m
    lat = [48.85 + 0.0001 * i for i in range(5)] + [48.85, 48.85 + 15 / 111_200]
    pd.DataFrame({"image": images(mydata), "latitude": lat, "longitude": [2.35] * 7}).to_csv(mydata / "positions.csv", index=False)
    dataset = load_dataset(str(mydata))
    northing = dataset.ground_truth.database_positions[:, 1]
    assert np.diff(northing) == pytest.approx(11.12, abs=0.02)
    # 25 m default radius: query 0 reaches 0, 11, 22 m; query 1 (15 m) reaches 0..40 m
    assert [p.tolist() for p in dataset.positives] == [[0, 1, 2], [0, 1, 2, 3]]
    assert dataset.summary()["unit"] == "metres" and dataset.summary()["radius"] == 25


def test_several_kinds_of_position_say_which_is_used(mydata):
    table = pd.DataFrame({"image": images(mydata), "x": range(7), "y": 0, "frame": range(7)})
    table.to_csv(mydata / "positions.csv", index=False)
    with pytest.warns(UserWarning, match=r"several kinds of position: x,y \(metres\) is used, frame ignored"):
        assert load_dataset(str(mydata)).ground_truth.unit == "metres"


def test_frames_need_a_radius_and_use_it(mydata):
    pd.DataFrame({"image": images(mydata), "frame": [0, 1, 2, 3, 4, 0, 4]}).to_csv(mydata / "positions.csv", index=False)
    with pytest.raises(VPRBenchError, match="radius = N"):
        load_dataset(str(mydata))
    (mydata / "dataset.toml").write_text('name = "mine"\nradius = 1\ndomain = "indoor"\n')
    dataset = load_dataset(str(mydata))
    assert [p.tolist() for p in dataset.positives] == [[0, 1], [3, 4]]
    assert (dataset.name, dataset.domain, dataset.ground_truth.unit) == ("mine", "indoor", "frames")


def test_utm_in_file_names(tmp_path, make_images):
    root = tmp_path / "utm"
    make_images(root / "database", [f"@{500000 + 30 * i}.0@4000000.0@31@U@@@{i}@.jpg" for i in range(4)])
    make_images(root / "queries", ["@500040.0@4000000.0@31@U@@@q@.jpg"])
    dataset = load_dataset(str(root))
    assert [p.tolist() for p in dataset.positives] == [[1, 2]]  # 10 m and 20 m; 40 m and 50 m are out


def test_missing_rows_and_bad_values_are_named(mydata):
    table = pd.DataFrame({"image": images(mydata)[:-1], "x": range(6), "y": 0})
    table.to_csv(mydata / "positions.csv", index=False)
    with pytest.raises(VPRBenchError, match=r"no position for 1 image\(s\), e.g. \['queries/q1.jpg'\]"):
        load_dataset(str(mydata))
    table = pd.DataFrame({"image": images(mydata), "x": ["1", "2", "oops", "4", "5", "6", ""], "y": 0})
    table.to_csv(mydata / "positions.csv", index=False)
    with pytest.raises(VPRBenchError, match=r"non-numeric positions in 2 row\(s\), e.g. for \['database/002.jpg', 'queries/q1.jpg'\]"):
        load_dataset(str(mydata))
    # one row with latitude and longitude swapped: named, as the other bad rows are (was: no row named)
    table = pd.DataFrame({"image": images(mydata), "latitude": -33.87, "longitude": 151.21})
    table.loc[5, ["latitude", "longitude"]] = [151.21, -33.87]
    table.to_csv(mydata / "positions.csv", index=False)
    with pytest.raises(VPRBenchError, match=r"latitudes beyond \+-84 degrees \(outside UTM\) or longitudes beyond \+-180 "
                                            r"in 1 row\(s\), e.g. for \['queries/q0.jpg'\]; fix those rows"):
        load_dataset(str(mydata))


def test_no_positions_and_no_utm_names(mydata):
    with pytest.raises(VPRBenchError, match="Cannot read UTM coordinates from the file name '000.jpg'.*positions.csv"):
        load_dataset(str(mydata))


def test_missing_queries_folder_is_named(tmp_path, make_images):
    make_images(tmp_path / "mine" / "database", ["a.jpg"])
    with pytest.raises(VPRBenchError, match=r"expected folder 'queries' under .*mine \(layout 'own'\) but it is missing. Put the database images"):
        load_dataset(str(tmp_path / "mine"))


def test_images_in_subfolders_are_named(tmp_path, make_images):
    root = tmp_path / "mine"
    make_images(root / "database", ["run1/a.jpg", "run2/deeper/b.jpg", "notes/readme.txt"])
    make_images(root / "queries", ["@0.0@0.0@.jpg"])
    with pytest.raises(VPRBenchError, match=r"no images in .*mine/database; .*mine/database has images only in "
                                            r"its subfolders \('run1', 'run2'\): move them up into it\.$"):
        load_dataset(str(root))
    make_images(root / "database", ["@0.0@5.0@.jpg"])  # some at the top: the rest are left out, with a warning
    with pytest.warns(UserWarning, match=r"mine/database: the images in its subfolders \('run1', 'run2'\) are not read"):
        assert load_dataset(str(root)).database[0].name == "@0.0@5.0@.jpg"


def test_verify_own_data(mydata):
    from vprbench.datasets import verify_dataset

    pd.DataFrame({"image": images(mydata), "x": [0, 10, 20, 30, 40, 0, 400], "y": 0}).to_csv(mydata / "positions.csv", index=False)
    report = verify_dataset(str(mydata))
    assert report.ok and report.layout == "own" and report.images_checked == 7
    assert report.warnings == ["1 query without a positive (counted as failures in Recall@K)"]
    assert "7 images decoded" in report.lines()[-1] and "radius 25 metres" in report.lines()[-1]
    assert report.summary["positive_pairs"] == 3
    missing = verify_dataset(str(mydata / "nope"))
    assert not missing.ok and "does not exist" in missing.problems[0]


def test_counts_and_radii_read_in_the_singular_and_plural(mydata, capsys, monkeypatch):
    from vprbench.cli.main import main
    from vprbench.text import plural, quantity

    assert [plural(n, "frame") for n in (0, 1, 2, 1.0, 2.5)] == ["0 frames", "1 frame", "2 frames", "1 frame", "2.5 frames"]
    assert (plural(1, "query"), plural(3, "query")) == ("1 query", "3 queries")
    assert (quantity(1, "frames"), quantity(0, "frames"), quantity(1, "metres"), quantity(25, "metres")) == \
        ("1 frame", "0 frames", "1 metre", "25 metres")
    assert (quantity(None, "frames"), quantity(3, None)) == ("–", "3")
    pd.DataFrame({"image": images(mydata), "frame": [0, 1, 2, 3, 4, 0, 4]}).to_csv(mydata / "positions.csv", index=False)
    (mydata / "dataset.toml").write_text('name = "mine"\nradius = 1\n')
    monkeypatch.chdir(mydata.parent)  # a relative path is shown as the folder it is (was: 'OK at mydata')
    assert main(["datasets", "verify", mydata.name]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"mine: OK at {mydata.resolve()} (layout own)")  # the dataset's name, then where it is
    assert "2 queries, 2 with a positive, 4 positive pairs (frames, radius 1 frame); 7 images decoded" in out, out
    assert main(["datasets", "info", str(mydata)]) == 0
    assert "within 1 frame " in capsys.readouterr().out
    assert main(["datasets", "info", mydata.name, "--json"]) == 0  # was: the root as typed, 'mydata'
    assert json.loads(capsys.readouterr().out)["root"] == str(mydata.resolve())


def test_positions_either_side_of_a_utm_zone_boundary_share_one_plane():
    """Longitude 6 E divides UTM zones 31 and 32: two points 157 m apart across it are 157 m apart in
    metres (each in its own zone's eastings they would be hundreds of kilometres apart)."""
    from vprbench.datasets.layouts.own_data import latlon_to_metres

    metres = latlon_to_metres(np.array([45.0, 45.0]), np.array([5.999, 6.001]))
    assert np.linalg.norm(metres[0] - metres[1]) == pytest.approx(157.3, abs=0.5)


def test_an_evaluation_lists_and_names_each_split_once(shared_data, tmp_path, cli, monkeypatch):
    """Was: `vprbench evaluate` on a folder of one's own read it twice (for its spec's protocol, then for
    the run), and made every split's image names twice (for the stores, then for the record's dataset
    identity; 0.6 s per split at 92k images). Each split is now listed once and named once."""
    import shutil
    from collections import Counter

    from vprbench.datasets import identity
    from vprbench.datasets.layouts import own_data
    from vprbench.evaluation import extract

    own, rows = tmp_path / "own", ["image,frame"]
    for i in range(4):
        for split, source in (("database", "ref"), ("queries", "query")):
            (own / split).mkdir(parents=True, exist_ok=True)
            shutil.copy(shared_data / "corridor" / source / f"{i:07d}.jpg", own / split / f"{i}.jpg")
            rows.append(f"{split}/{i}.jpg,{i}")
    (own / "positions.csv").write_text("\n".join(rows) + "\n")
    (own / "dataset.toml").write_text("radius = 1\n")
    listed, named = Counter(), Counter()
    list_images, image_names = own_data.list_images, identity.image_names

    def counted_list(folder, **options):
        listed[folder.name] += 1
        return list_images(folder, **options)

    def counted_names(paths, root):
        named[paths[0].parent.name] += 1
        return image_names(paths, root)

    monkeypatch.setattr(own_data, "list_images", counted_list)
    for module in (identity, extract):
        monkeypatch.setattr(module, "image_names", counted_names)
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", own, "--k", "1", "--cache-dir", tmp_path / "cache")
    assert code == 0 and "descriptors computed now: 8" in " ".join(out.split()), err
    assert (listed, named) == ({"database": 1, "queries": 1}, {"database": 1, "queries": 1})
