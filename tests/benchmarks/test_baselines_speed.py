"""Throughput of a CNN baseline's describe() (random weights in the official layout).
Run: pytest tests/benchmarks --benchmark-enable"""
import numpy as np
import pytest
import torch
from PIL import Image

from vprbench import create_method
from vprbench_baselines.cosplace import GeoLocalizationNet


@pytest.fixture
def cosplace_resnet18(tmp_path):
    path = tmp_path / "ResNet18_512_cosplace.pth"
    torch.save(GeoLocalizationNet("ResNet18", 512).state_dict(), path)
    return create_method("cosplace", backbone="ResNet18", dim=512, weights=str(path), device="cpu")


def test_cosplace_resnet18_describe_8_images_120x160(benchmark, cosplace_resnet18, tmp_path):
    rng = np.random.default_rng(0)
    paths = []
    for i in range(8):
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)).save(paths[-1])
    out = benchmark(cosplace_resnet18.describe, paths)
    assert out.shape == (8, 512)
