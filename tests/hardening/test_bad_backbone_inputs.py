"""Bad input of the backbones, through the command line: a layer beyond the backbone's depth, a
facet its attention cannot give, a checkpoint of another architecture or with missing or
unexpected keys, a vocabulary fitted on another backbone or layer. Each: one line naming both
values and what to do, exit 1, no traceback, nothing stored (no descriptor store, no result, no
vocabulary). An input that is not a multiple of the patch cannot come from the command line
(every entry with timm's embedding crops to the patch, and a fixed input size must be a multiple
of it: checked when the manifest is read)."""
from __future__ import annotations

import pytest
import torch

from vprbench import VPRBenchError
from vprbench.aggregation import Vocabulary
from vprbench.features.catalogue import _entries, backbone_spec, backbones
from vprbench.paths import cache_root

from hostile_files import assert_refused

RUN = ["--dataset", "corridor", "--resize", "64", "64", "--aggregation", "gem"]


@pytest.mark.parametrize("backbone, layer, depth", [("dinov3_vits16", 12, 12), ("pe_spatial_l14", 24, 24),
                                                    ("radio_v3_b16", 40, 12), ("siglip2_b16", -1, 12)])
def test_a_layer_beyond_the_depth_is_refused(backbone, layer, depth, shared_data, cli):
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", backbone, "--layer", layer, "--weights", "random",
                       *RUN, "--data-dir", shared_data)
    assert_refused(code, err, None, f"option layer takes a whole number from 0 to {depth - 1} (0-based block of "
                                     f"{backbone}); got {layer}")


def test_a_facet_the_attention_cannot_give_is_refused(shared_data, cli, monkeypatch):
    entry = backbone_spec("siglip2_b16").model_copy(update={"name": "tokens_only", "facets": ("token",)})
    monkeypatch.setitem(backbones(), "tokens_only", entry)
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", "tokens_only", "--facet", "key", "--layer", "3",
                       "--weights", "random", *RUN, "--data-dir", shared_data)
    assert_refused(code, err, None, "facet=key: backbone tokens_only gives token only", "choose one of those")



def test_an_entry_older_timm_does_not_have_is_refused_naming_the_version(shared_data, cli, monkeypatch):
    """An entry whose architecture the installed timm lacks (an older timm than pyproject.toml asks
    for): before, timm's RuntimeError 'Unknown model' ended the run in a traceback."""
    import timm

    entry = backbone_spec("radio_v3_b16").model_copy(update={"timm": "naflexvit_base_patch16_radio_v99"})
    monkeypatch.setitem(backbones(), "radio_v3_b16", entry)
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", "radio_v3_b16", "--layer", "3", "--weights",
                       "random", *RUN, "--data-dir", shared_data)
    assert_refused(code, err, None, "Backbone radio_v3_b16 is timm's architecture 'naflexvit_base_patch16_radio_v99'",
                   f"the timm installed here ({timm.__version__}) does not have", "pip install -U timm")


@pytest.mark.parametrize("change, said", [
    (lambda s: {k.replace("blocks.", "layers."): v for k, v in s.items()},  # another architecture's names
     ["Missing keys: blocks.0.attn.proj.bias", "Unexpected keys: layers.0.attn.proj.bias"]),
    (lambda s: {k: v for k, v in s.items() if k != "norm.weight"}, ["Missing keys: norm.weight. Unexpected keys: none"]),
    (lambda s: {**s, "blocks.0.attn.gate": torch.zeros(384)}, ["Missing keys: none. Unexpected keys: blocks.0.attn.gate"]),
    (lambda s: {**s, "cls_token": torch.zeros(1, 1, 768)}, ["Shape mismatches: cls_token: file (1, 1, 768) vs model "
                                                            "(1, 1, 384)"]),
])
def test_a_checkpoint_that_does_not_fit_is_refused_naming_the_keys(change, said, tiny_dinov3, shared_data, cli,
                                                                   tmp_path):
    path = tmp_path / "dinov3.pth"
    torch.save(change(tiny_dinov3), path)
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", "dinov3_vits16", "--layer", "1", "--weights", path,
                       *RUN, "--data-dir", shared_data)
    assert_refused(code, err, None, f"{path} for backbone dinov3_vits16: The weights file does not fit this backbone",
                   *said)


@pytest.mark.parametrize("backbone, layer, said", [
    ("dinov3_vits16", 8, "fitted on backbone dinov3_vits16 layer 9 facet value, but these features are backbone "
                         "dinov3_vits16@random layer 8 facet value"),
    ("pe_spatial_s16", 9, "fitted on backbone dinov3_vits16 layer 9 facet value, but these features are backbone "
                          "pe_spatial_s16@random layer 9 facet value"),
])
def test_a_vocabulary_of_another_backbone_or_layer_is_refused(backbone, layer, said, shared_data, cli, tmp_path):
    centres = tmp_path / "v.pt"
    Vocabulary(torch.randn(4, 384), {"backbone": "dinov3_vits16", "layer": 9, "facet": "value"}).save(centres)
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", backbone, "--layer", layer, "--weights", "random",
                       "--aggregation", "vlad", "--clusters", "4", "--vocabulary", centres, "--dataset", "corridor",
                       "--resize", "64", "64", "--data-dir", shared_data)
    assert_refused(code, err, None, said)
    assert not (cache_root() / "vocabularies").exists()


def test_a_fixed_input_size_must_be_a_multiple_of_the_patch_for_timms_embedding():
    text = ('[family]\nfamily = "X"\npatch = 16\ncls_token = true\nregisters = 0\nposition = "learned"\n'
            'position_interpolation = "timm"\nmean = [0.5, 0.5, 0.5]\nstd = [0.5, 0.5, 0.5]\nresize = "fixed"\n'
            'input_size = [224, 298]\ninterpolation = "bilinear"\nfacets = ["token"]\npreprocess = "x"\n'
            'cls = "final-norm"\nnormalise_patches = "always"\nlicence = "x"\ngated = false\npage = "https://x"\n'
            '[[backbone]]\nname = "x"\ntimm = "vit_small_patch16_224"\ndepth = 12\nwidth = 384\nhub = "timm/x"\n')
    with pytest.raises(VPRBenchError, match=r"Backbone manifest bad.toml, entry 'x': input_size "
                                            r"224 x 298 is not a multiple of the patch 16"):
        _entries(text, "bad.toml")
    assert _entries(text.replace("298", "304"), "good.toml")[0].input_size == (224, 304)
