"""Dense feature extraction speed (run: pytest tests/benchmarks --benchmark-enable).

Compares the extractor that stops after the requested block with a full timm forward
pass of the same random ViT-S/14 (what a hook on a complete forward pass costs).
"""
import pytest
import torch

from vprbench.features.backbones import backbone_spec, create_model
from vprbench.features.dense import DenseExtractor


@pytest.fixture(scope="module")
def vits14():
    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    return create_model(spec), spec, torch.randn(2, 3, 224, 308)


def test_stop_after_block_3(benchmark, vits14):
    model, spec, x = vits14
    extractor = DenseExtractor(model, spec, 3, "value")
    out = benchmark(extractor, x)
    assert out.shape == (2, 16 * 22, 384)


def test_full_forward_for_comparison(benchmark, vits14):
    model, spec, x = vits14
    model.set_input_size(img_size=(224, 308))  # timm needs a fixed size without dynamic_img_size
    with torch.no_grad():
        out = benchmark(model.forward_features, x)
    assert out.shape == (2, 1 + 16 * 22, 384)
