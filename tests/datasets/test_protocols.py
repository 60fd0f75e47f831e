"""Protocols as data: stable distinct ids and hashes; variants checked on real ground truth."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vprbench import VPRBenchError
from vprbench.cli.main import main
from vprbench.datasets import dataset_manifests, load_dataset, protocols
from vprbench.datasets.manifest import DatasetManifest
from vprbench.datasets.protocol import find_protocol


@pytest.fixture(scope="module")
def nordland_root(tmp_path_factory, shared_data, tiny_jpeg):
    """VPR-Bench's Nordland at its real size (27,592 + 2,760 hard links) with its real lists."""
    import os

    data = tmp_path_factory.mktemp("nordland")
    root = data / "Nordland"
    for folder, n in (("ref", 27592), ("query", 2760)):
        (root / folder).mkdir(parents=True)
        for i in range(n):
            os.link(tiny_jpeg, root / folder / f"{i:07d}.jpg")
    (root / "ground_truth_new.npy").symlink_to(shared_data / "ground-truth" / "vpr-bench" / "Nordland" / "ground_truth_new.npy")
    return data


def test_every_manifest_names_its_protocols_with_distinct_ids_and_hashes():
    ids, hashes = [], []
    for manifest in dataset_manifests().values():
        found = protocols(manifest)
        first = next(iter(found.values()))
        assert first.name != "default" and first.source and first.description, manifest.name
        for p in found.values():
            ids.append(p.id)
            hashes.append(p.hash)
            assert p.hash == protocols(manifest)[p.name].hash  # stable across reads
            assert len(p.hash) == 16 and p.record()["hash"] == p.hash
    assert len(set(ids)) == len(ids) and len(set(hashes)) == len(hashes)
    assert {"nordland:vpr-bench", "nordland:tolerance-10", "nordland:swapped", "msls-val:all-queries",
            "msls-val:740-queries", "vp-air:with-distractors", "vp-air:no-distractors"} <= set(ids)


def test_hash_covers_the_definition_not_the_prose():
    manifest = dataset_manifests()["nordland"]
    p = find_protocol(manifest, "tolerance-10")
    import dataclasses

    assert dataclasses.replace(p, description="other words", source="elsewhere").hash == p.hash
    assert dataclasses.replace(p, tolerance=5).hash != p.hash
    assert dataclasses.replace(p, swap=True).hash != p.hash
    # pinned: a change here changes every stored result's protocol (bump deliberately)
    assert p.hash == "8847a02450e4070b"


def test_unknown_protocol_lists_the_ones_that_exist():
    with pytest.raises(VPRBenchError, match="no protocol 'tolerance-5'.*vpr-bench, tolerance-10, swapped"):
        load_dataset("nordland", protocol="tolerance-5")


def test_bad_protocol_table_is_refused():
    text = 'name="x"\ntitle="x"\nlayout="own"\ndirectory="x"\ndomain="x"\nunit="positives"\n[[protocols]]\nname="a"\ntolerence=3\n'
    manifest = DatasetManifest.from_toml(text, "x.toml")
    with pytest.raises(VPRBenchError, match="unknown key.*tolerence"):
        protocols(manifest)
    manifest = DatasetManifest.from_toml(text.replace("tolerence", "tolerance"), "x.toml")
    with pytest.raises(VPRBenchError, match="needs `frames`"):
        protocols(manifest)


def test_nordland_protocols_on_the_real_lists(nordland_root):
    default = load_dataset("nordland", nordland_root, strict=True)
    assert default.kind == "benchmark" and default.protocol["id"] == "nordland:vpr-bench"
    assert default.summary()["positive_pairs"] == 2760 * 3 - 1

    wide = load_dataset("nordland", nordland_root, protocol="tolerance-10")
    assert wide.protocol["ground_truth"] == {"unit": "frames", "radius": 10, "radius_unit": "frames",
                                             "frames": {"database": [0, 1], "queries": [0, 10]}}
    pos = wide.positives
    assert pos[0].tolist() == list(range(0, 11)) and pos[1].tolist() == list(range(0, 21))
    assert pos[2759].tolist() == list(range(27580, 27592))
    assert sum(len(p) for p in pos) == 2758 * 21 + 11 + 12
    # every +-1 positive of the released lists is a +-10 positive
    assert all(set(a.tolist()) <= set(b.tolist()) for a, b in zip(default.positives, pos))

    swapped = load_dataset("nordland", nordland_root, protocol="swapped")
    assert (len(swapped.database), len(swapped.queries)) == (2760, 27592)
    assert swapped.database[0].parent.name == "query" and swapped.queries[0].parent.name == "ref"
    sp = swapped.positives
    assert sp[10].tolist() == [1] and sp[9].tolist() == [1] and sp[12].tolist() == [] and sp[0].tolist() == [0]
    pairs = {(int(d), q) for q, p in enumerate(default.positives) for d in p}
    assert pairs == {(q, int(d)) for q, p in enumerate(sp) for d in p}
    assert sum(len(p) > 0 for p in sp) == 8279  # Recall@K <= 8279 / 27592 = 30.0%
    assert len({default.protocol["hash"], wide.protocol["hash"], swapped.protocol["hash"]}) == 3


def test_a_dataset_loaded_under_one_protocol_is_not_specified_under_another(nordland_root):
    """`spec_for(method, load_dataset("nordland"), protocol="tolerance-10")` dropped the protocol unsaid: the
    spec named, and evaluate(spec, dataset=...) computed, vpr-bench's +-1 frames."""
    from vprbench import create_method
    from vprbench.spec import resolve_spec, spec_for

    hog, default = create_method("hog"), load_dataset("nordland", nordland_root)
    with pytest.raises(VPRBenchError, match=r"loaded under protocol nordland:vpr-bench, not 'tolerance-10'"):
        spec_for(hog, default, protocol="tolerance-10")
    with pytest.raises(VPRBenchError, match=r"loaded under protocol nordland:vpr-bench, not 'tolerance-10'"):
        resolve_spec("hog", default, protocol="tolerance-10")
    with pytest.raises(VPRBenchError, match="no protocol 'tolerance-5'.*vpr-bench, tolerance-10, swapped"):
        spec_for(hog, default, protocol="tolerance-5")  # as by name
    wide = load_dataset("nordland", nordland_root, protocol="tolerance-10")
    by_name = resolve_spec("hog", "nordland", protocol="tolerance-10")
    assert spec_for(hog, wide, protocol="tolerance-10").key == spec_for(hog, wide).key == by_name.key
    assert spec_for(hog, default, protocol="default").key == resolve_spec("hog", "nordland").key != by_name.key


def test_vp_air_without_distractors(tmp_path, make_images, save_rows):
    """VP-Air's real counts (2,706 references + 10,000 distractors, 2,706 queries); lists within 3 frames."""
    root = tmp_path / "VPAir"
    make_images(root / "reference_views", [f"{i:05d}.png" for i in range(1, 2707)])
    make_images(root / "distractors", [f"{i:05d}.png" for i in range(1, 10001)])
    make_images(root / "queries", [f"{i:05d}.png" for i in range(1, 2707)])
    lists = [list(range(max(0, i - 3), min(2706, i + 4))) for i in range(2706)]
    save_rows(root / "vpair_gt.npy", lists)
    full = load_dataset("vp-air", tmp_path, strict=True)
    clean = load_dataset("vp-air", tmp_path, protocol="no-distractors")
    assert (len(full.database), len(clean.database), len(clean.queries)) == (12706, 2706, 2706)
    assert all(p.parent.name == "reference_views" for p in clean.database)
    assert [p.tolist() for p in clean.positives] == lists == [p.tolist() for p in full.positives]
    assert clean.protocol["database"] == {"split": "database", "count": 2706, "exclude_folders": ["distractors"]}


def test_msls_740_queries_selected_by_key(tmp_path, make_images):
    """18,871 references (real count); 740 of the queries (real count) chosen by GSV-Cities' lists.
    The full query count is not sourced here: 900 stand in for it."""
    root = tmp_path / "msls" / "images" / "val"
    make_images(root / "database", [f"@{500000 + i * 30}@{4000000}@33@U@@@db{i:05d}@@@@@@@@.jpg" for i in range(18871)])
    keys = [f"key{i:04d}" for i in range(900)]
    make_images(root / "queries", [f"@{500000 + i * 30 + 5}@{4000000}@33@U@@@{k}@@@@@@@@.jpg" for i, k in enumerate(keys)])
    np.save(tmp_path / "msls" / "msls_val_qImages.npy", np.array([f"val/cph/query/images/{k}.jpg" for k in keys]))
    chosen = np.random.default_rng(0).choice(900, 740, replace=False)
    np.save(tmp_path / "msls" / "msls_val_qIdx.npy", chosen)
    with pytest.warns(UserWarning, match="900 query images"):  # the manifest's count is the 740-query one
        every = load_dataset("msls-val", tmp_path)
        subset = load_dataset("msls-val", tmp_path, protocol="740-queries")
    assert (len(every.queries), len(subset.queries), len(subset.database)) == (900, 740, 18871)
    assert {q.name.split("@")[7] for q in subset.queries} == {keys[i] for i in chosen}
    by_name = dict(zip([q.name for q in every.queries], every.positives))
    assert all(np.array_equal(by_name[q.name], p) for q, p in zip(subset.queries, subset.positives))
    (tmp_path / "msls" / "msls_val_qIdx.npy").unlink()
    with pytest.raises(VPRBenchError, match="msls_val_qIdx.npy, which is missing.*gsv-cities"), pytest.warns(UserWarning):
        load_dataset("msls-val", tmp_path, protocol="740-queries")


def test_own_data_is_kind_own(tmp_path, make_images):
    root = tmp_path / "mine"
    make_images(root / "database", ["@0@0@@@.jpg", "@0@100@@@.jpg"])
    make_images(root / "queries", ["@0@5@@@.jpg"])
    dataset = load_dataset(str(root))
    assert dataset.kind == "own" and dataset.protocol["name"] == "own" and dataset.protocol["ground_truth"]["radius"] == 25
    with pytest.raises(VPRBenchError, match="one protocol, 'own'"):
        load_dataset(str(root), protocol="swapped")


def test_datasets_info_lists_protocols(capsys):
    assert main(["datasets", "info", "nordland", "--protocols", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [p["name"] for p in listed] == ["vpr-bench", "tolerance-10", "swapped"]
    assert all({"id", "hash", "description", "source", "ground_truth"} <= set(p) for p in listed)
