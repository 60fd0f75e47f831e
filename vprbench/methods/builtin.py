"""The core methods, registered by import path: listing them imports no model code."""
from __future__ import annotations

import tomllib
from importlib.resources import files

from .registry import register_method

ANYLOC = "vprbench.methods.anyloc:AnyLoc"


def anyloc_presets() -> dict[str, dict]:
    """Preset name -> {"description": ..., "options": {...}} from manifests/methods/anyloc.toml."""
    return tomllib.loads((files("vprbench.manifests") / "methods" / "anyloc.toml").read_text())["presets"]


def register_core() -> None:
    register_method("hog", "vprbench.methods.hog:HOG", source="vprbench",
                    description="HOG of the resized whole image (VPR-Bench settings); no training")
    register_method("dense-vlad", "vprbench.methods.dense_vlad:DenseVLAD", source="vprbench",
                    description="DenseVLAD: dense multi-scale RootSIFT + VLAD (128 words fitted on the database)")
    for name, preset in anyloc_presets().items():
        register_method(name, ANYLOC, defaults=preset.get("options", {}), description=preset.get("description", ""),
                        source="vprbench")
    register_method("anyloc", ANYLOC, source="vprbench",
                    description="AnyLoc composition; every option settable (see docs/anyloc.md)")
