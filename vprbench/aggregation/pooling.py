"""Global pooling of patch features: GAP (mean), GMP (max), GeM (Radenović et al. 2018).

Inputs are (B, N, D) or (N, D) patch features (numpy or torch); outputs are (B, D) or (D,)
float32 tensors, L2-normalised. AnyLoc normalises these only at retrieval time; since
retrieval ranks by cosine similarity, normalising here gives the same ranking and the
`Method` contract asks for unit vectors.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import VPRBenchError
from .vlad import _as_tensor


def _prepare(features) -> tuple[torch.Tensor, bool]:
    x = _as_tensor(features)
    if not torch.is_floating_point(x):
        x = x.float()
    if x.dim() not in (2, 3):
        raise VPRBenchError(f"Pooling needs (N, D) or (B, N, D) patch features, got shape {tuple(x.shape)}.")
    if x.shape[-2] == 0:
        raise VPRBenchError("Pooling got an image with no patch features (N = 0).")
    single = x.dim() == 2
    return (x.unsqueeze(0) if single else x), single


def _finish(pooled: torch.Tensor, single: bool, normalise: bool) -> torch.Tensor:
    pooled = pooled.float()
    if normalise:
        pooled = F.normalize(pooled, dim=-1)
    return pooled[0] if single else pooled


def gap(features, *, normalise: bool = True) -> torch.Tensor:
    """Global average pooling over patches."""
    x, single = _prepare(features)
    return _finish(x.mean(dim=-2), single, normalise)


def gmp(features, *, normalise: bool = True) -> torch.Tensor:
    """Global max pooling over patches (per channel)."""
    x, single = _prepare(features)
    return _finish(x.amax(dim=-2), single, normalise)


def gem(features, p: float = 3.0, *, normalise: bool = True) -> torch.Tensor:
    """Generalised mean as AnyLoc computes it: x = mean(d^p), then |x|^(1/p) * sign(x).

    AnyLoc's patch features can be negative, so the mean of d^3 can be negative; its code
    takes the complex principal root and keeps |root| with the sign of x, i.e. the signed
    real root. For even p a negative d^p cannot occur, so the same formula holds.
    """
    if p <= 0:
        raise VPRBenchError(f"GeM power p must be positive, got {p}.")
    x, single = _prepare(features)
    x = x.double()  # p-th powers of small values lose float32 digits
    m = (x ** p).mean(dim=-2)
    root = m.abs() ** (1.0 / p) * torch.sign(m)
    tiny = torch.finfo(torch.float64).tiny
    lost = ~torch.isfinite(m) | (m.abs() < tiny)
    if lost.any():  # a large p overflowed to infinity or underflowed to (nearly) zero: each channel over its
        # largest magnitude gives the same root without either (it tends to max pooling, as it should); only
        # there, so every other descriptor stays bit for bit what it was
        scale = x.abs().amax(dim=-2).clamp_min(tiny)
        scaled = ((x / scale.unsqueeze(-2)) ** p).mean(dim=-2)
        root = torch.where(lost, scaled.abs() ** (1.0 / p) * torch.sign(scaled) * scale, root)
    return _finish(root, single, normalise)
