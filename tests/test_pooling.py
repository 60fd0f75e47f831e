import numpy as np
import pytest
import torch

from vprbench.aggregation import gap, gem, gmp
from vprbench.errors import VPRBenchError

# one image, 2 patches, 2 channels
PATCHES = torch.tensor([[1.0, -2.0], [3.0, 0.0]])


def test_gap_is_normalised_mean():
    # mean = (2, -1) -> / sqrt(5)
    assert torch.allclose(gap(PATCHES), torch.tensor([2.0, -1.0]) / 5 ** 0.5)
    assert torch.allclose(gap(PATCHES, normalise=False), torch.tensor([2.0, -1.0]))


def test_gmp_is_channel_max():
    assert torch.allclose(gmp(PATCHES, normalise=False), torch.tensor([3.0, 0.0]))
    assert torch.allclose(gmp(PATCHES), torch.tensor([1.0, 0.0]))


def test_gem_signed_real_root():
    # channel 0: mean(1, 27) = 14 -> 14^(1/3); channel 1: mean(-8, 0) = -4 -> -(4^(1/3))
    out = gem(PATCHES, normalise=False)
    assert out[0].item() == pytest.approx(14 ** (1 / 3), rel=1e-6)
    assert out[1].item() == pytest.approx(-(4 ** (1 / 3)), rel=1e-6)
    expected = np.array([14 ** (1 / 3), -(4 ** (1 / 3))])
    assert np.allclose(gem(PATCHES).numpy(), expected / np.linalg.norm(expected), atol=1e-6)


def test_gem_p1_equals_gap_and_batches_match_single_images():
    batch = torch.randn(3, 7, 5, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(gem(batch, p=1), gap(batch), atol=1e-6)
    stacked = torch.stack([gem(image) for image in batch])
    assert torch.equal(gem(batch), stacked)  # no dependence on batch composition
    assert gem(batch.numpy()).shape == (3, 5)


@pytest.mark.parametrize("p", [1e4, 1e20])
def test_gem_of_a_large_power_tends_to_max_pooling(p):
    """x**p overflowed to inf (NaN descriptors) or underflowed to all zeros, silently."""
    torch.manual_seed(0)
    features = torch.rand(2, 50, 8) + 0.1
    pooled = gem(features, p)
    assert torch.isfinite(pooled).all()
    assert torch.allclose(pooled, gmp(features), atol=1e-3)


def test_gem_of_ordinary_features_is_bit_for_bit_the_formula():
    """Rescaling every channel (for large powers) moved ordinary descriptors in their last bit: stored
    GeM descriptors and records no longer matched a new run's exactly."""
    features = torch.randn(50, 200, 128, generator=torch.Generator().manual_seed(0))
    for p in (1.0, 3.0):
        m = (features.double() ** p).mean(dim=-2)
        formula = m.abs() ** (1 / p) * torch.sign(m)
        assert torch.equal(gem(features, p, normalise=False), formula.float())
        assert torch.equal(gem(features, p), torch.nn.functional.normalize(formula.float(), dim=-1))


def test_pooling_errors():
    with pytest.raises(VPRBenchError, match="p must be positive"):
        gem(PATCHES, p=0)
    with pytest.raises(VPRBenchError, match=r"\(N, D\) or \(B, N, D\)"):
        gap(torch.zeros(5))
    with pytest.raises(VPRBenchError, match="no patch features"):
        gmp(torch.zeros(0, 4))
