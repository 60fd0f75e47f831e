"""DenseVLAD (Torii et al., CVPR 2015): dense multi-scale RootSIFT, VLAD over a database vocabulary.

SIFT is computed upright on a regular grid (2-pixel step) at four bin sizes (4, 6, 8, 10
pixels), RootSIFT-normalised, hard-assigned to the nearest of 128 words (k-means on a
bounded, seeded sample of database descriptors) and aggregated with intra-normalised VLAD.
The paper's final PCA-whitening to 4096 dimensions is not applied.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import faiss
import numpy as np

from ..aggregation import vlad_hard
from ..errors import VPRBenchError
from ..images import load_rgb
from ..loader import loaded
from .base import Method
from .checks import whole, wholes

#: OpenCV's descriptor bin width is 1.5 x keypoint size
_CV_BIN_PER_SIZE = 1.5


class DenseVLAD(Method):
    needs_fit = True
    batch_size = 8

    def __init__(self, clusters: int = 128, bin_sizes: tuple[int, ...] = (4, 6, 8, 10), step: int = 2,
                 max_side: int = 640, sample: int = 200_000, seed: int = 0, device: str = "cpu"):
        self.clusters = whole("dense-vlad", "clusters", clusters, 2, what="vocabulary size")
        self.bin_sizes = wholes("dense-vlad", "bin_sizes", bin_sizes, what="SIFT bin widths in pixels")
        self.step = whole("dense-vlad", "step", step, what="pixels between grid points")
        self.max_side = whole("dense-vlad", "max_side", max_side, 4 * max(self.bin_sizes),
                              what="longest image side in pixels, at least 4 x the largest bin size")
        self.sample = whole("dense-vlad", "sample", sample, self.clusters, what="descriptors sampled for k-means, at least clusters")
        self.seed = whole("dense-vlad", "seed", seed, 0)
        self.sift = cv2.SIFT_create()
        self.centres: np.ndarray | None = None
        self._grids: dict[tuple[int, int], list] = {}

    def fingerprint(self) -> dict:
        return {"clusters": self.clusters, "bin_sizes": list(self.bin_sizes), "step": self.step,
                "max_side": self.max_side, "sample": self.sample, "seed": self.seed,
                "opencv": cv2.__version__.split(".")[0], "descriptor_version": 1}

    def provenance(self) -> dict:
        return {"weights": {"source": "none"},  # SIFT: nothing learnt but the vocabulary
                "vocabulary": {"source": "map", "fitted_on_evaluated_database": True, "clusters": self.clusters,
                               "seed": self.seed}}

    def load(self, path: Path) -> np.ndarray:
        """The grey image at the working size (at most max_side pixels)."""
        gray = cv2.cvtColor(load_rgb(path), cv2.COLOR_RGB2GRAY)
        scale = min(1.0, self.max_side / max(gray.shape))
        if scale < 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if not self._grid(*gray.shape):
            raise VPRBenchError(f"dense-vlad: image {path} {gray.shape[::-1]} is too small for bin size {max(self.bin_sizes)}")
        return gray

    def rootsift(self, gray: np.ndarray) -> np.ndarray:
        """(n, 128) RootSIFT descriptors on the dense multi-scale grid of a grey image."""
        _, descriptors = self.sift.compute(gray, self._grid(*gray.shape))
        descriptors = descriptors.astype(np.float32)
        descriptors /= np.maximum(descriptors.sum(axis=1, keepdims=True), 1e-12)  # RootSIFT: L1, then sqrt
        return np.sqrt(descriptors)

    def local_features(self, path: Path) -> np.ndarray:
        return self.rootsift(self.load(path))

    def _grid(self, height: int, width: int) -> list:
        """Dense keypoints for an image size (cached: datasets have few distinct sizes)."""
        if (height, width) not in self._grids:
            keypoints = []
            for bin_size in self.bin_sizes:
                margin = 2 * bin_size  # the 4x4-bin window stays inside the image
                for y in range(margin, height - margin + 1, self.step):
                    for x in range(margin, width - margin + 1, self.step):
                        keypoints.append(cv2.KeyPoint(float(x), float(y), bin_size / _CV_BIN_PER_SIZE, 0.0))
            self._grids[(height, width)] = keypoints
        return self._grids[(height, width)]

    def fit(self, database: Sequence[Path]) -> None:
        rng = np.random.default_rng(self.seed)
        per_image = max(1, self.sample // max(1, len(database)))
        chunks = []
        for path in database:
            features = self.local_features(path)
            keep = rng.choice(len(features), size=min(per_image, len(features)), replace=False)
            chunks.append(features[np.sort(keep)])
        sample = np.concatenate(chunks)
        if len(sample) < self.clusters:
            raise VPRBenchError(f"dense-vlad: {len(sample)} sampled descriptors cannot make {self.clusters} clusters")
        kmeans = faiss.Kmeans(sample.shape[1], self.clusters, niter=25, seed=self.seed, verbose=False)
        kmeans.train(sample)
        self.centres = kmeans.centroids.astype(np.float32)

    def fit_state(self) -> dict[str, np.ndarray]:
        return {"centres": self.centres}

    def load_fit_state(self, state: dict[str, np.ndarray]) -> None:
        self.centres = np.asarray(state["centres"], dtype=np.float32)

    def describe(self, images: Sequence) -> np.ndarray:
        if self.centres is None:
            raise VPRBenchError("dense-vlad: the vocabulary is not fitted; evaluate fits it on the database first.")
        return np.stack([vlad_hard(self.rootsift(gray), self.centres, metric="euclidean").numpy()
                         for gray in loaded(self, images)])
