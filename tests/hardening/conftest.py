"""Fixtures of the bad-input suite (its tools are in hostile_files.py)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from vprbench.cli.main import main


@pytest.fixture
def marker(tmp_path) -> Path:
    """The file a payload would create; tests assert it never exists."""
    return tmp_path / "payload-ran"


@pytest.fixture
def cli(capsys):
    """cli(*args) -> (exit code, stdout, stderr) of the vprbench command, in process."""

    def run(*args) -> tuple[int, str, str]:
        code = main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture
def corridor_copy(shared_data, tmp_path) -> Path:
    """<tmp>/data/corridor: the real Corridor as symlinks, so files can be replaced one by one."""
    root = tmp_path / "data" / "corridor"
    shutil.copytree(shared_data / "corridor", root, copy_function=os.symlink)
    return root
