"""VLAD (Jégou et al. 2010; Arandjelović & Zisserman 2013 intra-normalisation).

Written once for every VLAD user (DenseVLAD, AnyLoc). Hard assignment sums residuals per
cluster as `sum(x) - n * centre`, so no clusters x features x dim tensor is ever built.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import VPRBenchError


def _as_tensor(x) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x)) if isinstance(x, np.ndarray) else x


def hard_assign(features: torch.Tensor, centres: torch.Tensor, metric: str = "cosine") -> torch.Tensor:
    """Index of each feature's centre: max cosine (AnyLoc) or min Euclidean distance (textbook)."""
    if metric == "cosine":
        # AnyLoc's form: a / (|a| + 1e-8) on both sides
        f = features / (features.norm(dim=-1, keepdim=True) + 1e-8)
        c = centres / (centres.norm(dim=-1, keepdim=True) + 1e-8)
        return (f @ c.T).argmax(dim=-1)
    if metric == "euclidean":
        return torch.cdist(features, centres.unsqueeze(0) if features.dim() == 3 else centres).argmin(dim=-1)
    raise VPRBenchError(f"Unknown VLAD assignment metric {metric!r}: use 'cosine' or 'euclidean'")


def vlad_hard(features, centres, *, metric: str = "cosine", intra_norm: bool = True) -> torch.Tensor:
    """VLAD of local features with hard assignment.

    features: (N, D) or (B, N, D); centres: (K, D), used as they are (not re-normalised).
    Returns (K*D,) or (B, K*D) float32: each cluster block L2-normalised (unused clusters
    stay zero) when `intra_norm`, then the whole vector L2-normalised.
    """
    features, centres = _as_tensor(features).float(), _as_tensor(centres).float().to(_as_tensor(features).device)
    single = features.dim() == 2
    if single:
        features = features.unsqueeze(0)
    if features.shape[-1] != centres.shape[-1]:
        raise VPRBenchError(
            f"Vocabulary dimension {centres.shape[-1]} does not match feature dimension {features.shape[-1]}: "
            "the vocabulary was fitted on other features (backbone, layer or facet)."
        )
    labels = hard_assign(features, centres, metric)                      # (B, N)
    one_hot = F.one_hot(labels, centres.shape[0]).to(features.dtype)      # (B, N, K)
    sums = one_hot.transpose(1, 2) @ features                             # (B, K, D)
    counts = one_hot.sum(dim=1).unsqueeze(-1)                             # (B, K, 1)
    residuals = sums - counts * centres.unsqueeze(0)
    if intra_norm:
        residuals = F.normalize(residuals, dim=-1)
    out = F.normalize(residuals.flatten(1), dim=-1)
    return out[0] if single else out
