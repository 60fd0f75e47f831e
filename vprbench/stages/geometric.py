"""Geometric verification with classic local features: the re-ranker every learned one is compared to.

Per query and candidate: OpenCV SIFT keypoints (RootSIFT optional: L1-normalise, square root),
Lowe's ratio test on the two nearest neighbours, then RANSAC through OpenCV's USAC (MAGSAC++
scoring) on a fundamental matrix or a homography. A candidate's score is its number of inliers;
candidates with equal counts keep their retrieval order. The USAC random state is fixed, so a
run is repeatable. SIFT features are computed once per image and kept in the feature store
(uint8, as OpenCV quantises them); RootSIFT is made from them when matching, so both share one
store.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from .base import Candidates, RerankOptions, Stage, StageContext, rerank_by_counts

#: fewest correspondences each model is estimated from
MINIMUM = {"fundamental": 8, "homography": 4}
#: OpenCV takes keypoint and iteration counts as C ints: a larger value raised deep inside it
C_INT_MAX = 2**31 - 1


class SiftRansacOptions(RerankOptions):
    features: Literal["rootsift", "sift"] = "rootsift"
    #: SIFT keypoints kept per image (the strongest; 0 = all)
    max_features: int = Field(2000, ge=0, le=C_INT_MAX)
    #: Lowe's ratio: a match is kept when its distance is below ratio x the second nearest's
    ratio: float = Field(0.8, gt=0, le=1)
    model: Literal["fundamental", "homography"] = "fundamental"
    #: RANSAC inlier threshold, pixels
    threshold: float = Field(3.0, gt=0)
    confidence: float = Field(0.999, gt=0, lt=1)
    max_iterations: int = Field(10000, ge=1, le=C_INT_MAX)


#: what `sift_features` gives per image: a stored image that is not is recomputed (features.FeatureStore)
SIFT_FORM = {"points": ("float32", (2,)), "descriptors": ("uint8", (128,))}


def sift_features(path, max_features: int) -> dict[str, np.ndarray]:
    """Keypoints (n, 2) float32 pixel coordinates and SIFT descriptors (n, 128) uint8 of one image."""
    import cv2

    from ..images import load_image

    grey = np.asarray(load_image(path, "L"))
    keypoints, descriptors = cv2.SIFT_create(nfeatures=max_features).detectAndCompute(grey, None)
    if descriptors is None:
        return {"points": np.zeros((0, 2), np.float32), "descriptors": np.zeros((0, 128), np.uint8)}
    points = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
    return {"points": points, "descriptors": np.clip(np.rint(descriptors), 0, 255).astype(np.uint8)}


def matchable(descriptors: np.ndarray, kind: str) -> np.ndarray:
    found = descriptors.astype(np.float32)
    if kind == "rootsift":  # Arandjelovic & Zisserman 2012: Hellinger kernel as a Euclidean distance
        found = np.sqrt(found / np.maximum(found.sum(axis=1, keepdims=True), 1e-12))
    return found


def ratio_matches(query: np.ndarray, database: np.ndarray, ratio: float) -> np.ndarray:
    """(m, 2) index pairs passing the ratio test, by exact nearest neighbours."""
    import cv2

    if len(query) < 2 or len(database) < 2:
        return np.zeros((0, 2), np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, database, k=2)
    kept = [(m.queryIdx, m.trainIdx) for m, n in pairs if m.distance < ratio * n.distance]
    return np.array(kept, dtype=np.int64).reshape(-1, 2)


def inliers(query_points: np.ndarray, database_points: np.ndarray, options: SiftRansacOptions) -> int:
    import cv2

    if len(query_points) < MINIMUM[options.model]:
        return 0
    params = cv2.UsacParams()
    params.confidence, params.maxIterations, params.threshold = options.confidence, options.max_iterations, options.threshold
    params.sampler, params.score, params.loMethod = cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MAGSAC, cv2.LOCAL_OPTIM_SIGMA
    params.randomGeneratorState = 0  # repeatable
    params.isParallel = False
    try:
        if options.model == "homography":
            _, mask = cv2.findHomography(query_points, database_points, params)
        else:
            _, mask = cv2.findFundamentalMat(query_points, database_points, params)
    except cv2.error:  # degenerate configurations: no model, no inliers
        return 0
    return 0 if mask is None else int(np.count_nonzero(mask))


class SiftRansac(Stage):
    track = "re-ranked"
    Options = SiftRansacOptions
    description = "SIFT/RootSIFT, ratio test, USAC (fundamental matrix or homography); score = inliers"

    def feature_identity(self) -> dict:
        import cv2

        from ..images import ORIENTATION

        return {"extractor": "opencv-sift", "opencv": cv2.__version__, "max_features": self.options.max_features,
                "decoding": ORIENTATION}

    def fingerprint(self) -> dict:
        import cv2

        # the inliers are OpenCV's (its SIFT, its USAC): the features are stored per OpenCV version, and so must the
        # record be, or a sweep after an upgrade served the old version's numbers for a run that computes new ones
        return {"opencv": cv2.__version__}

    def _store(self, context: StageContext):
        return context.features("sift", self.feature_identity(), SIFT_FORM)

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        options = self.options

        def count(query, other) -> int:
            query, query_descriptors = query
            pairs = ratio_matches(query_descriptors, matchable(other["descriptors"], options.features), options.ratio)
            return inliers(query["points"][pairs[:, 0]], other["points"][pairs[:, 1]], options)

        return rerank_by_counts(self.name, candidates, context, self._store(context),
                                lambda path: sift_features(path, options.max_features), count,
                                prepare=lambda query: (query, matchable(query["descriptors"], options.features)))

    def stored_bytes(self, context: StageContext) -> int:
        return int(self._store(context).bytes_per_image("database") * context.database.row_count)
