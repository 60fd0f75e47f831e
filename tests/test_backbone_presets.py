"""The DINOv3 presets, `methods backbones`, and vocabularies keyed by backbone, layer, facet,
cluster count (and random weights) for any backbone: fitted with `vocabulary fit --domain`
on the real Corridor images, used by name, refused for other features."""
import json
import re

import numpy as np
import pytest
import torch

from vprbench import VPRBenchError, create_method
from vprbench.aggregation import Vocabulary
from vprbench.cli.main import main
from vprbench.features.catalogue import backbones
from vprbench.methods import anyloc_vocabulary
from vprbench.methods.builtin import anyloc_presets


def cli(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def test_dinov3_presets_carry_the_papers_method_over_as_vprbenchs_choice():
    found = anyloc_presets()
    for name, aggregation in (("anyloc-vlad-dinov3", "vlad"), ("anyloc-gem-dinov3", "gem")):
        options = found[name]["options"]
        assert "vprbench's choice" in found[name]["description"]
        assert (options["backbone"], options["layer_for"], options["facet"], options["aggregation"]) == \
            ("dinov3_vitl16", "dinov3_vitl16:18", "value", aggregation)
    assert found["anyloc-vlad-dinov3"]["options"]["clusters"] == 32
    method = create_method("anyloc-vlad-dinov3", weights="random")
    assert (method.backbone, method.layer, method.facet, method.clusters) == ("dinov3_vitl16", 18, "value", 32)
    # 18 of 24 is the paper's 31 of 40 at the same relative depth: the DINOv2 preset lands on it too
    with pytest.warns(UserWarning, match="block 18 at the same relative depth"):
        assert create_method("anyloc-vlad-dinov2", backbone="dinov3_vitl16", weights="random").layer == 18


def test_methods_backbones_lists_every_entry_with_its_licence(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")
    code, out, _ = cli(capsys, "methods", "backbones")
    assert code == 0
    for name, entry in backbones().items():
        row = next(line for line in out.splitlines() if f" {name} " in line)
        assert entry.licence in row and entry.timm_name in row and (("(gated)" in row) == entry.gated)
    monkeypatch.setenv("COLUMNS", "80")  # a narrow terminal or a pipe: names were cut to 'dino_v…'
    code, out, _ = cli(capsys, "methods", "backbones")
    assert all(re.search(rf"│ {re.escape(name)} +│", out) for name in backbones()), out
    code, out, _ = cli(capsys, "methods", "backbones", "--json")
    listed = json.loads(out)
    assert [e["name"] for e in listed] == list(backbones()) and listed[0]["depth"] == backbones()[listed[0]["name"]].depth


@pytest.fixture
def hallways(monkeypatch):
    """A domain holding only Corridor (the real dataset at hand), as the paper's domains hold theirs."""
    policies = anyloc_vocabulary.vocabulary_policies()
    monkeypatch.setitem(policies["domains"], "hallways", [["corridor", 1]])
    monkeypatch.setitem(policies, "order", [*policies["order"], "corridor"])
    monkeypatch.setitem(policies, "image_size", [128, 128])  # the paper's 320 x 320 costs 6x more, for a test
    return "hallways"


def test_domain_vocabulary_of_a_new_family_is_keyed_by_its_features(shared_data, hallways, capsys, tmp_path):
    setting = ["--method", "anyloc-vlad-dinov3", "--backbone", "pe_spatial_s16", "--weights", "random",
               "--layer", "1", "--clusters", "4"]
    code, out, err = cli(capsys, "vocabulary", "fit", "--domain", hallways, *setting, "--budget", "3000",
                         "--data-dir", shared_data)
    assert code == 0, err
    # 111 reference images at 128x128 -> 8 x 8 patches of 16 pixels
    assert "Vocabulary hallways: 4 x 384, 3000 of 7104 features" in out
    folder = tmp_path / "user-cache" / "vprbench" / "vocabularies" / "pe_spatial_s16@random-l1-value-c4" / hallways
    fitted = folder / "vocabulary.pt"
    assert fitted.is_file()
    assert torch.load(fitted)["meta"]["backbone"] == "pe_spatial_s16@random"

    method = create_method("anyloc", backbone="pe_spatial_s16", weights="random", layer=1, clusters=4,
                           vocabulary=hallways, resize="64x64")
    images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    out = method.describe(images)
    assert out.shape == (2, 4 * 384) and np.allclose(np.linalg.norm(out, axis=1), 1, atol=1e-5)
    assert method.provenance()["vocabulary"]["file"] == str(fitted)

    # centres fitted on random weights never serve real ones, nor another layer, facet or cluster count
    (tmp_path / "pe.safetensors").write_bytes(b"a checkpoint of one's own")
    for other in ({"weights": str(tmp_path / "pe.safetensors")}, {"layer": 3}, {"facet": "key"}, {"clusters": 8}):
        options = {"backbone": "pe_spatial_s16", "weights": "random", "layer": 1, "clusters": 4, **other}
        with pytest.raises(VPRBenchError, match="No 'hallways' vocabulary for pe_spatial_s16"):
            create_method("anyloc", vocabulary=hallways, **options)
    # the file itself, given for other features: refused naming both settings
    with pytest.raises(VPRBenchError, match=r"fitted on backbone pe_spatial_s16@random layer 1 facet value, but "
                                            r"these features are backbone pe_spatial_s16@random layer 3 facet value"):
        create_method("anyloc", backbone="pe_spatial_s16", weights="random", layer=3, clusters=4, vocabulary=str(fitted))
    with pytest.raises(VPRBenchError, match=r"fitted on backbone pe_spatial_s16@random .* but these features are "
                                            r"backbone dinov3_vits16@random layer 1"):
        create_method("anyloc", backbone="dinov3_vits16", weights="random", layer=1, clusters=4, vocabulary=str(fitted))


def test_a_vocabulary_fitted_with_ones_own_checkpoint_serves_that_checkpoint_only(tmp_path):
    """A user's checkpoint (not the authors' release) keys vocabularies by its sha256: centres fitted
    on its features are found for it, never for another checkpoint or the official weights."""
    import hashlib

    mine, other = tmp_path / "mine.pth", tmp_path / "other.pth"
    torch.save({"x": torch.zeros(1)}, mine)
    torch.save({"x": torch.ones(1)}, other)
    setting = {"backbone": "pe_spatial_s16", "layer": 1, "clusters": 4}
    key = create_method("anyloc", weights=str(mine), **setting).vocabulary_backbone
    assert key == "pe_spatial_s16@" + hashlib.sha256(mine.read_bytes()).hexdigest()[:16]
    assert create_method("anyloc", **setting).vocabulary_backbone == "pe_spatial_s16"  # the authors' release
    fitted = anyloc_vocabulary.save_to_cache(Vocabulary(torch.randn(4, 384), {"backbone": key, "layer": 1, "facet": "value"}),
                                             key, 1, "value", "hallways")
    found = create_method("anyloc", weights=str(mine), vocabulary="hallways", **setting)
    assert found.provenance()["vocabulary"]["file"] == str(fitted)
    for weights in (str(other), None):
        with pytest.raises(VPRBenchError, match="No 'hallways' vocabulary for pe_spatial_s16"):
            create_method("anyloc", weights=weights, vocabulary="hallways", **setting)
    with pytest.raises(VPRBenchError, match=rf"fitted on backbone {key} layer 1 facet value, but these features are "
                                            r"backbone pe_spatial_s16@[0-9a-f]{16} layer 1"):
        create_method("anyloc", weights=str(other), vocabulary=str(fitted), **setting)


def test_importing_a_vocabulary_under_another_setting_is_refused_and_writes_nothing(capsys, tmp_path):
    Vocabulary(torch.randn(4, 384), {"backbone": "dinov3_vits16", "layer": 9, "facet": "value"}).save(tmp_path / "v.pt")
    code, _, err = cli(capsys, "vocabulary", "import", tmp_path / "v.pt", "--source", "indoor",
                       "--backbone", "dinov3_vits16", "--layer", "8", "--facet", "value")
    assert code != 0 and len(err.strip().splitlines()) == 1
    assert "fitted on backbone dinov3_vits16 layer 9 facet value, but these features are backbone dinov3_vits16 layer 8" in err
    assert not (tmp_path / "user-cache" / "vprbench" / "vocabularies").exists()
    code, _, err = cli(capsys, "vocabulary", "import", tmp_path / "v.pt", "--source", "indoor",
                       "--backbone", "dinov3_vits16", "--layer", "9", "--facet", "value")
    assert code == 0, err


def test_reproduce_backbones_plan_lists_what_each_row_needs(capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("COLUMNS", "1000")  # one line per row
    code, out, err = cli(capsys, "reproduce", "anyloc", "--table", "backbones", "--dry-run",
                         "--data-dir", tmp_path / "no-data")
    assert code == 0, err
    assert "192 cells to evaluate" in " ".join(out.split())  # 16 rows x the 12 datasets of Tables II and III
    rows = {line.split("│")[1].strip(): line for line in out.splitlines() if line.startswith("│ ")}
    assert len(rows) == 16 and all(" 12 " in line and "12 datasets (notes below)" in line for line in rows.values())
    notes = dict(re.findall(r"^\[(\d+)\] (.*)$", out, re.MULTILINE))

    def needs(row):  # the notes a row refers to, each said once below the table
        return " | ".join(notes[n] for n in re.findall(r"\[(\d+)\]", rows[row].split("│")[5]))

    # the paper's setting has released centres (fetched, not fitted); another backbone needs its domain
    # vocabularies fitted
    paper = needs("VLAD DINOv2 ViT-G/14 (paper)")
    assert "vocabulary fit" not in paper and "the authors' vocabulary 'indoor': run 'vprbench vocabulary download" in paper
    assert "vocabular" not in needs("GeM SigLIP 2 B/16")
    assert ("vocabularies D = indoor, urban, hawkins, laurel-caverns, aerial: run 'vprbench vocabulary fit --domain D "
            f"--method anyloc-vlad-dinov3 --backbone dinov3_vitl16 --layer 18 --facet value --clusters 32 --data-dir "
            f"{tmp_path / 'no-data'}'") \
        in needs("VLAD DINOv3 ViT-L/16")  # the run's data root: the fit reads the same datasets
    assert "gated, DINOv3 License: request access at https://github.com/facebookresearch/dinov3" in needs("GeM DINOv3 ViT-B/16")
    assert "huggingface.co/timm/vit_pe_spatial_base_patch16_512.fb" in needs("VLAD PE-spatial B/16")
    # timm's weights are all model.safetensors: each named by its repository, not said as another's
    assert "weights timm/naflexvit_base_patch16_radio_v3.c_radio/model.safetensors: let vprbench download " \
           "https://huggingface.co/timm/naflexvit_base_patch16_radio_v3.c_radio (" in needs("VLAD RADIO v3 B/16")
    missing = sorted(re.findall(r"^dataset (\S+): ", "\n".join(notes.values()), re.MULTILINE))
    assert len(missing) == 12 and missing[:2] == ["17places", "baidu-mall"]
