"""Helpers for dataset tests: trees of tiny images named as the real ones (hard links to one JPEG)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image


@pytest.fixture(scope="session")
def tiny_jpeg(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("tiny") / "tiny.jpg"
    Image.fromarray(np.full((8, 8, 3), 127, np.uint8)).save(path)
    return path


@pytest.fixture
def make_images(tiny_jpeg):
    """make_images(folder, names) -> paths: hard links (or copies across devices) to one tiny JPEG."""

    def make(folder: Path, names) -> list[Path]:
        folder.mkdir(parents=True, exist_ok=True)
        paths, made = [], {folder}
        for name in names:
            path = folder / name
            if path.parent not in made:
                path.parent.mkdir(parents=True, exist_ok=True)
                made.add(path.parent)
            try:
                os.link(tiny_jpeg, path)
            except OSError:
                path.write_bytes(tiny_jpeg.read_bytes())
            paths.append(path)
        return paths

    return make


@pytest.fixture(scope="session")
def save_rows():
    return write_rows


@pytest.fixture(scope="session")
def brute_force():
    return brute_force_positives


def write_rows(path: Path, lists) -> None:
    """Positive lists in the authors' row format: object array of [index, [positives]]."""
    rows = np.empty((len(lists), 2), dtype=object)
    for i, positives in enumerate(lists):
        rows[i, 0], rows[i, 1] = i, list(positives)
    np.save(path, rows, allow_pickle=True)


def brute_force_positives(queries: np.ndarray, database: np.ndarray, radius: float, chunk: int = 1024) -> list[set]:
    """Independent check: all database points within radius, by full distance computation."""
    found = []
    for start in range(0, len(queries), chunk):
        block = queries[start:start + chunk]
        squared = sum((block[:, None, k] - database[None, :, k]) ** 2 for k in range(database.shape[1]))
        rows, cols = np.nonzero(squared <= radius**2)
        found += [set(cols[rows == i].tolist()) for i in range(len(block))]
    return found
