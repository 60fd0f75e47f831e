"""Core methods: importing this module registers them."""
from . import anyloc
from .dense_vlad import DenseVLAD
from .hog import HOG
from .registry import register_method

register_method("hog", HOG, description="HOG of the resized whole image (VPR-Bench settings); no training", source="vprbench")
register_method("dense-vlad", DenseVLAD,
                description="DenseVLAD: dense multi-scale RootSIFT + VLAD (128 words fitted on the database)",
                source="vprbench")
anyloc.register()
