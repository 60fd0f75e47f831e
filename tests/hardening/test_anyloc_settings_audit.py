"""AnyLoc's settings as the paper states them: presets, vocabulary domains and resizes, and the
reproduction plans against the paper's reported cells (the formulas: test_anyloc_fidelity_audit.py)."""
from __future__ import annotations

import numpy as np
import pytest

from vprbench.features.backbones import backbone_spec
from vprbench.features.resize import dataset_resize

MEAN, STD = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])


def test_presets_are_the_paper_settings():
    from vprbench.methods.builtin import anyloc_presets

    p = {name: preset["options"] for name, preset in anyloc_presets().items()}
    vlad_v2 = dict(backbone="dinov2_vitg14", layer_for="dinov2_vitg14:31", facet="value", aggregation="vlad",
                   clusters=32, vocabulary="domain")
    assert p["anyloc-vlad-dinov2"] == vlad_v2 and p["anyloc-vlad-dinov2-pca"] == {**vlad_v2, "pca_dim": 512}
    assert p["anyloc-gem-dinov2"] == dict(backbone="dinov2_vitg14", layer_for="dinov2_vitg14:31", facet="value",
                                          aggregation="gem")
    vlad_v1 = dict(backbone="dino_vits8", layer_for="dino_vits8:9", facet="key", aggregation="vlad", clusters=128,
                   vocabulary="map")
    assert p["anyloc-vlad-dino"] == vlad_v1 and p["anyloc-vlad-dino-pca"] == {**vlad_v1, "pca_dim": 512}
    g, s = backbone_spec("dinov2_vitg14"), backbone_spec("dino_vits8")
    assert (g.depth, g.width, g.patch, s.depth, s.width, s.patch, s.stride) == (40, 1536, 14, 12, 384, 8, 4)
    assert tuple(s.input_size) == (224, 298) and s.interpolation == "nearest"
    assert tuple(g.mean) == tuple(MEAN) and tuple(g.std) == tuple(STD) == tuple(s.std)


def test_vocabulary_domains_and_resizes_are_the_papers():
    from vprbench.methods.anyloc_vocabulary import domain_datasets, domain_image_size, paper_vocabulary

    def members(domain):
        return sorted(domain_datasets(domain))
    indoor = [("17places", 1), ("baidu-mall", 1), ("gardens-point", 1)]
    urban = [("oxford", 1), ("pitts30k", 4), ("st-lucia", 1)]
    aerial = [("nardo-air", 1), ("nardo-air-r", 1), ("vp-air", 2)]
    rest = [("hawkins", 1), ("laurel-caverns", 1), ("mid-atlantic-ridge", 1)]
    assert (members("indoor"), members("urban"), members("aerial")) == (indoor, urban, aerial)
    assert members("structured") == sorted(indoor + urban)
    assert members("unstructured") == sorted(aerial + rest)
    assert members("global") == sorted(indoor + urban + aerial + rest)
    assert domain_image_size() == (320, 320)
    assert {d: paper_vocabulary(d) for d in ["baidu-mall", "oxford", "vp-air", "hawkins", "laurel-caverns",
                                             "mid-atlantic-ridge"]} == {
        "baidu-mall": "indoor", "oxford": "urban", "vp-air": "aerial", "hawkins": "hawkins",
        "laurel-caverns": "laurel-caverns", "mid-atlantic-ridge": "map-mid-atlantic-ridge"}
    assert {d: dataset_resize(d) for d in ["pitts30k", "st-lucia", "17places", "baidu-mall", "mid-atlantic-ridge",
                                           "oxford", "gardens-point", "hawkins", "laurel-caverns", "nardo-air",
                                           "vp-air"]} == {
        "pitts30k": (480, 640), "st-lucia": (480, 640), "17places": (480, 640), "baidu-mall": (480, 640),
        "mid-atlantic-ridge": (405, 720), "oxford": None, "gardens-point": None, "hawkins": None,
        "laurel-caverns": None, "nardo-air": None, "vp-air": None}


@pytest.mark.parametrize("table", ["2", "3"])
def test_tables_ii_and_iii_plan_every_reported_cell(table, tmp_path):
    from vprbench.reference import paper_results
    from vprbench.sweep.reproduce import table_cells

    spec, cells = table_cells("anyloc", table, data_dir=tmp_path / "data", cache_dir=tmp_path / "cache")
    reported = paper_results(table=spec["paper"])
    by_cell = {(c.row, c.column): c for c in cells}
    assert set(by_cell) == {(r.row, r.column) for r in reported.itertuples()}
    for r in reported.itertuples():
        cell = by_cell[(r.row, r.column)]
        if r.row == "NetVLAD":
            assert not cell.cells and cell.reason.startswith("the authors ran a NetVLAD checkpoint of their own")
            continue
        (run,) = cell.cells  # the -PCA rows too, on databases under 512 images: fitted on the domain's stacked
        if r.row.endswith("-PCA"):
            assert run.spec.options["pca_on"] == "domain"
        assert run.spec.dataset.name == r.column
        assert run.spec.method == r.row.lower()  # the CSV's row labels name the vprbench methods
        if r.column == "vp-air":
            assert run.spec.dataset.protocol == "with-distractors"  # 2,706 + 10,000 database images


def test_table_vii_vit_b_row_runs_the_authors_layer_10(tmp_path):
    """The authors' ViT-size runs take each DINOv2 at its best layer (S 10, B 10, L 20, G 31: their plot's
    `best_layers`, runs `l10_value_c32/.../dinov2_vitb14`); the plan ran ViT-B at ViT-G's relative depth, 9."""
    from vprbench.methods.anyloc import AnyLoc
    from vprbench.sweep.reproduce import table_cells

    _, cells = table_cells("anyloc", "7", data_dir=tmp_path / "data", cache_dir=tmp_path / "cache")
    runs = [run for cell in cells if cell.row == "ViT-B AnyLoc-VLAD-DINOv2" for run in cell.cells]
    assert len(runs) == 12  # every dataset of the five domain columns
    for run in runs:
        options = {k: v for k, v in run.spec.options.items() if k != "cache_dir"}
        method = AnyLoc(**{**options, "weights": "random"})
        assert (method.backbone, method.layer, method.facet, method.clusters, method.vocabulary) == \
            ("dinov2_vitb14", 10, "value", 32, "map")
