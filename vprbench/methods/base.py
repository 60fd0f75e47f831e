"""The interface every method implements, core and third-party alike."""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from ..errors import VPRBenchError


class PostProcessor(Protocol):
    """A transform of stored descriptors learnt from the database (never the queries), e.g.
    PCA-whitening. The evaluation fits it on the database's row source (`vprbench.row_sources`)
    within a memory budget, saves `state()` in the store's folder under a name made from
    `key(...)`, and applies `transform` chunk by chunk, so no split is ever whole in memory.
    An optional `check_rows(n, dataset_name)` refuses a database of `n` images it cannot fit,
    before any descriptor is computed; an optional `check_budget(rows, memory_budget)` (rows: their
    shape only) refuses a fit the budget cannot hold, before a stack's other databases are described.
    Optional, read from the fit rows' shape before the fit so the run's budget is checked once for
    the fit, the search and the stages: `output_dim(rows)` (the dimension `transform` returns; without
    it the run is planned after the fit), `state_bytes(rows)` (what `state()` will hold) and
    `least_budget(rows, memory_budget)` (the least budget `fit` takes under that budget).
    """

    def key(self, rows, memory_budget: int) -> dict:
        """What defines the fitted state (options, and the algorithm the budget selects), from the rows'
        `row_count`, `dim` and `dtype` only: a sweep computes it from a stored record's shape to judge
        whether the record fitted what this run would, and runs the cell again when it cannot."""

    def fit(self, rows, memory_budget: int) -> object:
        """Learn from the database rows, holding at most `memory_budget` bytes."""

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """(n, D) float32 -> (n, D') float32; each output row depends on its input row only
        (blocks may arrive padded with zero rows, whose outputs are dropped)."""

    def state(self) -> dict[str, np.ndarray]: ...

    def load_state(self, state: dict[str, np.ndarray]) -> None: ...


class Method(ABC):
    """Turns images into L2-normalised float32 global descriptors.

    Subclass it, then `vprbench.register_method("my-method", MyMethod)`. Contract:
    - `describe` returns one row per image, in input order, and a row never depends on
      which other images share its batch.
    - `fingerprint` names everything that changes descriptors (weights identity,
      preprocessing, options), read off what `describe` uses; the descriptor store is keyed
      by it, and a method whose fingerprint changed after `create_method` is refused.
    - A method that learns something (a vocabulary) sets `needs_fit = True`, fits in
      `fit` on database images only, and round-trips it through `fit_state`/`load_fit_state`
      so an interrupted extraction resumes with the same vocabulary.
    """

    #: set by the registry to the name the method was created under
    name: str = ""
    #: set by the registry: the options the user gave on top of the preset
    options: dict = {}
    needs_fit: bool = False
    #: images handed to one `describe` call by the pipeline
    batch_size: int = 16
    #: how descriptors are compared: "cosine" (inner product of L2-normalised rows, the contract
    #: above) or "mean-absolute-difference" (a distance over rows as they are, e.g. `sad`; searched
    #: exactly, without post-processing)
    compare: str = "cosine"

    def __repr__(self) -> str:
        """`HOG('hog', options={'resize': [64, 64]})`: what `create_method` made it as, not an address."""
        try:
            name, options = getattr(self, "name", ""), getattr(self, "options", {})
        except Exception:  # a plugin's property that raises: the plain repr, never a failing one
            return object.__repr__(self)
        return f"{type(self).__name__}({f'{name!r}, ' if name else ''}options={options!r})"

    @classmethod
    def cached_identities(cls, options: dict, dataset: str, cache_dir=None) -> dict[str, str]:
        """Option -> the content of what it names in the cache by name (a vocabulary fitted earlier
        under a name), as found when the run's spec is made, without downloading or loading a model:
        part of the run's key (not its leaderboard row), so a refit is another run. Default: none."""
        return {}

    #: the option naming the dataset the method is for (AnyLoc's `dataset`), if it has one: in an
    #: evaluation an unset one is the dataset evaluated (`use_dataset`), so written equal, it is one run
    dataset_option: str | None = None

    @classmethod
    def implied_options(cls, options: dict) -> dict:
        """Option -> the value an option left unset (None) takes given the others (AnyLoc: the preset's
        block on this backbone): written out, that value is the same run. Default: none."""
        return {}

    def use_dataset(self, name: str) -> None:  # pragma: no cover - default no-op
        """Called first by an evaluation with the dataset's name: per-dataset settings
        (e.g. AnyLoc's resize policy and domain vocabulary) must be in place before
        `fingerprint` and `fit`."""

    def fingerprint(self) -> dict:
        return {}

    def prepare(self) -> None:  # pragma: no cover - default no-op
        """Load what `fit` and `describe` need (a model's weights), once there is something to compute
        and before its store folders are made: a file refused here leaves nothing in the cache."""

    def fit(self, database: Sequence[Path]) -> None:  # pragma: no cover - default no-op
        """Learn from the database images (never the queries)."""

    def fit_state(self) -> dict[str, np.ndarray]:
        return {}

    def load_fit_state(self, state: dict[str, np.ndarray]) -> None:  # pragma: no cover
        """Restore what `fit` learnt, as returned by `fit_state`. The state is read from the cache, where
        a file may have been edited or crafted (its fit id is a hash anyone can write again): raise a
        VPRBenchError, ValueError or KeyError for one that is not what `fit` gives; it is discarded and fitted again."""

    def load(self, path: Path):
        """Read and preprocess one image for `describe`; runs in data-loader worker processes.
        The default hands `describe` the path itself."""
        return path

    @abstractmethod
    def describe(self, images: Sequence) -> np.ndarray:
        """(len(images), dim) float32, rows L2-normalised; `images` are what `load` returned."""

    def provenance(self) -> dict:
        """Where what shapes the descriptors came from, for the result record:
        {"weights": {"source": "official"|"user"|"random"|"none", ...},
         "vocabulary": {"source": ..., "fitted_on": ..., "fitted_on_evaluated_database": bool, ...},
         "pca": {...}}.
        Every part that is fitted (a vocabulary, PCA, whitening, ...) names the data it was fitted
        on (`fitted_on`: a dataset and protocol, a folder's content, a file's sha256) and whether
        that is the evaluated database (`fitted_on_evaluated_database`, the field's "transductive";
        null when unknown). "none" weights with a fitted part is not "nothing learnt": the record
        lists the fitted parts in `provenance.learnt`. Keys that do not apply are left out."""
        return {}

    def postprocessor(self) -> PostProcessor | None:
        """What transforms stored descriptors before search (fitted on the database, applied
        chunk by chunk with bounded memory), or None."""
        return None

    def postprocess_datasets(self) -> list[str] | None:
        """The benchmarks whose databases `postprocessor()` is fitted on, stacked in this order (the
        evaluated one among them), once `use_dataset` has named it; None: the evaluated database alone.
        Each is described as its own evaluation would, so their stores serve those runs too."""
        return None

    def postprocess(self, database: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whole matrices in memory: the `postprocessor()` fitted on `database` and applied to both.
        A plugin may still override this older hook; the evaluation then holds both splits in
        memory, so prefer `postprocessor()`."""
        post = self.postprocessor()
        if post is None:
            return database, queries
        from ..row_sources import DEFAULT_MEMORY_BUDGET, ArrayRows

        post.fit(ArrayRows(database), DEFAULT_MEMORY_BUDGET)
        return post.transform(database), post.transform(queries)


def l2_normalise(x: np.ndarray, axis: int = -1) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.maximum(norm, 1e-12)


def fitted_centres(state: dict[str, np.ndarray], clusters: int, dim: int, who: str) -> np.ndarray:
    """The (clusters, dim) finite float32 centres of a saved fit state (`Method.load_fit_state`); a
    VPRBenchError saying what it holds instead (the file is then discarded and fitted again)."""
    if "centres" not in state:
        raise VPRBenchError(f"{who}: the fit state holds no centres (it holds {', '.join(map(repr, sorted(state)))[:80]})")
    found = np.asarray(state["centres"])
    if found.dtype.kind != "f" or found.shape != (clusters, dim) or not np.isfinite(found).all():
        raise VPRBenchError(f"{who}: the fit state holds centres of {found.dtype} {found.shape}"
                            + (" with NaN or infinite values" if found.dtype.kind == "f" and found.shape == (clusters, dim)
                               else "") + f", not {clusters} x {dim} finite numbers")
    return found.astype(np.float32)
