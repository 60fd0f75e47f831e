"""The interface every post-retrieval stage implements (re-ranking, sequence matching), core
and third-party alike.

    retrieval -> Candidates (top-K per query) -> stage 1 -> stage 2 ... -> Recall@K, PR

A stage gets what came before it as `Candidates` and a `StageContext` (the dataset, the
retriever's descriptors of both splits, a per-image feature store, the memory budget and a
progress reporter) and returns new `Candidates`. The pipeline checks what it returns
(`check_candidates`) and refuses, naming the stage, rather than score a broken list.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..errors import VPRBenchError
from ..search.exact import order_results

TRACKS = ("single-image", "re-ranked", "sequence")


@dataclass(frozen=True)
class Candidates:
    """Per query, database indices and their scores, best first: `indices` int64 (Q, K),
    `scores` float32 (Q, K), higher is better (a stage working with distances negates them)."""

    indices: np.ndarray
    scores: np.ndarray

    @property
    def k(self) -> int:
        return int(self.indices.shape[1])

    @property
    def query_count(self) -> int:
        return int(self.indices.shape[0])

    def top(self, k: int) -> "Candidates":
        return Candidates(self.indices[:, :k], self.scores[:, :k])


class StageOptions(BaseModel):
    """A stage's options: subclass it with typed fields and defaults. Unknown options and
    values of the wrong type are refused when the spec is made."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # inf cannot be hashed into the spec (JSON)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_a_number(cls, value, info):
        """pydantic reads true as 1 and false as 0: max_features=false would silently mean every keypoint."""
        annotation = cls.model_fields[info.field_name].annotation
        kinds = (annotation, *get_args(annotation))
        if isinstance(value, bool) and bool not in kinds and (int in kinds or float in kinds):
            raise ValueError(f"takes a number, not {str(value).lower()}")
        return value


class RerankOptions(StageOptions):
    """What every re-ranker takes: how many candidates it re-orders (`--rerank-k`)."""

    k: int = Field(100, ge=1)


@dataclass
class StageContext:
    """What a stage may use besides the candidates.

    - `dataset`: the `vprbench.datasets.Dataset` (its `database`/`queries` image paths in ground-truth
      order, `root`, `ground_truth` with positions and unit, `protocol`).
    - `database`, `queries`: the retriever's descriptors as its search saw them (post-processed,
      e.g. PCA-whitened) as row sources (`vprbench.row_sources`: `row_count`, `dim`,
      `read_rows(start, stop)`, `read_rows_at(sorted indices)`); float32 rows, never re-extracted.
    - `features(name, identity, form=None)`: a `FeatureStore` for per-image data (local features), kept
      in the cache beside descriptor stores, resumable and lock-safe (vprbench/stages/features.py);
      `form` (array name -> dtype and trailing shape) has stored images that do not fit it recomputed.
    - `memory_budget` (bytes), `progress` (rich-like: add_task/advance), `cache_dir`, `lock_timeout`,
      `device` (the run's torch device, for a stage that runs a network).
    - `spec`: the run's spec; `prefix`: the identity of everything before this stage (the
      retriever and earlier stages), e.g. to key what a stage caches on what produced its input.
    """

    dataset: Any
    database: Any
    queries: Any
    spec: Any = None
    prefix: dict = field(default_factory=dict)
    cache_dir: Path | None = None
    memory_budget: int = 1_000_000_000
    lock_timeout: float | None = None
    progress: Any = None
    #: how the method compares its descriptors (`Method.compare`): "cosine" or a distance such as
    #: "mean-absolute-difference" (sad), for stages that compute scores of their own
    compare: str = "cosine"
    device: str = "cpu"
    #: the feature stores handed out in this run (features_computed sums theirs)
    stores: list = field(default_factory=list, repr=False)

    def features(self, name: str, identity: dict, form: dict | None = None):
        """The store of per-image data `name` (e.g. "sift") computed as `identity` says (its options,
        the library version): one per dataset image set, resumable, lock-safe. `form`: what each image's
        arrays are (`FeatureStore`'s), so a stored image that is not is recomputed, never handed to the stage."""
        from .features import KEPT_BYTES, FeatureStore

        store = FeatureStore.for_images(name, identity, self.dataset, self.cache_dir, self.lock_timeout,
                                        min(KEPT_BYTES, self.memory_budget // 4), form)  # two splits open at once
        self.stores.append(store)
        return store

    @property
    def features_computed(self) -> int:
        """Images whose per-image data were computed (not read from a store) so far in this run."""
        return sum(store.computed for store in self.stores)


class Stage:
    """A post-retrieval stage. Subclass it, set `track` and `Options`, implement `apply`.

    - `name`: set by the registry to the name the stage was created under.
    - `options`: the validated `Options` instance (`self.options.k` ...).
    - `apply(candidates, context)` returns new `Candidates` for every query, in query order, with
      at least as many columns as the largest K reported; indices are database rows.
    - `candidates_needed()`: how many candidates retrieval must hand it (None: the run's largest K).
    - `check(dataset)`: refuse a dataset the stage cannot run on (VPRBenchError), before any work.
    - `check_compare(compare)`: refuse a method whose descriptors are compared by `compare` (its
      `Method.compare`) when the stage cannot use them, before any work.
    - `least_budget(database, queries, k)`: the least memory budget `apply` takes on rows of these
      shapes with `k` candidates per query (None: it refuses none); the run refuses once, before
      any search, a budget below the largest of its parts' (evaluation/budget.py).
    - `query_window(options)`: the consecutive queries one query's result reads (sequence stages: their window).
    - `stored_bytes(context)`: bytes it keeps per database image (for the record's cost), 0 if none.
    - `file_identities(options)`: the options that name files, by content (part of the run's identity).
    - `provenance()`: where what it learnt came from (its weights), for the record and the board.
    - `fingerprint()`: what its results depend on beyond its options, as `Method.fingerprint` (a
      "version" its author raises when the code changes them): a sweep serves a stored record only
      while it is the one the record was made with.
    """

    name: str = ""
    track: ClassVar[Literal["re-ranked", "sequence"]] = "re-ranked"
    Options: ClassVar[type[StageOptions]] = StageOptions
    description: ClassVar[str] = ""

    def __init__(self, options: StageOptions | None = None):
        self.options = options if options is not None else self.Options()

    def candidates_needed(self) -> int | None:
        return getattr(self.options, "k", None)

    def check(self, dataset) -> None:
        """Refuse `dataset` before any work (e.g. a sequence stage on unordered images)."""

    def check_compare(self, compare: str) -> None:
        """Refuse a method compared by `compare` ("cosine", or a distance such as sad's
        "mean-absolute-difference") before any work, when the stage's arithmetic needs another."""

    def least_budget(self, database, queries, k: int) -> int | None:
        """Bytes `apply` needs at least, from the row sources' shapes and read costs only (no row read)."""
        return None

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        raise NotImplementedError

    def stored_bytes(self, context: StageContext) -> int:
        return 0

    @classmethod
    def query_window(cls, options: dict) -> int:
        """How many consecutive queries (traverse order) one query's result reads the descriptors
        of, for these options (a record's): 1, its own. The bootstrap's blocks cover it
        (evaluation/blocks.py); ValueError for options the stage refuses."""
        return 1

    @classmethod
    def file_identities(cls, options: StageOptions) -> dict:
        """Option -> the content of the file it names ("sha256:<hex>"), in the run's identity instead of
        the path: a file moved is the same run, a file edited another. Called when the spec is made, so a
        stage may refuse here a file it cannot use. Default: every option whose value is an existing file,
        or a folder written as a path (weights: a folder holding the release's file) by its files."""
        from ..content_identity import value_identity

        found = {}
        for name, value in options.model_dump(mode="json").items():
            try:
                identity = value_identity(name, value)
            except OSError as error:
                raise VPRBenchError(f"Stage option {name}: cannot read {value} ({error.strerror or error}).") from None
            if identity is not None:
                found[name] = identity
        return found

    def provenance(self) -> dict:
        """Where what the stage learnt came from, as `Method.provenance` says it: {"weights": {"source":
        "official"|"user"|"random", ...}}. The board keeps a run whose stage ran on random weights out of
        every cell and marks one on the user's weights, as for methods. {} when nothing is learnt."""
        return {}

    def fingerprint(self) -> dict:
        """What changes the stage's results beyond its options (JSON values), in its record: raise a
        {"version": 2} when its code changes them, or a sweep keeps serving the old records. Default {}
        (records written before stages had one count as made with it)."""
        return {}


def repeated_row(indices: np.ndarray) -> int | None:
    """The first row (query) of `indices` (Q, K) holding one database index twice, None when none does."""
    ordered = np.sort(indices, axis=1)
    repeats = (ordered[:, 1:] == ordered[:, :-1]).any(1)
    return int(np.flatnonzero(repeats)[0]) if repeats.any() else None


def unordered_row(scores: np.ndarray) -> int | None:
    """The first row of `scores` (Q, K) whose scores increase somewhere along it, None when none does."""
    rising = (np.diff(np.asarray(scores), axis=1) > 0).any(1)
    return int(np.flatnonzero(rising)[0]) if rising.any() else None


def check_candidates(found, stage: str, queries: int, database: int, k: int) -> Candidates:
    """What stage `stage` returned, checked: Candidates of `queries` rows, >= `k` columns, indices in
    [0, database) and each once per row, finite scores. Anything else is refused naming the stage."""
    where = f"Stage {stage!r} returned"
    if not isinstance(found, Candidates):
        raise VPRBenchError(f"{where} {type(found).__name__}, not Candidates; fix the stage.")
    indices, scores = np.asarray(found.indices), np.asarray(found.scores)
    if indices.ndim != 2 or indices.shape != scores.shape:
        raise VPRBenchError(f"{where} indices {indices.shape} and scores {scores.shape}; both must be "
                            "(queries, K) alike; fix the stage.")
    if indices.shape[0] != queries:
        raise VPRBenchError(f"{where} candidates for {indices.shape[0]} queries, but there are {queries}: "
                            "every query must be present, in order; fix the stage.")
    if indices.shape[1] < k:
        raise VPRBenchError(f"{where} {indices.shape[1]} candidates per query, fewer than the largest K "
                            f"reported ({k}); fix the stage or lower --k.")
    if not np.issubdtype(indices.dtype, np.integer):
        raise VPRBenchError(f"{where} indices of type {indices.dtype}, not integers; fix the stage.")
    if indices.size and (indices.min() < 0 or indices.max() >= database):
        bad = int(np.flatnonzero((indices < 0).any(1) | (indices >= database).any(1))[0])
        raise VPRBenchError(f"{where} database indices out of range for query {bad} (the database has "
                            f"{database} images, 0..{database - 1}); fix the stage.")
    bad = repeated_row(indices)
    if bad is not None:
        raise VPRBenchError(f"{where} one database image twice among the candidates of query {bad}; fix the stage.")
    if not np.issubdtype(scores.dtype, np.number) or not np.isfinite(scores).all():
        raise VPRBenchError(f"{where} scores that are not finite numbers; fix the stage.")
    rising = unordered_row(scores)
    if rising is not None:  # Recall@K reads the order, the PR metrics the first score: they must agree
        raise VPRBenchError(f"{where} the candidates of query {rising} not best first (scores must not increase "
                            "along a row); fix the stage.")
    return Candidates(indices.astype(np.int64, copy=False), scores.astype(np.float32, copy=False))


def check_reordered(found: Candidates, given: Candidates, stage: str, database: int) -> None:
    """A re-ranker re-orders the candidates it was given: one naming a database image it was not given (found
    by its own search) is refused, or recall after it could pass the ceiling the record states."""
    rows = np.arange(found.query_count, dtype=np.int64)[:, None] * database  # each row's indices apart from the others'
    foreign = ~np.isin(found.indices + rows, given.indices + rows)
    if foreign.any():
        q = int(np.flatnonzero(foreign.any(1))[0])
        image = int(found.indices[q][foreign[q]][0])
        raise VPRBenchError(f"Stage {stage!r} returned database image {image} for query {q}, which is not among the "
                            f"{given.k} candidates it was given: a re-ranker re-orders its candidates; fix the stage.")


def reordered(indices: np.ndarray, scores: np.ndarray, grid: float | None = None) -> Candidates:
    """Candidates sorted by score descending, ties by database index ascending (the search's tie
    rule). `grid`: scores rounded to multiples of it first, so a last-bit difference between CPUs
    cannot swap two candidates."""
    scores = np.asarray(scores, dtype=np.float64)
    if grid:
        scores = np.rint(scores / grid) * grid
    scores, indices = order_results(scores, np.asarray(indices, dtype=np.int64))
    return Candidates(indices, scores.astype(np.float32))


def by_count(candidates: Candidates, counts: np.ndarray) -> Candidates:
    """The candidates re-ordered by `counts` (Q, K) descending (inliers, mutual matches); equal counts
    keep their retrieval order. The counts become the scores."""
    order = np.argsort(-np.asarray(counts), axis=1, kind="stable")
    return Candidates(np.take_along_axis(candidates.indices, order, 1),
                      np.take_along_axis(np.asarray(counts), order, 1).astype(np.float32))


def progress_task(context: StageContext, description: str, total: int):
    """`advance(n=1)` of a progress task on `context.progress` (a no-op without one)."""
    progress = context.progress
    if progress is None:
        return lambda n=1: None
    task = progress.add_task(description, total=total)
    return lambda n=1: progress.advance(task, n)


def rerank_by_counts(name: str, candidates: Candidates, context: StageContext, store, extract, count,
                     prepare=lambda query: query) -> Candidates:
    """What every count-based re-ranker does: each image's data from the feature store `store`
    (`extract(path)` computes it once when missing), `count(prepare(query data), candidate data)`
    for every query and candidate (matches, inliers), then the candidates re-ordered by those
    counts (`by_count`). `prepare` runs once per query (e.g. descriptors made matchable)."""
    dataset = context.dataset
    counts = np.zeros(candidates.indices.shape, dtype=np.int64)
    advance = progress_task(context, f"{name} re-ranking", candidates.query_count)
    with store.opened("database", lambda row: extract(dataset.database[row])) as db, \
            store.opened("queries", lambda row: extract(dataset.queries[row])) as qs:
        for q in range(candidates.query_count):
            query = prepare(qs(q))
            for c, row in enumerate(candidates.indices[q]):
                counts[q, c] = count(query, db(int(row)))
            advance()
    return by_count(candidates, counts)
