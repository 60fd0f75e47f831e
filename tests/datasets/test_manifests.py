"""Every shipped manifest is complete enough for list/info/verify and points at a known layout."""
from __future__ import annotations

from pathlib import Path

import pytest

from vprbench.datasets import dataset_manifests, how_to_get
from vprbench.datasets.layouts import candidates
from vprbench.datasets.layouts.base import EXPECTS, LAYOUTS

ANYLOC = {
    # name: (directory, domain, database, queries, radius, radius unit)
    "baidu-mall": ("baidu_datasets", "indoor", 689, 2292, 10, "metres"),
    "gardens-point": ("gardens", "indoor", 200, 200, 2, "frames"),
    "17places": ("17places", "indoor", 406, 406, 2, "frames"),
    "pitts30k": ("pitts30k", "urban", 10000, 6816, 25, "metres"),
    "st-lucia": ("st_lucia", "urban", 1549, 1464, 25, "metres"),
    "oxford": ("Oxford_Robotcar", "urban", 213, 251, 25, "metres"),
    "hawkins": ("hawkins_long_corridor", "degraded", 127, 118, 8, "metres"),
    "laurel-caverns": ("laurel_caverns", "subt", 141, 112, 8, "metres"),
    "nardo-air": ("test_40_midref_rot0", "aerial", 102, 71, 60, "metres"),
    "nardo-air-r": ("test_40_midref_rot90", "aerial", 102, 71, 60, "metres"),
    "vp-air": ("VPAir", "aerial", 12706, 2706, 3, "frames"),
    "mid-atlantic-ridge": ("eiffel", "underwater", 65, 101, 0.3, "metres"),
}


def test_the_twelve_anyloc_datasets_match_the_paper_and_release_names():
    manifests = dataset_manifests()
    for name, (directory, domain, db, q, radius, unit) in ANYLOC.items():
        m = manifests[name]
        assert (m.directory, m.domain, m.database_count, m.query_count, m.radius) == (directory, domain, db, q, radius), name
        assert (m.radius_unit or m.unit) == unit, name


@pytest.mark.parametrize("name", sorted(dataset_manifests()))
def test_manifest_is_complete(name):
    m = dataset_manifests()[name]
    assert m.title and m.domain and m.citation and m.source and m.notes
    assert m.database_count and m.query_count and m.radius is not None
    # how to get it from the manifest, where it goes said once by how_to_get
    assert m.download or (m.instructions and "place it" not in m.instructions.lower())
    told = how_to_get(m, Path("/data"))
    assert f"/data/{m.directory}" in told and told.lower().count("place it") == (0 if m.download else 1)
    for candidate in candidates(m):
        assert candidate.layout in LAYOUTS
        assert EXPECTS[candidate.layout](candidate.options), f"{name}: layout {candidate.layout} expects nothing"


def test_other_benchmarks_are_there():
    assert {"nordland", "tokyo247", "sped", "msls-val", "pitts250k", "corridor"} <= set(dataset_manifests())
