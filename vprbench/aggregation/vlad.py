"""VLAD (Jégou et al. 2010; Arandjelović & Zisserman 2013 intra-normalisation).

Written once for every VLAD user (DenseVLAD, AnyLoc). Hard assignment sums residuals per
cluster as `sum(x) - n * centre`, and the soft forms use the same algebra with weights
(`sum_q w_qk x_q - (sum_q w_qk) c_k`), so no clusters x features x dim tensor is ever built.

AnyLoc's VLAD class L2-normalises the local features before taking residuals
(`norm_descs=True`); pass `normalise_features=True` for features that are not unit
vectors already (DINO v1 path). DINOv2 patch features arrive normalised.
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


def vlad_hard(
    features, centres, *, metric: str = "cosine", intra_norm: bool = True, normalise_features: bool = False
) -> torch.Tensor:
    """VLAD of local features with hard assignment.

    features: (N, D) or (B, N, D); centres: (K, D), used as they are (not re-normalised).
    Returns (K*D,) or (B, K*D) float32: each cluster block L2-normalised (unused clusters
    stay zero) when `intra_norm`, then the whole vector L2-normalised.
    """
    features, centres, single = _prepare(features, centres)
    if normalise_features:
        # labels are scale-invariant (cosine), so normalising first changes only the residuals, as in AnyLoc
        features = F.normalize(features, dim=-1)
    labels = hard_assign(features, centres, metric)                      # (B, N)
    one_hot = F.one_hot(labels, centres.shape[0]).to(features.dtype)      # (B, N, K)
    sums = one_hot.transpose(1, 2) @ features                             # (B, K, D)
    counts = one_hot.sum(dim=1).unsqueeze(-1)                             # (B, K, 1)
    residuals = sums - counts * centres.unsqueeze(0)
    return _finish(residuals, single, intra_norm)


def _prepare(features, centres) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """(B, N, D) float32 features, (K, D) centres on the same device, and whether input was (N, D)."""
    features = _as_tensor(features).float()
    centres = _as_tensor(centres).float().to(features.device)
    if features.dim() not in (2, 3) or centres.dim() != 2:
        raise VPRBenchError(
            f"VLAD needs features (N, D) or (B, N, D) and centres (K, D); got {tuple(features.shape)} "
            f"and {tuple(centres.shape)}."
        )
    single = features.dim() == 2
    if single:
        features = features.unsqueeze(0)
    if features.shape[-1] != centres.shape[-1]:
        raise VPRBenchError(
            f"Vocabulary dimension {centres.shape[-1]} does not match feature dimension {features.shape[-1]}: "
            "the vocabulary was fitted on other features (backbone, layer or facet)."
        )
    return features, centres, single


def _finish(blocks: torch.Tensor, single: bool, intra_norm: bool) -> torch.Tensor:
    """(B, K, D) per-cluster sums -> intra-normalised (unused clusters stay zero), flattened, L2."""
    if intra_norm:
        blocks = F.normalize(blocks, dim=-1)
    out = F.normalize(blocks.flatten(1), dim=-1)
    return out[0] if single else out


def soft_assign(features: torch.Tensor, centres: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """(B, N, K) weights softmax(temperature * cosine(feature, centre)) over clusters, as AnyLoc.

    Cosine as torch's cosine_similarity (norms clamped at 1e-8), computed by one matmul
    instead of broadcasting (N, K, D).
    """
    f = features / features.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    c = centres / centres.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return torch.softmax(temperature * (f @ c.T), dim=-1)


def vlad_soft_official(
    features, centres, temperature: float = 1.0, *, intra_norm: bool = True, normalise_features: bool = False
) -> torch.Tensor:
    """AnyLoc's soft-assignment VLAD, reproduced as its code computes it.

    Block k is `sum_q w_qk * sum_c (x_q - c_c) = C * (sum_q w_qk x_q) - (sum_q w_qk) * sum_c c_c`:
    every cluster block sums the residuals to ALL centres (not textbook soft VLAD, see
    `vlad_soft`). w = softmax(temperature * cosine), temperature 1.0 as AnyLoc's default.
    Weights use the features as given; residuals use the normalised ones when
    `normalise_features`, like AnyLoc's `norm_descs`.
    """
    features, centres, single = _prepare(features, centres)
    weights = soft_assign(features, centres, temperature)               # (B, N, K)
    if normalise_features:
        features = F.normalize(features, dim=-1)
    weighted = weights.transpose(1, 2) @ features                       # (B, K, D)
    mass = weights.sum(dim=1).unsqueeze(-1)                             # (B, K, 1)
    blocks = centres.shape[0] * weighted - mass * centres.sum(dim=0)
    return _finish(blocks, single, intra_norm)


def vlad_soft(
    features, centres, temperature: float = 1.0, *, intra_norm: bool = True, normalise_features: bool = False
) -> torch.Tensor:
    """Textbook soft-assignment VLAD: block k = sum_q w_qk (x_q - c_k), same weights as AnyLoc."""
    features, centres, single = _prepare(features, centres)
    weights = soft_assign(features, centres, temperature)
    if normalise_features:
        features = F.normalize(features, dim=-1)
    blocks = weights.transpose(1, 2) @ features - weights.sum(dim=1).unsqueeze(-1) * centres.unsqueeze(0)
    return _finish(blocks, single, intra_norm)
