"""UTM zones in file names: easting/northing compare only within one zone (number and hemisphere)."""
from __future__ import annotations

import numpy as np
import pytest

from vprbench.datasets import load_dataset

# a database image in zone 11 at easting 500000 and a query in zone 10 at 500005: ~530 km apart
FAR_DB = "@0500000.00@4178910.00@11@S@37.74@-117.00@far@@@@@@@@.jpg"
FAR_Q = "@0500005.00@4178910.00@10@S@37.74@-123.00@q-far@@@@@@@@.jpg"
# two zone-10 images 10 m apart (another letter band of the same hemisphere: one northing system)
NEAR_DB = "@0600000.00@4178910.00@10@T@37.74@-121.86@near@@@@@@@@.jpg"
NEAR_Q = "@0600010.00@4178910.00@10@S@37.74@-121.86@q-near@@@@@@@@.jpg"


@pytest.fixture
def two_zones(tmp_path, make_images):
    root = tmp_path / "two-zones"
    make_images(root / "database", [FAR_DB, NEAR_DB])
    make_images(root / "queries", [FAR_Q, NEAR_Q])
    return root


def test_a_pair_joining_two_zones_is_no_positive_and_verify_says_the_zones(two_zones, cli):
    with pytest.warns(UserWarning, match=r"1 query-database pair\(s\) within 25 m by easting/northing alone lie in "
                                         r"different UTM zones, e.g. queries/@0500005.*\(zone 10S\) and "
                                         r"database/@0500000.*\(zone 11S\)"):
        dataset = load_dataset(str(two_zones))
    names = lambda split, idx: [getattr(dataset, split)[i].name for i in idx]  # noqa: E731
    by_query = {q.name: names("database", p) for q, p in zip(dataset.queries, dataset.positives)}
    assert by_query == {FAR_Q: [], NEAR_Q: [NEAR_DB]}  # was: FAR_Q had FAR_DB, ~530 km away
    with pytest.warns(UserWarning, match="lie in different UTM zones"):
        code, out, err = cli("datasets", "verify", two_zones)
    assert code == 0, out + err
    assert "1 positive pair " in out  # was: 2
    assert "positions span 2 UTM zones (10 north, 11 north); positives are within one zone" in out
    with pytest.warns(UserWarning):
        code, out, _ = cli("datasets", "verify", two_zones, "--json")
    assert __import__("json").loads(out)["utm_zones"] == ["10 north", "11 north"]


def test_hemispheres_are_two_zones_and_bands_of_one_hemisphere_one(tmp_path, make_images):
    """Zone 56 band J (south) and band P (north) share number and easting, not the northing system."""
    root = tmp_path / "hemispheres"
    make_images(root / "database", ["@0500000.00@4000000.00@56@J@@@a@.jpg", "@0500000.00@4000000.00@56@K@@@b@.jpg"])
    make_images(root / "queries", ["@0500000.00@4000000.00@56@P@@@q@.jpg", "@0500000.00@4000000.00@56@M@@@r@.jpg"])
    with pytest.warns(UserWarning, match="2 query-database pair"):
        dataset = load_dataset(str(root))
    assert [q.name.split("@")[4] for q in dataset.queries] == ["M", "P"]
    assert [p.tolist() for p in dataset.positives] == [[0, 1], []]  # M: both southern images; P: none


def test_a_zone_kept_through_a_protocol_that_keeps_or_swaps_images(two_zones):
    from vprbench.datasets.protocol import _keep_database, _keep_queries, _swapped

    with pytest.warns(UserWarning):
        gt = load_dataset(str(two_zones)).ground_truth
    assert [p.tolist() for p in _keep_queries(gt, np.array([True, False])).positives()] == [[]]
    assert [p.tolist() for p in _keep_database(gt, np.array([True, False])).positives()] == [[], []]
    assert [p.tolist() for p in _swapped(gt, 2).positives()] == [[], [1]]


@pytest.mark.parametrize("names, said", [
    (["@0@0@.jpg", "@0@5@10@S@@@b@.jpg"], r"queries/@0@5@10@S@@@b@.jpg names UTM zone 10S but database/@0@0@.jpg "
                                          r"names no zone: their positions cannot be compared; give every file name "
                                          r"its zone, or none\."),
    (["@0@0@10@S@@@a@.jpg", "@0@5@61@S@@@b@.jpg"], r"Cannot read the UTM zone '61S' from the file name "
                                                   r"'@0@5@61@S@@@b@.jpg': expected a zone number 1-60"),
    (["@0@0@10@S@@@a@.jpg", "@0@5@10@@@@b@.jpg"], r"Cannot read the UTM zone '10' from the file name"),
])
def test_zones_that_cannot_be_compared_are_refused_in_one_line(tmp_path, make_images, cli, names, said):
    root = tmp_path / "bad"
    make_images(root / "database", names[:1])
    make_images(root / "queries", names[1:])
    code, out, err = cli("datasets", "verify", root)
    assert code != 0 and "Traceback" not in out + err
    error = [line for line in out.splitlines() if "error:" in line]
    assert len(error) == 1 and __import__("re").search(said, error[0]), out + err


def test_names_without_a_zone_are_one_plane_as_before(tmp_path, make_images):
    """SPED as the downloader formats it: '@0@<index * 1000>@@@@@<index>@...' (no zone)."""
    root = tmp_path / "sped"
    make_images(root / "database", [f"@0@{i * 1000}@@@@@{i:07d}@@@@@@@@.jpg" for i in range(3)])
    make_images(root / "queries", [f"@0@{i * 1000}@@@@@{i:07d}@@@@@@@@.jpg" for i in range(3)])
    assert [p.tolist() for p in load_dataset(str(root)).positives] == [[0], [1], [2]]


def _both_rules(db_names, q_names):
    """Positives from the names with zones (this rule) and by easting/northing alone (the field's code)."""
    from pathlib import Path

    from vprbench.datasets.layouts.utm_zones import positions_from_names
    from vprbench.datasets.model import GroundTruth

    paths = [Path(n) for n in list(db_names) + list(q_names)]
    positions, zones = positions_from_names(paths, Path("."))
    n = len(db_names)
    zoned = GroundTruth("metres", 25.0, positions[:n], positions[n:], database_zones=zones[:n], query_zones=zones[n:])
    plane = GroundTruth("metres", 25.0, positions[:n], positions[n:])
    return zones, zoned.positives(), plane.positives()


def test_st_lucias_real_names_keep_every_positive(shared_data):
    """The real St Lucia name lists (the shared ground truth whose names carry zones): one zone, 56 J,
    and the same 21,787 positive pairs as easting/northing alone."""
    base = shared_data / "ground-truth" / "vlad-buff" / "st_lucia"
    db, q = (np.load(base / f"st_lucia_{s}Images.npy") for s in ("db", "q"))
    zones, zoned, plane = _both_rules(db, q)
    assert set(zones) == {"56 south"}
    assert all(np.array_equal(a, b) for a, b in zip(zoned, plane)) and sum(map(len, zoned)) == 21787


def test_cities_in_several_zones_keep_every_positive_as_msls_val_names_them():
    """MSLS val as format_mapillary.py names it (each image in its own zone from utm.from_latlon): San
    Francisco (zone 10) and Copenhagen, across 12 E (zones 32 and 33). No pair within 25 m joins two
    zones, so positives are those of easting/northing alone."""
    import utm

    rng = np.random.default_rng(0)
    lat = np.concatenate([rng.uniform(37.70, 37.72, 1500), rng.uniform(55.60, 55.61, 3000)])
    lon = np.concatenate([rng.uniform(-122.45, -122.43, 1500), rng.uniform(11.995, 12.005, 3000)])
    names = []
    for i, (la, lo) in enumerate(zip(lat, lon)):
        e, n, number, letter = utm.from_latlon(la, lo)
        names.append(f"@{e:010.2f}@{n:010.2f}@{number:02d}@{letter}@{la:.5f}@{lo:.5f}@{i}@@@@@@@@.jpg")
    zones, zoned, plane = _both_rules(names[::3], [m for i, m in enumerate(names) if i % 3])
    assert set(zones) == {"10 north", "32 north", "33 north"}
    assert all(np.array_equal(a, b) for a, b in zip(zoned, plane)) and sum(map(len, zoned)) > 1000


def test_queries_of_two_zones_are_two_places_in_the_bootstrap(tmp_path, make_images):
    """The bootstrap's places group queries within the radius: as for positives, only within one zone."""
    from vprbench.evaluation.blocks import for_dataset

    root = tmp_path / "places"
    make_images(root / "database", ["@0500000.00@4178910.00@10@S@@@a@.jpg", "@0500000.00@4178910.00@11@S@@@b@.jpg"])
    make_images(root / "queries", ["@0500001.00@4178910.00@10@S@@@q@.jpg", "@0500001.00@4178910.00@11@S@@@r@.jpg"])
    with pytest.warns(UserWarning):
        dataset = load_dataset(str(root))
    assert [p.tolist() for p in dataset.positives] == [[0], [1]]
    assert for_dataset(dataset).places.tolist() == [0, 1]  # was: [0, 0], one place ~530 km wide
