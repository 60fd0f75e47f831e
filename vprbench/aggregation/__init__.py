"""Aggregation: local features (patches, keypoints) -> one global descriptor."""
from .vlad import vlad_hard

__all__ = ["vlad_hard"]
