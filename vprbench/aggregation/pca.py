"""PCA-whitening of global descriptors (AnyLoc's -PCA presets: 49,152 -> 512 dims).

As AnyLoc: sklearn `PCA(dim, svd_solver="full", whiten=True)` fitted on the dataset's
database descriptors, applied to database and queries, then L2 normalisation.
"""
from __future__ import annotations

import numpy as np

from ..errors import VPRBenchError

DEFAULT_PCA_DIM = 512


class PCAWhitening:
    """Fit on database descriptors, transform any descriptors; state is plain numpy arrays."""

    def __init__(self, dim: int = DEFAULT_PCA_DIM):
        if dim < 1:
            raise VPRBenchError(f"PCA dimension must be at least 1, got {dim}.")
        self.dim = dim
        self.mean: np.ndarray | None = None
        self.projection: np.ndarray | None = None  # (dim, D): components / sqrt(explained variance)

    def fit(self, database: np.ndarray) -> "PCAWhitening":
        from sklearn.decomposition import PCA

        database = np.asarray(database, dtype=np.float32)
        if database.ndim != 2:
            raise VPRBenchError(f"PCA needs (N, D) descriptors, got shape {database.shape}.")
        n, d = database.shape
        if self.dim > min(n, d):
            raise VPRBenchError(
                f"PCA dimension {self.dim} is larger than the number of database images ({n}) or the "
                f"descriptor dimension ({d}): choose pca_dim <= {min(n, d)}."
            )
        pca = PCA(self.dim, svd_solver="full", whiten=True).fit(database)
        self.mean = pca.mean_.astype(np.float32)
        self.projection = (pca.components_ / np.sqrt(pca.explained_variance_)[:, None]).astype(np.float32)
        return self

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, dim) float32, whitened and L2-normalised."""
        if self.projection is None:
            raise VPRBenchError("PCA-whitening was used before being fitted on database descriptors.")
        descriptors = np.asarray(descriptors, dtype=np.float32)
        if descriptors.ndim != 2 or descriptors.shape[1] != self.projection.shape[1]:
            raise VPRBenchError(
                f"PCA was fitted on {self.projection.shape[1]}-dimensional descriptors, got shape {descriptors.shape}."
            )
        out = (descriptors - self.mean) @ self.projection.T
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        return (out / np.maximum(norms, 1e-12)).astype(np.float32)

    def state(self) -> dict[str, np.ndarray]:
        """For `Method.fit_state()`: saved beside the descriptors."""
        if self.projection is None:
            raise VPRBenchError("PCA-whitening has no state before it is fitted.")
        return {"pca_mean": self.mean, "pca_projection": self.projection}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> "PCAWhitening":
        pca = cls(int(state["pca_projection"].shape[0]))
        pca.mean = np.asarray(state["pca_mean"], dtype=np.float32)
        pca.projection = np.asarray(state["pca_projection"], dtype=np.float32)
        return pca


def pca_whiten(database: np.ndarray, queries: np.ndarray, dim: int = DEFAULT_PCA_DIM) -> tuple[np.ndarray, np.ndarray]:
    """Fit on `database`, return (database, queries) whitened to `dim` and L2-normalised
    (drop-in for `Method.postprocess`)."""
    pca = PCAWhitening(dim).fit(database)
    return pca.transform(database), pca.transform(queries)
