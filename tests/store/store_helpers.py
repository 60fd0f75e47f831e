"""Small deterministic methods for the store tests (registered by the tests and their driver scripts).

`LOG` (environment): each describe call appends the names it described, one per line.
`KILL_AT_BATCH` (environment): the process SIGKILLs itself at that describe call.
"""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np

import vprbench
from vprbench.images import load_image
from vprbench.loader import loaded


def thumbnail(path, size: int = 8) -> np.ndarray:
    return np.asarray(load_image(path, "L").resize((size, size)), np.float32).ravel()


def _unit(rows: np.ndarray) -> np.ndarray:
    return rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)


class Thumb(vprbench.Method):
    """Grey thumbnails; names what it described in $LOG; can kill itself at batch $KILL_AT_BATCH."""

    batch_size = 10

    def __init__(self, size: int = 8, device: str = "cpu"):
        self.size, self.calls = int(size), 0

    def fingerprint(self) -> dict:
        return {"size": self.size}

    def load(self, path: Path):
        return path.name, thumbnail(path, self.size)

    def describe(self, images):
        self.calls += 1
        if self.calls == int(os.environ.get("KILL_AT_BATCH", 0)):
            os.kill(os.getpid(), signal.SIGKILL)
        items = [(Path(x).name, thumbnail(x, self.size)) if isinstance(x, (str, os.PathLike)) else x for x in images]
        if os.environ.get("LOG"):
            with open(os.environ["LOG"], "a") as log:
                log.writelines(f"{name}\n" for name, _ in items)
        return _unit(np.stack([row for _, row in items]))


class Fitted(Thumb):
    """Thumbnails minus the database mean (+ shift): a deterministic "vocabulary" to fit and save."""

    needs_fit = True

    def __init__(self, size: int = 8, shift: float = 0.0, device: str = "cpu"):
        super().__init__(size)
        self.shift, self.centre = float(shift), None
        self.fits = 0

    def fingerprint(self) -> dict:
        return {"size": self.size, "shift": self.shift}

    def fit(self, database):
        self.fits += 1
        self.centre = np.mean([thumbnail(p, self.size) for p in database], axis=0) + self.shift

    def fit_state(self):
        return {"centre": self.centre}

    def load_fit_state(self, state):
        self.centre = np.asarray(state["centre"], np.float32)

    def describe(self, images):
        if self.centre is None:
            raise vprbench.VPRBenchError("Fitted: describe before fit")
        return _unit(super().describe(images) * 255.0 - self.centre)


class Unsaved(Fitted):
    """Fits (randomly: every fit differs) but cannot save its fit: an empty fit_state()."""

    def fit(self, database):
        super().fit(database)
        self.centre = self.centre + np.random.default_rng().normal(0, 5, self.centre.shape).astype(np.float32)

    def fit_state(self):
        return {}


class Forgetful(Thumb):
    """Its fingerprint() forgets the `size` option: the store key must cover it anyway."""

    def fingerprint(self) -> dict:
        return {}


class Oracle(vprbench.Method):
    """Knows each image's place: `places` maps an image name (relative to the dataset root) to
    the database row nearest to where it was taken. Every place has a random unit code and an
    image is described by its place's code, so a query's top match is exactly its nearest
    database image: Recall@1 is 100 % whenever store rows, search indices and positives stay
    aligned (a shuffled store or a misaligned shard would break it). `folder`: the dataset's
    directory, whose path the names are relative to."""

    batch_size = 512

    def __init__(self, places: dict | None = None, dim: int = 32, device: str = "cpu", folder: str = "pitts30k"):
        self.places, self.folder = places or {}, folder
        codes = np.random.default_rng(0).normal(size=(max(self.places.values(), default=0) + 1, int(dim)))
        self.codes = _unit(codes).astype(np.float32)

    def load(self, path: Path):
        return self.places[Path(path).as_posix().split(f"/{self.folder}/", 1)[1]]

    def describe(self, items):
        return self.codes[np.asarray(loaded(self, items), dtype=np.int64)]


def register_all() -> None:
    for name, factory in (("thumb-test", Thumb), ("fitted-test", Fitted), ("unsaved-test", Unsaved),
                          ("forgetful-test", Forgetful), ("oracle-test", Oracle)):
        vprbench.register_method(name, factory)
