"""Cosine k-means as AnyLoc fits its VLAD vocabularies, and a bounded-memory sampler.

AnyLoc fits its centres with fast_pytorch_kmeans 0.1.6 in cosine mode on L2-normalised
patch features. `kmeans_cosine` follows that algorithm step by step:
- initial centres: `RandomState(seed).choice(n, k, replace=False)` rows of the features
  (the official scripts call `np.random.seed(42)` first, so the draw is the same);
- assignment: argmax of `a/(|a|+1e-8) @ (c/(|c|+1e-8)).T`;
- update: plain mean of the assigned features (not re-normalised), an empty cluster
  becomes a zero vector;
- stop after 100 iterations or once sum((new - old)^2) <= 1e-4 (the update is applied
  before the test).

The official fit keeps every patch of every database image in memory (~94 GB for
Pitts-30k with ViT-G). `FeatureSampler` keeps a uniform random sample of at most
`budget` features, fed image by image (reservoir sampling), so memory does not grow with
the dataset. `exact=True` in `fit_vocabulary` reproduces the official fit on all patches.
"""
from __future__ import annotations

import numpy as np
import torch

from ..errors import VPRBenchError

#: AnyLoc's k-means settings (fast_pytorch_kmeans 0.1.6 defaults + AnyLoc's seed)
KMEANS_SEED, KMEANS_MAX_ITER, KMEANS_TOL = 42, 100, 1e-4
#: default sample budget (features): 250k x 1536 float32 (ViT-G) is 1.5 GB; ViT-S 0.4 GB
DEFAULT_BUDGET = 250_000

def _cosine_labels(x: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    a = x / (x.norm(dim=-1, keepdim=True) + 1e-8)
    b = centres / (centres.norm(dim=-1, keepdim=True) + 1e-8)
    return (a @ b.transpose(-2, -1)).max(dim=-1)[1]


def kmeans_cosine(
    features, clusters: int, *, seed: int = KMEANS_SEED, max_iter: int = KMEANS_MAX_ITER,
    tol: float = KMEANS_TOL, init: torch.Tensor | None = None,
) -> tuple[torch.Tensor, int]:
    """Cosine k-means as fast_pytorch_kmeans 0.1.6 -> ((K, D) float32 centres, iterations run).

    `features` (N, D) are used as given (AnyLoc normalises them first: see `fit_vocabulary`).
    """
    x = torch.as_tensor(np.ascontiguousarray(features) if isinstance(features, np.ndarray) else features).float()
    if x.dim() != 2:
        raise VPRBenchError(f"k-means needs (N, D) features, got shape {tuple(x.shape)}.")
    n = x.shape[0]
    if clusters < 1:
        raise VPRBenchError(f"Number of clusters must be at least 1, got {clusters}.")
    if clusters > n:
        raise VPRBenchError(
            f"Cannot fit {clusters} clusters on {n} features: use fewer clusters or more images "
            "(or a larger sample budget)."
        )
    if init is None:
        centres = x[np.random.RandomState(seed).choice(n, size=[clusters], replace=False)]
    else:
        centres = torch.as_tensor(init).float()
    arranged = torch.arange(clusters)[:, None]
    iterations = 0
    for iterations in range(1, max_iter + 1):
        closest = _cosine_labels(x, centres)
        # the (K, N) mask and matmul are the official update; same ops give the same rounding
        mask = (closest[None].expand(clusters, -1) == arranged).float()
        means = mask @ x / mask.sum(-1)[..., :, None]
        means[means != means] = 0  # empty cluster: 0/0 -> zero vector, as the official code
        error = (means - centres).pow(2).sum()
        centres = means
        if error <= tol:
            break
    return centres, iterations


def _unit(x: np.ndarray) -> np.ndarray:
    """Rows L2-normalised as F.normalize (norm clamped at 1e-12); only kept rows pay for it."""
    x = x.astype(np.float32, copy=False)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


class FeatureSampler:
    """Uniform random sample of at most `budget` features from a stream (reservoir sampling).

    Feed one image's (N, D) features at a time with `add`; features are L2-normalised on the
    way in (AnyLoc fits on normalised features). The buffer is allocated once at
    `budget x D` and never grows; the sample depends only on the seed and the feeding order.
    """

    def __init__(self, budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED):
        if budget < 1:
            raise VPRBenchError(f"Sample budget must be at least 1 feature, got {budget}.")
        self.budget, self.seed = budget, seed
        self.rng = np.random.default_rng(seed)
        self.buffer: np.ndarray | None = None
        self.seen = 0  # features offered so far

    def add(self, features) -> None:
        x = features.detach().cpu().numpy() if isinstance(features, torch.Tensor) else np.asarray(features)
        x = x.reshape(-1, x.shape[-1])
        if self.buffer is None:
            self.buffer = np.empty((self.budget, x.shape[1]), dtype=np.float32)
        elif x.shape[1] != self.buffer.shape[1]:
            raise VPRBenchError(f"Feature dimension changed from {self.buffer.shape[1]} to {x.shape[1]} while sampling.")
        filled = min(self.seen, self.budget)
        take = min(self.budget - filled, len(x))
        self.buffer[filled:filled + take] = _unit(x[:take])
        rest = x[take:]
        if len(rest):
            # item t (0-based over the stream) replaces slot j ~ U{0..t} when j < budget
            t = self.seen + take + np.arange(len(rest))
            slots = self.rng.integers(0, t + 1)
            keep = np.flatnonzero(slots < self.budget)
            # a later item overwrites an earlier one in the same slot: keep the last per slot
            _, first = np.unique(slots[keep][::-1], return_index=True)
            chosen = keep[::-1][first]
            self.buffer[slots[chosen]] = _unit(rest[chosen])
        self.seen += len(x)

    def sample(self) -> np.ndarray:
        """The current sample, (min(seen, budget), D) float32 (a view, no copy)."""
        if self.buffer is None:
            raise VPRBenchError("No features were given to the vocabulary sampler (no images?).")
        return self.buffer[: min(self.seen, self.budget)]
