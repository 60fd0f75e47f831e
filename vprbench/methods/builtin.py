"""The core methods, by import path: listing them imports no model code."""
from __future__ import annotations

import tomllib
from importlib.resources import files

ANYLOC = "vprbench.methods.anyloc:AnyLoc"


def anyloc_presets() -> dict[str, dict]:
    """Preset name -> {"description": ..., "options": {...}} from manifests/methods/anyloc.toml."""
    text = (files("vprbench.manifests") / "methods" / "anyloc.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)["presets"]


def core_methods() -> list[dict]:
    """register_method's keywords for each core method and AnyLoc preset."""
    found = [
        {"name": "hog", "factory": "vprbench.methods.hog:HOG",
         "description": "HOG of the resized whole image (VPR-Bench settings); no training"},
        {"name": "dense-vlad", "factory": "vprbench.methods.dense_vlad:DenseVLAD",
         "description": "DenseVLAD: dense multi-scale RootSIFT + VLAD (128 words fitted on the database)"},
        {"name": "sad", "factory": "vprbench.methods.sad:SAD",
         "description": "SeqSLAM's front end: 64x32 grey, 8x8 patch-normalised, mean absolute difference; no training"},
    ]
    found += [{"name": name, "factory": ANYLOC, "defaults": preset.get("options", {}),
               "description": preset.get("description", "")} for name, preset in anyloc_presets().items()]
    found.append({"name": "anyloc", "factory": ANYLOC,
                  "description": "AnyLoc composition; every option settable (see docs/anyloc.md)"})
    return [{**entry, "source": "vprbench"} for entry in found]
