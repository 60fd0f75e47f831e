"""Fixtures of the bad-input suite (its tools are in hostile_files.py)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest


@pytest.fixture
def marker(tmp_path) -> Path:
    """The file a payload would create; tests assert it never exists."""
    return tmp_path / "payload-ran"


@pytest.fixture
def corridor_copy(shared_data, tmp_path) -> Path:
    """<tmp>/data/corridor: the real Corridor as symlinks, so files can be replaced one by one."""
    root = tmp_path / "data" / "corridor"
    shutil.copytree(shared_data / "corridor", root, copy_function=os.symlink)
    return root


@pytest.fixture
def tiny_dinov3(monkeypatch) -> dict:
    """A DINOv3 ViT-S/16 of 2 blocks (listed as dinov3_vits16, so a run takes it) and its weights,
    as an official-format state dict."""
    import torch

    from vprbench.features.backbones import create_model
    from vprbench.features.catalogue import backbone_spec, backbones

    entry = backbone_spec("dinov3_vits16")
    entry = entry.model_copy(update={"depth": 2, "timm_kwargs": {**entry.timm_kwargs, "depth": 2}})
    monkeypatch.setitem(backbones(), "dinov3_vits16", entry)
    torch.manual_seed(0)
    return {k: v.detach().clone() for k, v in create_model(entry).state_dict().items()}


@pytest.fixture
def images(shared_data) -> list:
    """Five Corridor query images."""
    return sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:5]
