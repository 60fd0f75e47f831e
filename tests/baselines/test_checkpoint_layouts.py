"""The baselines' networks have exactly the official checkpoints' parameter names and shapes.

tests/data/checkpoints/*.json list {name: shape} dumped from the authors' own model
definitions (random init), so a released checkpoint loads with no missing or unexpected key.
"""
import json
from pathlib import Path

import pytest
import torch

from vprbench_baselines import cosplace, eigenplaces, mixvpr, netvlad

DATA = Path(__file__).resolve().parents[1] / "data" / "checkpoints"


def reference(name: str) -> dict:
    return json.loads((DATA / f"{name}.json").read_text())


def shapes(model: torch.nn.Module) -> dict:
    return {k: list(v.shape) for k, v in model.state_dict().items()}


def build_on_meta(factory, *args):
    # meta tensors: names and shapes without allocating or initialising weights
    with torch.device("meta"):
        return factory(*args)


@pytest.mark.parametrize("module,name", [(cosplace, "cosplace"), (eigenplaces, "eigenplaces")])
def test_gem_fc_networks_match_official_layout(module, name):
    ref = reference(name)
    assert {b: list(d) for b, d in module.RELEASED.items()} == ref["available"]
    for variant, expected in ref["models"].items():
        backbone, dim = variant.rsplit("_", 1)
        assert shapes(build_on_meta(cosplace.GeoLocalizationNet, backbone, int(dim))) == expected, variant


@pytest.mark.parametrize("backbone,dims", list(cosplace.RELEASED.items()))
def test_every_released_dimension_sets_the_fc_shape(backbone, dims):
    for dim in dims:
        layout = shapes(build_on_meta(cosplace.GeoLocalizationNet, backbone, dim))
        assert layout["aggregation.3.weight"] == [dim, cosplace.CHANNELS[backbone]]
        assert layout["aggregation.3.bias"] == [dim]


def test_mixvpr_matches_official_layout():
    expected = reference("mixvpr")["models"]["resnet50_4096"]
    assert shapes(build_on_meta(mixvpr.MixVPRNet, mixvpr.CONFIGS[4096])) == expected


@pytest.mark.parametrize("dim, channels, rows", [(512, 256, 2), (128, 64, 2)])
def test_mixvpr_smaller_releases_are_the_4096_layout_with_their_files_channels_and_rows(dim, channels, rows):
    """resnet50_MixVPR_{dim}_channels(C)_rows(R).ckpt: only the two projections differ."""
    expected = dict(reference("mixvpr")["models"]["resnet50_4096"])
    expected.update({"aggregator.channel_proj.weight": [channels, 1024], "aggregator.channel_proj.bias": [channels],
                     "aggregator.row_proj.weight": [rows, 400], "aggregator.row_proj.bias": [rows]})
    assert shapes(build_on_meta(mixvpr.MixVPRNet, mixvpr.CONFIGS[dim])) == expected
    assert mixvpr.WEIGHTS[dim].file_name == f"resnet50_MixVPR_{dim}_channels({channels})_rows({rows}).ckpt"


@pytest.mark.parametrize("backbone", list(netvlad.DVGL_RELEASES))
def test_benchmark_netvlad_matches_official_layout(backbone):
    expected = reference("netvlad-dvgl")["models"][f"{backbone}_netvlad"]
    assert shapes(build_on_meta(netvlad.DVGLNetVLAD, backbone)) == expected


@pytest.mark.parametrize("pca_dim", netvlad.WPCA_DIMS)
def test_vgg16_netvlad_wpca_matches_patch_netvlad_layout(pca_dim):
    expected = reference("netvlad-patchnetvlad")["models"][f"vgg16_wpca{pca_dim}"]
    assert shapes(build_on_meta(netvlad.VGG16NetVLAD, pca_dim)) == expected


def test_vgg16_netvlad_full_is_wpca_layout_without_pca():
    expected = reference("netvlad-patchnetvlad")["models"]["vgg16_wpca4096"]
    expected = {k: v for k, v in expected.items() if not k.startswith("WPCA.")}
    assert shapes(build_on_meta(netvlad.VGG16NetVLAD, None)) == expected
