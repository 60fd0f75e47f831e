import pytest
import torch
import torch.nn.functional as F

from vprbench.aggregation import vlad_hard, vlad_soft, vlad_soft_official
from vprbench.errors import VPRBenchError


def literal_official_soft(x, centres, temperature, normalise):
    """Line-by-line loop form of AnyLoc's soft VLAD (residuals to every centre per block)."""
    weights = torch.softmax(temperature * F.cosine_similarity(x[:, None, :], centres[None], dim=2), dim=1)
    if normalise:
        x = F.normalize(x)
    residuals = x[:, None, :] - centres[None]                    # (N, K, D)
    blocks = []
    for k in range(len(centres)):
        total = (weights[:, k, None, None] * residuals).reshape(-1, x.shape[1]).sum(0)
        blocks.append(F.normalize(total, dim=0))
    return F.normalize(torch.cat(blocks), dim=0)


def literal_textbook_soft(x, centres, temperature):
    weights = torch.softmax(temperature * F.cosine_similarity(x[:, None, :], centres[None], dim=2), dim=1)
    blocks = [F.normalize((weights[:, k, None] * (x - centres[k])).sum(0), dim=0) for k in range(len(centres))]
    return F.normalize(torch.cat(blocks), dim=0)


@pytest.fixture
def data():
    g = torch.Generator().manual_seed(3)
    return torch.randn(2, 40, 6, generator=g) * 2, torch.randn(5, 6, generator=g)


@pytest.mark.parametrize("temperature", [1.0, 7.5])
@pytest.mark.parametrize("normalise", [False, True])
def test_official_soft_matches_literal_loop(data, temperature, normalise):
    x, centres = data
    ours = vlad_soft_official(x, centres, temperature, normalise_features=normalise)
    for b in range(2):
        assert torch.allclose(ours[b], literal_official_soft(x[b], centres, temperature, normalise), atol=1e-6)


def test_textbook_soft_matches_literal_loop_and_differs_from_official(data):
    x, centres = data
    ours = vlad_soft(x[0], centres, 2.0)
    assert ours.shape == (30,)
    assert torch.allclose(ours, literal_textbook_soft(x[0], centres, 2.0), atol=1e-6)
    assert (ours - vlad_soft_official(x[0], centres, 2.0)).abs().max() > 1e-2


def test_official_soft_hand_computed_two_clusters():
    # one feature; centres (1,0) and (0,1); temperature 0 -> equal weights 1/2
    # block k = 1/2 * (2x - (c0 + c1)) = x - (0.5, 0.5) for both clusters
    x = torch.tensor([[2.0, 0.0]])
    centres = torch.eye(2)
    block = F.normalize(torch.tensor([1.5, -0.5]), dim=0)
    expected = F.normalize(torch.cat([block, block]), dim=0)
    assert torch.allclose(vlad_soft_official(x, centres, 0.0), expected, atol=1e-7)


def test_hard_vlad_unused_cluster_stays_zero():
    x = torch.tensor([[1.0, 0.1], [1.0, -0.1], [0.1, 1.0]])
    centres = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])  # cluster 2 gets no feature
    out = vlad_hard(x, centres).reshape(3, 2)
    # cluster 0: residuals (0, 0.1) + (0, -0.1) sum to zero; cluster 1: (0.1, 0); cluster 2 unused
    assert torch.equal(out[2], torch.zeros(2))
    assert torch.allclose(out[1], torch.tensor([1.0, 0.0]))
    assert torch.equal(out[0], torch.zeros(2))


def test_soft_vlad_dimension_error(data):
    x, centres = data
    with pytest.raises(VPRBenchError, match="Vocabulary dimension 7 does not match feature dimension 6"):
        vlad_soft_official(x, torch.zeros(5, 7))
    with pytest.raises(VPRBenchError, match="Vocabulary dimension"):
        vlad_soft(x, torch.zeros(5, 7))
