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
