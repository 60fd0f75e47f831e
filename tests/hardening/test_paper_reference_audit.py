"""The AnyLoc reproduction against the reference copy of the paper (../shared/reference): every
reported value vprbench ships, the figure each planned cell is compared with, and the datasets'
counts, radii and resize, cell by cell. Tests reading the reference skip where it is absent."""
from __future__ import annotations

import csv
import re

import pytest

from vprbench.reference import paper_results
from vprbench.sweep.reproduce import reported_value, table_cells

PAPER_TABLES = {"structured": "II", "unstructured": "III"}
ABLATIONS = {"vit_and_layer": "ablation-layer", "facet": "ablation-facet"}


def _reference(folder) -> dict[tuple[str, str, str, str], float]:
    """(table, row, column, metric) -> value, from the reference CSVs."""
    out = {}
    for r in csv.DictReader((folder / "anyloc-paper-results.csv").read_text().splitlines()):
        for metric in ("r1", "r5"):
            out[PAPER_TABLES[r["table"]], r["method"], r["dataset"], metric] = float(r[metric])
    for r in csv.DictReader((folder / "anyloc-paper-tables-4-7.csv").read_text().splitlines()):
        out[r["table"], r["row"], r["column"], "dim" if r["column"] == "dim" else "r1"] = float(r["value"])
    for r in csv.DictReader((folder / "anyloc-ablations.csv").read_text().splitlines()):
        row = f"{r['backbone']} layer {r['layer']} {r['facet']} {r['clusters']} clusters"
        out[ABLATIONS[r["study"]], row, r["dataset"], "r1"] = float(r["r1"])
    return out


def test_every_shipped_reported_value_is_the_references(shared_reference):
    wanted = _reference(shared_reference)
    shipped = {(r.table, r.row, r.column, r.metric): r.value for r in paper_results().itertuples()}
    assert {k: shipped.get(k) for k in wanted} == wanted
    assert sorted(set(shipped) - set(wanted)) == []


@pytest.mark.parametrize("table", ["2", "3", "4", "5", "6", "7", "layer", "facet"])
def test_each_planned_cell_is_compared_with_its_own_figure_and_runs_its_setting(table, shared_reference, tmp_path):
    wanted = _reference(shared_reference)
    spec, cells = table_cells("anyloc", table, cache_dir=tmp_path, data_dir=tmp_path)
    assert cells
    for tc in cells:
        for metric in spec["metrics"]:
            assert reported_value(spec, tc.row, tc.column, metric) == wanted[spec["paper"], tc.row, tc.column, metric]
        setting = re.fullmatch(r"(\S+) layer (\d+) (\w+) (\d+) clusters", tc.row)
        if setting:  # an ablation run: the row's own backbone, layer, facet and clusters
            backbone, layer, facet, clusters = setting.groups()
            for cell in tc.cells:
                method = _method(cell)
                assert cell.spec.dataset.name == tc.column
                assert (method.backbone, method.layer, method.facet, method.clusters) == \
                    (backbone, int(layer), facet, int(clusters)), tc.row


def _method(cell):
    """The AnyLoc method a cell makes (its spec leaves out options at their default); nothing loads."""
    import warnings

    from vprbench.methods.anyloc import AnyLoc
    from vprbench.methods.registry import method_entry

    options = {**method_entry(cell.spec.method).effective_defaults(), **cell.spec.options, "vocabulary": "map"}
    with warnings.catch_warnings():  # a preset's layer on another backbone: the same relative depth, said
        warnings.simplefilter("ignore")
        return AnyLoc(**options)


NOTES_NAMES = {"Baidu Mall": "baidu-mall", "Gardens Point": "gardens-point", "17 Places": "17places",
               "Pitts-30k test": "pitts30k", "St Lucia": "st-lucia", "Oxford RobotCar": "oxford",
               "Hawkins": "hawkins", "Laurel Caverns": "laurel-caverns", "Nardo-Air": "nardo-air",
               "Nardo-Air R": "nardo-air-r", "VP-Air": "vp-air", "Mid-Atlantic Ridge": "mid-atlantic-ridge"}
#: documented in the manifests' notes: Hawkins is evaluated on the folders' 127/118 (the authors'
#: loader's pose rows; the 65/101 are Mid-Atlantic Ridge's), 17 Places' lists hold +-2 frames
DOCUMENTED = {("hawkins", "database"): 127, ("hawkins", "queries"): 118, ("17places", "radius"): 2}


def test_the_dataset_manifests_have_the_references_counts_and_radii(shared_reference):
    from vprbench.datasets import dataset_manifest

    text = (shared_reference / "anyloc-notes.md").read_text()
    rows = re.findall(r"^\| ([^|(]+?)(?: \([^|]*\))? \| [^|]+ \| ([\d,+ ]+) \| ([\d,]+) \| ([\d.]+) (m|frames)\b", text, re.M)
    assert {NOTES_NAMES[name] for name, *_ in rows} == set(NOTES_NAMES.values())
    number = lambda text: sum(int(part.replace(",", "")) for part in text.split("+"))
    for name, database, queries, radius, unit in rows:
        manifest = dataset_manifest(NOTES_NAMES[name])
        key = NOTES_NAMES[name]
        assert manifest.database_count == DOCUMENTED.get((key, "database"), number(database)), key
        assert manifest.query_count == DOCUMENTED.get((key, "queries"), number(queries)), key
        assert manifest.radius == DOCUMENTED.get((key, "radius"), float(radius)), key
        assert (manifest.radius_unit or manifest.unit) == {"m": "metres", "frames": "frames"}[unit], key


def test_anylocs_per_dataset_resize_is_the_references(shared_reference):
    from vprbench.features.resize import DATASET_RESIZE

    text = " ".join((shared_reference / "anyloc-notes.md").read_text().split())
    listed = re.search(r"Resize per dataset: ([^.]+?) are resized to (\d+)x(\d+) \(.*?\); ([\w -]+?) to (\d+)x(\d+); "
                       r"([^.]+?) keep their native size", text)
    assert listed, "the reference notes no longer state the per-dataset resize in the form this test reads"
    names = lambda words: {NOTES_NAMES.get(w.strip(), NOTES_NAMES.get(w.strip() + " test"))
                           for w in re.split(r",| and ", words)}
    wanted = {name: (int(listed[2]), int(listed[3])) for name in names(listed[1])}
    wanted |= {name: (int(listed[5]), int(listed[6])) for name in names(listed[4])}
    assert DATASET_RESIZE == wanted
    assert not names(listed[7]) & set(DATASET_RESIZE)


#: the paper's presets (reference notes, "Presets in the paper"): backbone, layer, facet, clusters
PRESETS = {"DINOv2": ("dinov2_vitg14", 31, "value", 32), "DINO": ("dino_vits8", 9, "key", 128)}


@pytest.mark.parametrize("table", ["2", "3", "4", "5", "6", "7"])
def test_each_anyloc_cell_runs_the_papers_features_at_anylocs_size_for_its_dataset(table, tmp_path):
    from vprbench.features.resize import DATASET_RESIZE

    _, cells = table_cells("anyloc", table, cache_dir=tmp_path, data_dir=tmp_path)
    for tc in cells:
        for cell in tc.cells:
            if not cell.spec.method.startswith("anyloc"):
                continue
            method = _method(cell)
            family = "DINOv2" if "DINOv2" in tc.row or "dinov2" in cell.spec.method else "DINO"
            backbone, layer, facet, clusters = PRESETS[family]
            if tc.row == "ViT-B AnyLoc-VLAD-DINOv2":  # Table VII: ViT-B at the authors' layer for it
                backbone, layer = "dinov2_vitb14", 10
            assert (method.backbone, method.layer, method.facet) == (backbone, layer, facet), (table, tc.row)
            if method.aggregation.startswith("vlad"):
                assert method.clusters == clusters, (table, tc.row)
            assert method.resize is None  # unset: use_dataset picks AnyLoc's size for the dataset
            method.dataset = cell.spec.dataset.name
            assert method.resize == DATASET_RESIZE.get(cell.spec.dataset.name), (table, tc.row, tc.column)
