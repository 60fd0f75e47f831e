"""Sequence matching stages (the sequence track): SeqSLAM and the descriptor-sequence score over
any method's stored descriptors; see matching.py for the algorithms, search.py for the blocks."""
from .stage import DiagonalSequence, SeqSLAM

__all__ = ["DiagonalSequence", "SeqSLAM"]
