"""`vprbench reproduce anyloc`: each table's cells against the paper (settings, reported numbers,
what a cell needs) and its bad input, one line each."""
from __future__ import annotations

import pytest

from vprbench.cli.main import main
from vprbench.sweep.needs import vocabulary_for
from vprbench.sweep.reproduce import reported_value, table_cells


def _cells(table: str, row: str, cache_dir) -> dict:
    spec, cells = table_cells("anyloc", table, cache_dir=cache_dir)
    found = {tc.column: tc for tc in cells if tc.row == row}
    assert found, f"table {table} has no row {row!r}"
    return spec, found


def printed_table(spec, cells, cache_dir, stored=None, width: int = 400) -> str:
    """The paper's table `reproduce` prints, as text at `width` columns."""
    from rich.console import Console

    from vprbench.cli.reproduce import paper_table
    from vprbench.run_settings import RunSettings

    console = Console(width=width, record=True, markup=False)
    console.print(paper_table(spec, cells, RunSettings(cache_dir=cache_dir), stored))
    return console.export_text()


def test_dino_vlad_rows_of_tables_2_and_3_use_the_domain_vocabularies(tmp_path):
    # Table VII's map-specific ViT-S means equal Tables II/III's AnyLoc-VLAD-DINO only where the
    # domain's vocabulary is the map's (SubT 52.7, underwater 41.6), not indoor (72.9 vs 73.3)
    spec7, vii = _cells("7", "ViT-S AnyLoc-VLAD-DINO", tmp_path)
    assert reported_value(spec7, "ViT-S AnyLoc-VLAD-DINO", "indoor", "r1") == 72.9
    for table, row in (("2", "AnyLoc-VLAD-DINO"), ("2", "AnyLoc-VLAD-DINO-PCA"), ("3", "AnyLoc-VLAD-DINO")):
        spec, cells = _cells(table, row, tmp_path)
        runnable = [c for tc in cells.values() for c in tc.cells]
        assert len(runnable) == 6  # the -PCA row's too: fitted on the domain's databases stacked
        assert {c.spec.options["vocabulary"] for c in runnable} == {"domain"}, (table, row)
        assert {c.spec.options["backbone"] for c in runnable} == {"dino_vits8"}
        assert {(c.spec.options["facet"], c.spec.options["clusters"]) for c in runnable} == {("key", 128)}
    assert reported_value(spec, "AnyLoc-VLAD-DINO", "nardo-air", "r1") == 43.7  # spec: Table III's
    spec2, _ = _cells("2", "AnyLoc-VLAD-DINO", tmp_path)
    indoor = [reported_value(spec2, "AnyLoc-VLAD-DINO", d, "r1") for d in ("baidu-mall", "gardens-point", "17places")]
    assert indoor == [61.2, 95.0, 63.8] and round(sum(indoor) / 3, 1) == 73.3
    # the map-specific tables keep the map's vocabulary
    assert {c.spec.options["vocabulary"] for tc in vii.values() for c in tc.cells} == {"map"}
    _, vi = _cells("6", "DINO hard VLAD", tmp_path)
    assert {c.spec.options["vocabulary"] for tc in vi.values() for c in tc.cells} == {"map"}


def test_baseline_cells_see_anylocs_per_dataset_resize(tmp_path):
    """The authors' CLIP and CosPlace scripts read images through their dataset loaders, which resize
    Baidu Mall, 17 Places, Pitts-30k and St Lucia to 480x640 and Mid-Atlantic Ridge to 405x720 (on the
    normalised tensor); before, every CLIP-CLS and CosPlace cell ran on the images as stored, and MixVPR
    resized with PIL bicubic (its authors') instead of AnyLoc's bilinear tensor resize."""
    from vprbench.features.resize import dataset_resize

    seen = {}
    for table in ("2", "3"):
        _, cells = _cells(table, "CLIP-CLS", tmp_path)
        for column, tc in cells.items():
            (cell,) = tc.cells
            assert cell.spec.dataset.name == column
            seen[column] = cell.spec.options.get("resize")
            assert seen[column] == (list(dataset_resize(column)) if dataset_resize(column) else None), column
            assert cell.spec.options.get("preprocess", "anyloc") == "anyloc"
    assert seen["baidu-mall"] == [480, 640] and seen["mid-atlantic-ridge"] == [405, 720] and seen["oxford"] is None
    # CosPlace: through the same loaders (CosPlace/eval.py), resized on the normalised tensor; MixVPR:
    # its loaders' own 320x320 tensor resize (MixVPR/mixer_top_k_vpr.py), no dataset size
    for table in ("2", "3"):
        _, cosplace = _cells(table, "CosPlace", tmp_path)
        for column, tc in cosplace.items():
            (cell,) = tc.cells
            assert cell.spec.options.get("resize") == (list(dataset_resize(column)) if dataset_resize(column) else None)
            assert cell.spec.options["preprocess"] == "anyloc"
        _, mixvpr = _cells(table, "MixVPR", tmp_path)
        assert {(c.spec.options["preprocess"], c.spec.options.get("resize")) for tc in mixvpr.values()
                for c in tc.cells} == {("anyloc", None)}
    # the other rows keep their own preprocessing (the AnyLoc presets resize per dataset themselves)
    _, gem = _cells("2", "AnyLoc-GeM-DINOv2", tmp_path)
    assert "resize" not in gem["baidu-mall"].cells[0].spec.options


def test_a_dino_domain_cell_names_the_vocabulary_it_needs(tmp_path):
    _, cells = _cells("3", "AnyLoc-VLAD-DINO", tmp_path)
    nardo = cells["nardo-air"].cells[0]
    assert vocabulary_for(nardo, tmp_path) == (
        "vocabulary 'aerial' for dino_vits8 layer 9 key c128",
        "run 'vprbench vocabulary fit --domain aerial --method anyloc-vlad-dino --backbone dino_vits8 --layer 9 --facet key "
        "--clusters 128'")
    # Mid-Atlantic Ridge: the paper's vocabulary there is its own map's, fitted in the run
    assert vocabulary_for(cells["mid-atlantic-ridge"].cells[0], tmp_path) is None


def test_table_6_shows_the_papers_descriptor_dimensions(tmp_path):
    spec, cells = table_cells("anyloc", "6", cache_dir=tmp_path)
    text = printed_table(spec, cells, tmp_path, width=220).splitlines()
    assert [cell.strip() for cell in text[3].split("┃")[1:-1]] == ["row", "baidu-mall R1", "oxford R1", "dim"], text
    lines = {line.split("│")[1].strip(): line for line in text if line.count("│") > 2}
    for row, dim in (("DINO GAP", 384), ("DINO hard VLAD", 49152), ("DINOv2 GeM", 1536), ("DINOv2 soft VLAD", 49152)):
        assert lines[row].split("│")[4].strip() == f"{dim} / not measured", lines[row]


@pytest.mark.parametrize("flag, value, wanted", [
    ("--batch-size", "0", "reproduce: option batch_size takes a whole number >= 1 (images per batch); got 0."),
    ("--device", "foo", "reproduce: option device takes a torch device such as cpu, cuda or cuda:1; got 'foo'."),
])
def test_a_bad_run_setting_is_one_line_naming_it(tmp_path, capsys, flag, value, wanted):
    # was two lines blaming the table's first method ("Plan anyloc table 6 has 1 problem(s) ... anyloc-vlad-dino: ...")
    code = main(["reproduce", "anyloc", "--table", "6", "--dry-run", flag, value, "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1 and err.strip().splitlines() == [f"error: {wanted}"], err


@pytest.mark.parametrize("given, hint", [("II", "2"), ("vii", "7"), ("Layer", "layer"), ("ablation-facet", "facet")])
def test_the_papers_table_names_point_to_ours(tmp_path, capsys, given, hint):
    code = main(["reproduce", "anyloc", "--table", given, "--dry-run", "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.strip() == (f"error: The anyloc paper has no table {given!r} here; tables: 2, 3, 4, 5, 6, 7, layer, "
                           f"facet, backbones. Did you mean: {hint}?")


def test_publish_with_a_dry_run_is_refused_not_ignored(tmp_path, capsys):
    code = main(["reproduce", "anyloc", "--table", "6", "--dry-run", "--publish", str(tmp_path / "site"),
                 "--cache-dir", str(tmp_path / "cache")])
    err = capsys.readouterr().err
    assert code == 1 and err.strip() == (
        "error: --publish writes the table and the leaderboard after the cells run; --dry-run runs nothing and "
        "publishes nothing: drop one of them (cells already measured are read, not run again).")
    assert not (tmp_path / "site").exists()



def test_the_backbones_plan_runs_to_its_table_with_nothing_reported(tmp_path, capsys):
    # no table of the paper: the real (not dry) run ended in "error: The anyloc paper has no table
    # 'backbones'" once its cells were judged, so its table was never printed
    (tmp_path / "data").mkdir()
    code = main(["reproduce", "anyloc", "--table", "backbones", "--quiet", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(tmp_path / "cache")])
    captured = capsys.readouterr()
    assert code == 0 and "error" not in captured.err, captured.err
    assert "reported (paper) / measured here" in captured.out
    spec, cells = table_cells("anyloc", "backbones", cache_dir=tmp_path / "cache")
    line = next(x for x in printed_table(spec, cells, tmp_path / "cache", width=1000).splitlines() if x.startswith("│ VLAD DINOv2 ViT-G/14 (paper)"))
    values = [cell.strip() for cell in line.split("│")[2:-1]]
    assert values == ["- / not measured"] * 24, values  # 12 datasets x R@1, R@5


def test_a_vocabulary_fit_command_names_the_runs_own_data_root_and_cache(tmp_path, capsys, monkeypatch):
    # it said "run 'vprbench vocabulary fit --domain aerial ... --layer 9'": run as printed, that
    # fits from the default data root into the default cache, where this run never looks
    monkeypatch.setenv("COLUMNS", "400")
    data, cache = tmp_path / "my data", tmp_path / "cache"
    data.mkdir()
    code = main(["reproduce", "anyloc", "--table", "3", "--dry-run", "--data-dir", str(data), "--cache-dir", str(cache)])
    out = " ".join(capsys.readouterr().out.split())
    assert code == 0
    assert (f"vocabulary 'aerial' for dino_vits8 layer 9 key c128: run 'vprbench vocabulary fit --domain aerial "
            f"--method anyloc-vlad-dino --backbone dino_vits8 --layer 9 --facet key --clusters 128 --data-dir '{data}' "
            f"--cache-dir {cache}'") in out


def _edited(monkeypatch, edit):
    import copy

    import vprbench.sweep.reproduce as reproduce

    tables = copy.deepcopy(reproduce.reproduce_tables("anyloc"))
    edit(tables)
    monkeypatch.setattr(reproduce, "reproduce_tables", lambda paper: tables)


@pytest.mark.parametrize("edit, wanted", [
    # Baidu Mall's reported numbers beside an Oxford run, and Oxford's beside Baidu Mall's
    (lambda t: t["2"]["columns"].update({"baidu-mall": ["oxford"], "oxford": ["baidu-mall"]}),
     "column 'baidu-mall' runs oxford: a dataset's column runs that dataset only"),
    # a row label the CSV does not have: its reported numbers were silently '-'
    (lambda t: t["2"]["rows"][6].update(row="AnyLoc-GeM-DINOv2 "),
     "the paper's table II has row 'AnyLoc-GeM-DINOv2', which the plan leaves out"),
    (lambda t: t["4"]["columns"].update(indoor=["baidu-mall", "gardens-point"]),
     "column 'indoor' runs baidu-mall, gardens-point; the indoor domain is 17places, baidu-mall, gardens-point"),
    # the same set of datasets, one twice: Baidu Mall counted twice in the indoor mean shown beside the paper's
    (lambda t: t["4"]["columns"].update(indoor=["baidu-mall", "gardens-point", "17places", "baidu-mall"]),
     "column 'indoor' lists baidu-mall more than once"),
    (lambda t: t["5"]["rows"][0]["cells"]["vocab-transfer"].update(dataset="gardens-point"),
     "row 'baidu-mall->17places': cell 'vocab-transfer' runs gardens-point"),
    (lambda t: t["2"].update(metrics=["r1"]), "the paper's table II has metric 'r5', which the plan leaves out"),
    (lambda t: t["2"].update(paper="IIX"), "paper = 'IIX' is no table of the paper's reported numbers."),
    (lambda t: t["2"]["rows"].append(dict(t["2"]["rows"][0])), "row 'NetVLAD' is there more than once"),
    # these were tracebacks (KeyError, AttributeError)
    (lambda t: t["2"].pop("columns"), "row 'NetVLAD' has no columns"),
    (lambda t: t["2"]["rows"][0].pop("row"), "rows must be a list of tables, each with its row label"),
    (lambda t: t["5"]["rows"][0]["cells"]["map-specific"].pop("dataset"),
     "row 'baidu-mall->17places': cell 'map-specific' needs its dataset"),
    (lambda t: t["2"]["rows"][3].update(dataset_resize="yes"),
     "row 'CLIP-CLS': dataset_resize must be true or false, and not given with a resize option"),
])
def test_an_inconsistent_plan_is_refused_naming_what(monkeypatch, tmp_path, capsys, edit, wanted):
    _edited(monkeypatch, edit)
    table = "4" if "indoor" in wanted else "5" if "17places" in wanted else "2"
    code = main(["reproduce", "anyloc", "--table", table, "--dry-run", "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code != 0 and "Traceback" not in err
    assert err.startswith(f"error: The reproduction plan of table {table} (manifests/reproduce/anyloc.toml) is inconsistent")
    assert wanted in err, err


def test_the_shipped_plans_are_consistent_with_the_papers_tables():
    from vprbench.sweep.reproduce import plan_problems, reproduce_tables

    assert {name: plan_problems(spec, name) for name, spec in reproduce_tables("anyloc").items()} == \
        {name: [] for name in ("2", "3", "4", "5", "6", "7", "layer", "facet", "backbones")}


def test_a_stored_run_that_fell_back_to_the_maps_vocabulary_is_not_the_papers(monkeypatch, tmp_path, capsys):
    # `evaluate anyloc-vlad-dino --vocabulary domain` without the domain's vocabulary fits the map's
    # (with a warning) under the same spec: its record was counted as the paper's cell, "complete" in
    # the dry run and shown against Table III's domain-vocabulary number
    from vprbench.sweep.runner import StoredRecords

    monkeypatch.setenv("COLUMNS", "400")
    monkeypatch.setattr(StoredRecords, "record", lambda self, spec, options=None: {"created": "2026-01-02T03:04:05+00:00"})
    code = main(["reproduce", "anyloc", "--table", "3", "--dry-run", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(tmp_path / "cache")])
    lines = capsys.readouterr().out.splitlines()
    assert code == 0

    def status(row):
        line = next(x for x in lines if x.startswith(f"│ {row} ") and "nardo-air:anyloc" in x)
        return line.split("│")[3].split()[0]

    assert status("AnyLoc-VLAD-DINO") == "missing"  # its 'aerial' vocabulary for ViT-S/8 is not fitted
    assert status("DINO-CLS") == "complete"  # no vocabulary: its stored record stands


def test_the_paper_table_shows_measured_minus_reported(tmp_path, monkeypatch):
    """A cell reads 'reported / measured (delta) [CI]'; the delta is measured - reported (+ above the paper)."""
    import vprbench.sweep.reproduce as reproduce_module

    class Stored:
        def record(self, spec, settings):
            return {"run_id": "r"}

    spec, cells = table_cells("anyloc", "6", cache_dir=tmp_path)
    monkeypatch.setattr(reproduce_module, "measured", lambda records, metric: (99.0, 98.0, 99.5))
    reported = reproduce_module.reported_value(spec, "DINOv2 GeM", "baidu-mall", "r1")
    assert reported is not None and reported < 99.0
    line = next(line for line in printed_table(spec, cells, tmp_path, Stored(), width=220).splitlines() if "│ DINOv2 GeM" in line)
    assert line.split("│")[2].strip() == f"{reported:.1f} / 99.0 (+{99.0 - reported:.1f}) [98.0, 99.5]"


def test_the_released_vocabulary_download_command_runs_as_printed(tmp_path):
    # it said "run 'vprbench vocabulary download --data-dir ...'", a flag that command does not take
    # (it reads no data): copied as printed, it stopped at argparse
    import shlex

    from vprbench.cli.main import build_parser

    _, cells = _cells("2", "AnyLoc-VLAD-DINOv2", tmp_path)
    given = {"data-dir": str(tmp_path / "my data"), "cache-dir": str(tmp_path / "cache")}
    _, how = vocabulary_for(cells["baidu-mall"].cells[0], tmp_path, given)
    command = shlex.split(how.split("run '", 1)[1].split("'", 1)[0])
    assert command[:3] == ["vprbench", "vocabulary", "download"], how
    args = build_parser().parse_args(command[1:])
    assert args.cache_dir == given["cache-dir"]


def test_the_paper_table_prints_each_reported_value_as_published(tmp_path):
    """The authors' ablation runs publish two decimals: key 80.62 and query 80.56 (Pitts-30k, DINOv2
    layer 31) both read 80.6, and 58.25 read 58.2, so the table no longer said which facet won."""
    def cells_of(table: str) -> dict:
        spec, cells = table_cells("anyloc", table, cache_dir=tmp_path)
        lines = [x for x in printed_table(spec, cells, tmp_path).splitlines() if x.count("│") > 2]
        return {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:-1]] for line in lines}

    facet = cells_of("facet")  # columns: baidu-mall, oxford, pitts30k (R@1)
    assert facet["dinov2_vitg14 layer 31 key 32 clusters"][2] == "80.62 / not measured"
    assert facet["dinov2_vitg14 layer 31 query 32 clusters"][2] == "80.56 / not measured"
    assert facet["dino_vits8 layer 9 query 128 clusters"][0] == "58.25 / not measured"
    # one decimal stays one decimal, a whole number keeps it: Table II NetVLAD, Gardens Point R@5 = 85.0
    assert cells_of("2")["NetVLAD"][2:4] == ["58.5 / not measured", "85.0 / not measured"]


def test_the_backbones_table_says_it_is_not_the_papers(tmp_path, capsys, monkeypatch):
    # its title read "Backbones: ... on the paper's datasets" beside rows marked "(paper)": a reader took
    # it for one of the paper's tables whose reported values were missing
    monkeypatch.setenv("COLUMNS", "400")
    code = main(["reproduce", "anyloc", "--table", "backbones", "--dry-run", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(tmp_path / "cache")])
    out = " ".join(capsys.readouterr().out.split())
    assert code == 0 and "vprbench's own table (not the paper's; nothing reported)" in out
    spec, cells = table_cells("anyloc", "backbones", cache_dir=tmp_path / "cache")
    assert "vprbench's own table (not the paper's; nothing reported)" in printed_table(spec, cells, tmp_path / "cache")


def test_a_baseline_rows_weights_are_needed_where_the_run_reads_them(tmp_path):
    """MixVPR's checkpoint is only on Google Drive: the dry run said "into <cache>/torch/hub/checkpoints, or
    pass weights=PATH"; a file put there made the dry run say 'would run' and the run stop asking for
    --weights, which reproduce refuses. A CLIP file put loose under <cache>/huggingface counted as present
    though the run reads the hub's cache layout only."""
    from vprbench.sweep.needs import missing_for
    from vprbench.weights import hub_folder, weights_folder

    def needs(row):
        spec, cells = _cells("2", row, tmp_path)
        cell = cells["oxford"].cells[0]
        weights = {r["row"]: r.get("weights") for r in spec["rows"]}[row]
        return cell, [how for thing, how in missing_for(cell, weights, tmp_path, tmp_path) if thing.startswith("weights")]

    name = "resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt"
    cell, (how,) = needs("MixVPR")
    assert how == ("download it from https://drive.google.com/file/d/1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L/view (no "
                   f"direct download) and put it at {weights_folder(tmp_path) / name} (the authors publish no sha256, "
                   "so one put there by hand runs as your own weights, as with --weights (a † 'user weights' row, "
                   "not the official one))")
    assert "weights" not in cell.spec.options
    weights_folder(tmp_path).mkdir(parents=True)
    (weights_folder(tmp_path) / name).write_bytes(b"checkpoint")
    cell, found = needs("MixVPR")  # put there, the run is given it: nothing missing, and it is the file read
    assert found == [] and cell.spec.options["weights"] == str(weights_folder(tmp_path) / name)
    assert cell.spec.files["weights"].startswith("sha256:")

    _, (how,) = needs("CLIP-CLS")
    assert how.startswith("let vprbench download https://huggingface.co/laion/CLIP-ViT-bigG-14-laion2B-39B-b160k (a "
                          f"run online with this cache), or put the file at the hub cache {hub_folder(tmp_path)}: ")
    hub_folder(tmp_path).mkdir(parents=True)
    (hub_folder(tmp_path) / "open_clip_pytorch_model.bin").write_bytes(b"loose")
    assert len(needs("CLIP-CLS")[1]) == 1  # not in the hub's layout: the run would not read it
    _, (how,) = needs("CosPlace")
    assert "pass weights=PATH" not in how and f"put the file at {weights_folder(tmp_path)}/" in how
    assert how.endswith("one put there by hand runs as your own weights, as with --weights (a † 'user weights' row, "
                        "not the official one)")


def test_the_netvlad_rows_say_why_they_cannot_run_as_the_paper_ran_them(tmp_path):
    # "no vprbench method matches this row" beside a 'netvlad' method vprbench has: what is missing is the
    # authors' own checkpoint (dvgl_benchmark/dvgl_many.sh: a best_model.pth of their training), not a method
    from vprbench.methods.registry import method_entry

    assert method_entry("netvlad")
    for table in ("2", "3"):
        _, cells = _cells(table, "NetVLAD", tmp_path)
        assert {tc.reason for tc in cells.values()} == {
            "the authors ran a NetVLAD checkpoint of their own training (dvgl_benchmark/dvgl_many.sh loads their "
            "best_model.pth; ResNet-18 conv4 by the benchmark's defaults), which they did not release; vprbench's "
            "netvlad runs other weights, so its numbers would not be the paper's run"}
        assert all(not tc.cells for tc in cells.values())
    _, vii = _cells("7", "ViT-B CosPlace", tmp_path)  # no reason given: no vprbench method is still the reason
    assert {tc.reason for tc in vii.values()} == {"no vprbench method matches this row"}


def test_the_pca_rows_fit_on_the_domains_databases_stacked_as_the_authors_did(tmp_path, capsys, monkeypatch):
    # was: Gardens Point, 17 Places and Oxford not runnable (PCA to 512 on 200-406 images) and the other three
    # fitted on their own database, beside the paper's values from a PCA fitted on the domain's databases
    # stacked (scripts/joint_pca_project.py)
    from vprbench.sweep.needs import missing_for

    for row in ("AnyLoc-VLAD-DINOv2-PCA", "AnyLoc-VLAD-DINO-PCA"):
        _, cells = _cells("2", row, tmp_path)
        assert {column for column, tc in cells.items() if tc.cells and not tc.reason} == {
            "baidu-mall", "gardens-point", "17places", "pitts30k", "st-lucia", "oxford"}
        assert {tc.cells[0].spec.options["pca_on"] for tc in cells.values()} == {"domain"}
        # a cell needs every database its PCA is fitted on, named with how to get it
        needs = [thing for thing, _ in missing_for(cells["oxford"].cells[0], None, tmp_path / "data", tmp_path)]
        assert needs[:3] == ["dataset oxford", "dataset st-lucia", "dataset pitts30k"], needs
        # the urban stack's exact fit takes more than the default 1 GB: said before the run
        memory = [n for n in missing_for(cells["oxford"].cells[0], None, tmp_path / "data", tmp_path) if "memory" in n[0]]
        assert memory == [("memory for PCA-whitening of 11,762 x 49,152 descriptors to 512", "run with --search-memory 1.2 GB or "
                           "more, so the PCA is fitted exactly, not by randomized iteration (1.0 GB given)")]
        assert not any("memory" in n[0] for n in missing_for(cells["oxford"].cells[0], None, tmp_path / "data", tmp_path,
                                                             memory_budget=1_200_000_000))
        assert not any("memory" in n[0] for n in missing_for(cells["baidu-mall"].cells[0], None, tmp_path / "data",
                                                             tmp_path))  # 1,295 indoor rows: 13 MB
    monkeypatch.setenv("COLUMNS", "400")
    assert main(["reproduce", "anyloc", "--table", "2", "--dry-run", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    pca = [x for x in lines if "-PCA " in x and "│" in x]
    assert len(pca) == 12 and not any("not runnable" in x for x in pca)

