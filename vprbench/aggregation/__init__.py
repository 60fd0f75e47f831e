"""Aggregation: local features (patches, keypoints) -> one global descriptor.

pooling (GAP/GMP/GeM), VLAD (hard, AnyLoc soft, textbook soft), the VLAD vocabulary
(cosine k-means, bounded sampler, storage) and PCA-whitening. AnyLoc's vocabulary policy
(domains, released centres) is `vprbench.methods.anyloc_vocabulary`.
"""
from .pca import PCAWhitening, pca_whiten
from .pooling import gap, gem, gmp
from .vlad import vlad_hard, vlad_soft, vlad_soft_official
from .kmeans import FeatureSampler, kmeans_cosine
from .vocabulary import Vocabulary, fit_vocabulary, load_vocabulary

__all__ = [
    "FeatureSampler", "PCAWhitening", "Vocabulary", "fit_vocabulary", "gap", "gem", "gmp",
    "kmeans_cosine", "load_vocabulary", "pca_whiten", "vlad_hard", "vlad_soft", "vlad_soft_official",
]
