"""Aggregation: local features (patches, keypoints) -> one global descriptor.

pooling (GAP/GMP/GeM), VLAD (hard, AnyLoc soft, textbook soft), the VLAD vocabulary
(cosine k-means, bounded sampler, released centres, domain policies) and PCA-whitening.
"""
from .pca import PCAWhitening, pca_whiten
from .policies import (
    domain_datasets,
    domain_image_size,
    fit_database_vocabulary,
    fit_domain_vocabulary,
    fit_map_vocabulary,
    paper_vocabulary,
    resolve_vocabulary,
    save_to_cache,
)
from .pooling import POOLINGS, gap, gem, gmp
from .vlad import vlad_hard, vlad_soft, vlad_soft_official
from .vocabulary import (
    FeatureSampler,
    Vocabulary,
    fit_vocabulary,
    kmeans_cosine,
    load_vocabulary,
)

__all__ = [
    "POOLINGS", "FeatureSampler", "PCAWhitening", "Vocabulary", "domain_datasets", "domain_image_size",
    "fit_database_vocabulary", "fit_domain_vocabulary", "fit_map_vocabulary", "fit_vocabulary",
    "gap", "gem", "gmp", "kmeans_cosine", "load_vocabulary", "paper_vocabulary", "pca_whiten",
    "resolve_vocabulary", "save_to_cache", "vlad_hard", "vlad_soft", "vlad_soft_official",
]
