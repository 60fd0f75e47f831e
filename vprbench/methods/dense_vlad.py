"""DenseVLAD (Torii et al., CVPR 2015): dense multi-scale RootSIFT, VLAD over a 128-word vocabulary.

SIFT is computed upright on a regular grid (2-pixel step) at four bin sizes (4, 6, 8, 10
pixels), RootSIFT-normalised, hard-assigned to the nearest of 128 words (k-means on a
bounded, seeded sample of descriptors) and aggregated with intra-normalised VLAD.
The paper's final PCA-whitening to 4096 dimensions is not applied.

Every bin size gives 128-dimensional descriptors of its own keypoints (scales are pooled, not
concatenated), so a vocabulary is (clusters, 128) and the descriptor clusters x 128.
Where the words come from is the `vocabulary` option (see `vprbench.methods.dense_vlad_vocabulary`):
the evaluated database ("map"), another dataset or domain, a folder of images, or a file.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import cv2
import faiss
import numpy as np

from ..aggregation import vlad_hard
from ..errors import VPRBenchError
from ..images import load_rgb
from ..loader import loaded
from .base import Method, fitted_centres
from .checks import text, whole, wholes
from .dense_vlad_vocabulary import SIFT_DIM, VocabularySource, cached_vocabulary, parse_vocabulary

#: OpenCV's descriptor bin width is 1.5 x keypoint size
_CV_BIN_PER_SIZE = 1.5


class DenseVLAD(Method):
    batch_size = 8
    device = "cpu"  # OpenCV SIFT on the CPU, whatever --device says (checked, then unused): the record says so

    def __init__(self, clusters: int = 128, bin_sizes: tuple[int, ...] = (4, 6, 8, 10), step: int = 2,
                 max_side: int = 640, sample: int = 200_000, seed: int = 0, vocabulary: str = "map",
                 device: str = "cpu", cache_dir=None, data_dir=None):
        self.clusters = whole("dense-vlad", "clusters", clusters, 2, what="vocabulary size")
        self.bin_sizes = wholes("dense-vlad", "bin_sizes", bin_sizes, what="SIFT bin widths in pixels")
        self.step = whole("dense-vlad", "step", step, what="pixels between grid points")
        self.max_side = whole("dense-vlad", "max_side", max_side, 4 * max(self.bin_sizes),
                              what="longest image side in pixels, at least 4 x the largest bin size")
        self.sample = whole("dense-vlad", "sample", sample, self.clusters, what="descriptors sampled for k-means, at least clusters")
        self.seed = whole("dense-vlad", "seed", seed, 0)
        self.source: VocabularySource = parse_vocabulary(
            text("dense-vlad", "vocabulary", vocabulary, "map, a dataset, a domain, a folder of images or a file"))
        self.cache_dir, self.data_dir = cache_dir, data_dir
        #: "map" fits on the evaluated database; any other source is fitted (or read) before describing
        self.needs_fit = self.source.kind == "map"
        self.dataset: str | None = None
        self.vocabulary_info: dict = {}
        self.sift = cv2.SIFT_create()
        self.centres: np.ndarray | None = None
        #: sha256 of the images of a folder vocabulary (the record checks them against the evaluated dataset)
        self.folder_digests: set[str] = set()
        self._grids: dict[tuple[int, int], list] = {}

    def use_dataset(self, name: str) -> None:
        self.dataset = name

    # ------------------------------------------------------------ identity
    def fit_recipe(self) -> dict:
        """What a fitted vocabulary depends on besides the images it is fitted on."""
        return {"method": "dense-vlad", "clusters": self.clusters, "bin_sizes": list(self.bin_sizes), "step": self.step,
                "max_side": self.max_side, "sample": self.sample, "seed": self.seed,
                "opencv": cv2.__version__.split(".")[0], "descriptor_version": 1}

    def fingerprint(self) -> dict:
        found = {k: v for k, v in self.fit_recipe().items() if k != "method"}
        if not self.needs_fit:  # a vocabulary from elsewhere is identified by its centres' bytes
            found["vocabulary"] = "sha256:" + _sha256(self.vocabulary_centres())
        return found

    def provenance(self) -> dict:
        # SIFT has no learnt weights; the vocabulary is learnt, and says from what
        return {"weights": {"source": "none"}, "vocabulary": self.vocabulary_provenance()}

    def vocabulary_provenance(self) -> dict:
        info = {"option": self.source.option, "clusters": self.clusters, "seed": self.seed, "sample": self.sample}
        if self.needs_fit:
            info.update(source="fitted", fitted_on=f"the database of {self.dataset}" if self.dataset else
                        "the database given to fit()", fitted_on_evaluated_database=True)
        else:
            info.update(self.vocabulary_info)
            info["fitted_on_evaluated_database"] = self.source.includes(self.dataset, self.vocabulary_info)
        if self.centres is not None:
            info["centres_sha256"] = _sha256(self.centres)
        return info

    def fitted_image_digests(self) -> dict[str, set[str]]:
        return {"vocabulary": self.folder_digests} if self.folder_digests else {}

    # ------------------------------------------------------------ local features
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

    # ------------------------------------------------------------ vocabulary
    def fit_centres(self, images: Sequence[Path]) -> np.ndarray:
        """k-means words of a seeded sample of the images' descriptors (the same quota per image)."""
        rng = np.random.default_rng(self.seed)
        per_image = max(1, self.sample // max(1, len(images)))
        chunks = []
        for path in images:
            features = self.local_features(path)
            keep = rng.choice(len(features), size=min(per_image, len(features)), replace=False)
            chunks.append(features[np.sort(keep)])
        sample = np.concatenate(chunks) if chunks else np.zeros((0, SIFT_DIM), np.float32)
        if len(sample) < self.clusters:
            raise VPRBenchError(f"dense-vlad: {len(sample)} sampled descriptors cannot make {self.clusters} clusters")
        return kmeans_words(sample, self.clusters, self.seed)

    def fit(self, database: Sequence[Path]) -> None:
        if self.needs_fit:
            self.centres = self.fit_centres(database)

    def vocabulary_centres(self) -> np.ndarray:
        """The centres of a vocabulary from elsewhere: read, or fitted once and cached in cache_dir."""
        if self.centres is None:
            self.centres, self.vocabulary_info = cached_vocabulary(self, self.source)
        return self.centres

    def fit_state(self) -> dict[str, np.ndarray]:
        return {"centres": self.centres} if self.needs_fit else {}

    def load_fit_state(self, state: dict[str, np.ndarray]) -> None:
        self.centres = fitted_centres(state, self.clusters, SIFT_DIM, "dense-vlad")  # read from the cache: checked

    def describe(self, images: Sequence) -> np.ndarray:
        if self.centres is None and self.needs_fit:
            raise VPRBenchError("dense-vlad: the vocabulary is not fitted; evaluate fits it on the database first.")
        centres = self.vocabulary_centres()
        return np.stack([vlad_hard(self.rootsift(gray), centres, metric="euclidean").numpy()
                         for gray in loaded(self, images)])


#: OpenMP threads faiss's k-means runs on, whatever the machine's or torchrun's count: its centres
#: depend on the count (one sample gave another vocabulary at each of 1, 2, 3 and 8 threads). 2: the
#: count the published Corridor runs were fitted with, whose vocabulary this keeps
KMEANS_THREADS = 2


def kmeans_words(sample: np.ndarray, clusters: int, seed: int) -> np.ndarray:
    """faiss k-means (25 iterations) of the sampled descriptors: (clusters, D) float32 centres, the
    same on any thread count (the caller's count is restored)."""
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(KMEANS_THREADS)
    try:
        kmeans = faiss.Kmeans(sample.shape[1], clusters, niter=25, seed=seed, verbose=False)
        kmeans.train(sample)
    finally:
        faiss.omp_set_num_threads(before)
    return kmeans.centroids.astype(np.float32)


def _sha256(centres: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(centres, dtype=np.float32).tobytes()).hexdigest()
