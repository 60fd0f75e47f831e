"""A cached vocabulary is served by its name only to the features it was fitted on: the patch stride is
keyed (DINO v1 at 4 vs 8 gives other features) and recorded, a file saved before that is served only where
it proves its stride, and folder names hold no character Windows refuses."""
import pytest
import torch

from vprbench import create_method
from vprbench.aggregation.vocabulary import Vocabulary, vocabulary_dir
from vprbench.errors import VPRBenchError
from vprbench.methods.anyloc_vocabulary import cached_vocabulary_file, save_to_cache

DINO = {"backbone": "dino_vits8", "weights": "random", "layer": 1, "facet": "key", "clusters": 4}


def _centres(seed: int = 0) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(seed)), dim=1)


def test_a_vocabulary_fitted_at_one_stride_never_serves_another(tmp_path):
    at4 = save_to_cache(Vocabulary(_centres(0), {}), "dino_vits8@random", 1, "key", "indoor", tmp_path, stride=4)
    assert at4.parent.parent.name == "dino_vits8@random-l1-key-c4"  # the backbone's own stride: the name as before
    method = create_method("anyloc", **DINO, vocabulary="indoor", cache_dir=tmp_path)  # stride 4, DINO's own
    found = method.provenance()["vocabulary"]
    assert found["file"] == str(at4) and found["fitted_stride"] == 4  # the record tells the stride of the fit
    # was served silently: stride 8 read the stride-4 centres
    with pytest.raises(VPRBenchError, match=r"No 'indoor' vocabulary for dino_vits8@random layer 1 key at stride 8 "):
        create_method("anyloc", **DINO, vocabulary="indoor", stride=8, cache_dir=tmp_path)
    at8 = save_to_cache(Vocabulary(_centres(1), {}), "dino_vits8@random", 1, "key", "indoor", tmp_path, stride=8)
    assert at8.parent.parent.name == "dino_vits8@random-l1-key-c4-s8"
    assert create_method("anyloc", **DINO, vocabulary="indoor", stride=8, cache_dir=tmp_path).vocabulary_info["file"] == str(at8)
    # the file itself, given for the other stride: refused naming both
    with pytest.raises(VPRBenchError, match=r"fitted on backbone dino_vits8@random layer 1 facet key stride 4, but these "
                                            r"features are backbone dino_vits8@random layer 1 facet key stride 8"):
        create_method("anyloc", **DINO, vocabulary=str(at4), stride=8)


def test_a_vocabulary_saved_without_its_stride_is_served_only_where_it_proves_it(tmp_path, cli):
    old = {"layer": 1, "facet": "key", "source": "indoor"}  # as vprbench saved them before the stride was keyed
    path = Vocabulary(_centres(), {**old, "backbone": "dino_vits8@random"}).save(
        vocabulary_dir("dino_vits8@random", 1, "key", 4, "indoor", tmp_path) / "vocabulary.pt")
    with pytest.raises(VPRBenchError, match=r"does not record the patch stride it was fitted at .* stride 4: if it "
                                            r"was fitted at stride 4, import it again with `(vprbench vocabulary import "
                                            r"[^`]+)`, else fit it again") as refused:
        create_method("anyloc", **DINO, vocabulary="indoor", cache_dir=tmp_path)
    assert create_method("anyloc", **DINO, vocabulary=str(path)).vocabulary_info["file"] == str(path)  # vouched for
    # the command the message gives, run as given, makes it servable by name
    said = refused.value.args[0].split("`vprbench ")[1].split("`")[0].split()
    code, _, err = cli(*said, "--cache-dir", str(tmp_path))
    assert code == 0, err
    served = create_method("anyloc", **DINO, vocabulary="indoor", cache_dir=tmp_path).vocabulary_info
    assert served["file"] == str(path) and served["fitted_stride"] == 4
    # a backbone that runs at its patch stride only proves it by its name
    pe = Vocabulary(_centres(), {**old, "facet": "value", "backbone": "pe_spatial_s16@random"}).save(
        vocabulary_dir("pe_spatial_s16@random", 1, "value", 4, "indoor", tmp_path) / "vocabulary.pt")
    method = create_method("anyloc", backbone="pe_spatial_s16", weights="random", layer=1, clusters=4,
                           vocabulary="indoor", cache_dir=tmp_path)
    assert method.vocabulary_info["file"] == str(pe)


def test_vocabulary_folder_names_hold_no_character_windows_refuses(tmp_path):
    backbone = "timm:vit_small_patch16_224.dino"
    folder = vocabulary_dir(backbone, 1, "value", 4, "map-corridor", tmp_path)
    assert folder.relative_to(tmp_path).parts == ("vocabularies", "timm_vit_small_patch16_224.dino-l1-value-c4",
                                                  "map-corridor")  # was 'timm:vit_...'
    assert vocabulary_dir("a", 1, "value", 4, 'x<>:"\\|?*.', tmp_path).name == "x" + "_" * 8
    # a folder written under the old name (Linux) is still read
    old = tmp_path / "vocabularies" / f"{backbone}-l1-value-c4" / "indoor" / "vocabulary.pt"
    Vocabulary(_centres(), {"backbone": backbone, "layer": 1, "facet": "value"}).save(old)
    assert cached_vocabulary_file("indoor", backbone, 1, "value", 4, tmp_path) == old


def test_import_keys_and_records_the_stride(cli, tmp_path):
    Vocabulary(_centres(), {}).save(tmp_path / "v.pt")
    code, out, err = cli("vocabulary", "import", str(tmp_path / "v.pt"), "--source", "indoor", "--backbone",
                         "dino_vits8@random", "--layer", "1", "--facet", "key", "--stride", "8",
                         "--cache-dir", str(tmp_path / "c"))
    assert code == 0, err
    saved = tmp_path / "c" / "vocabularies" / "dino_vits8@random-l1-key-c4-s8" / "indoor" / "vocabulary.pt"
    assert torch.load(saved)["meta"]["stride"] == 8
    code, _, err = cli("vocabulary", "import", str(tmp_path / "v.pt"), "--source", "indoor", "--backbone",
                       "dino_vits8", "--layer", "1", "--facet", "key", "--stride", "3", "--cache-dir", str(tmp_path / "c"))
    assert code == 1 and err.strip().endswith("--stride 3 does not divide the patch 8 of dino_vits8: give one of 1, 2, 4, 8.")


def test_dinov3s_bfloat16_rope_periods_are_keyed_as_in_the_store(tmp_path):
    """A timm: name of DINOv3's release now runs with the release's bfloat16 RoPE periods (its store key says
    so), but its vocabularies kept the key of the float32 periods it ran with before: centres fitted on those
    features (up to 1.2e-2 apart) were served to the new ones."""
    from vprbench.aggregation.vocabulary import vocabulary_key
    from vprbench.methods.anyloc_vocabulary import released_path, released_sources
    from vprbench.store.folder import method_fingerprint

    timm = {"backbone": "timm:vit_small_patch16_dinov3", "weights": "random", "layer": 1, "clusters": 4}
    before = tmp_path / "vocabularies" / "timm_vit_small_patch16_dinov3@random-l1-value-c4" / "indoor" / "vocabulary.pt"
    Vocabulary(_centres(0), {"backbone": "timm:vit_small_patch16_dinov3@random", "layer": 1, "facet": "value",
                             "stride": 16}).save(before)  # as fitted on timm's float32 periods
    legacy = tmp_path / "vocabularies" / "timm:vit_small_patch16_dinov3@random-l1-value-c4" / "indoor" / "vocabulary.pt"
    Vocabulary(_centres(0), {"backbone": "timm:vit_small_patch16_dinov3@random", "layer": 1,
                             "facet": "value"}).save(legacy)  # the name before names were made portable
    with pytest.raises(VPRBenchError, match=r"No 'indoor' vocabulary for timm:vit_small_patch16_dinov3@random layer 1 "
                                            r"value with 4 clusters \(looked in \S+rope_periods-bfloat16"):
        create_method("anyloc", **timm, vocabulary="indoor", cache_dir=tmp_path)  # was served `before`
    now = save_to_cache(Vocabulary(_centres(1), {}), "timm:vit_small_patch16_dinov3@random", 1, "value", "indoor", tmp_path)
    assert now.parent.parent.name == "timm_vit_small_patch16_dinov3@random-l1-value-c4-rope_periods-bfloat16"
    method = create_method("anyloc", **timm, vocabulary="indoor", cache_dir=tmp_path)
    assert method.vocabulary_info["file"] == str(now)
    assert method_fingerprint(method)["rope_periods"] == "bfloat16"  # the same thing in the store key
    # float32 or no RoPE: keys as before, the authors' released folders among them
    assert {released_path(source).parent.parent.name for source in released_sources()} == {"dinov2_vitg14-l31-value-c32"}
    assert vocabulary_key("dinov2_vitg14", 31, "value", 32) == "dinov2_vitg14-l31-value-c32"
    assert vocabulary_key("dinov2_vits14@random", 1, "value", 4) == "dinov2_vits14@random-l1-value-c4"
    assert vocabulary_key("dino_vits8@random", 1, "key", 4, 8) == "dino_vits8@random-l1-key-c4-s8"
    assert vocabulary_key("pe_spatial_s16@random", 1, "value", 4) == "pe_spatial_s16@random-l1-value-c4"
    assert "rope_periods" not in create_method("anyloc", backbone="pe_spatial_s16", weights="random", layer=1,
                                               aggregation="gem").fingerprint()  # RoPE in float32
