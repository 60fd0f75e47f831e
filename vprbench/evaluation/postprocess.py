"""Post-processing (e.g. PCA-whitening) between the descriptor stores and the search: a
post-processor fitted on the database rows (its state saved beside the stores, keyed by what
defines it) and applied tile by tile on a fixed grid, so a row's values depend neither on how a
caller chunks its reads nor on its neighbours."""
from __future__ import annotations

import hashlib
import json
import time
import warnings
from pathlib import Path

import numpy as np

from ..aggregation.pca import PROJECTION_BLOCK_BYTES
from ..errors import VPRBenchError
from ..fsutil import atomic_path, write_in_turn
from ..hashing import exact_data
from ..loader import checked, plugin_part, postprocessor_of
from ..row_sources import ArrayRows, RowSource, read_bytes_per_row
from ..search.row_checks import zero_rows
from .budget import said_number

#: a post-processor transforms tiles of at most this many input bytes (see transform_rows)
TRANSFORM_BYTES = 128 * 2**20


def padded(block: np.ndarray, rows: int) -> np.ndarray:
    """`block` with zero rows appended up to `rows` (itself when it has them)."""
    if len(block) == rows:
        return block
    out = np.zeros((rows, block.shape[1]), dtype=np.float32)
    out[:len(block)] = block
    return out


def transform_rows(dim: int) -> int:
    """Rows per tile a post-processor transforms at once (TRANSFORM_BYTES at 16 bytes per
    input value: float32 and float64 copies); depends on the dimension only."""
    rows = max(1, TRANSFORM_BYTES // (16 * int(dim)))
    return int(min(1024, max(16, 1 << (rows.bit_length() - 1))))


def kept_undescribed(undescribed: np.ndarray, after: np.ndarray) -> np.ndarray:
    """`after` (post-processed rows) with the rows `undescribed` flags (all zero before: images the
    method had nothing to describe) set to zero again: post-processing cannot describe them, and
    would turn them all into one vector (PCA's centring) that matches some image."""
    if undescribed.any():
        after = np.array(after, dtype=np.float32)
        after[undescribed] = 0
    return after


class TransformedRows:
    """A row source seen through a fitted post-processor, transformed tile by tile on the grid
    of `transform_rows(source.dim)` (aligned to row 0, short tiles padded with zero rows), so a
    row's values depend neither on how a caller chunks its reads nor on its neighbours."""

    def __init__(self, source: RowSource, postprocessor, counts_state: bool = False):
        self.source, self.postprocessor = source, postprocessor
        self.row_count, self.folder, self.dtype = int(source.row_count), source.folder, np.dtype(np.float32)
        self.tile = transform_rows(source.dim)
        self.dim = int(self._transform(source.read_rows(0, 1)).shape[1])
        # the fitted state (PCA's projection: 100 MB at AnyLoc's 49,152 -> 512), held while rows are read;
        # counted by one of the sources sharing it (`counts_state`)
        self.state_bytes = _state_bytes(postprocessor) if counts_state else 0

    def _transform(self, block: np.ndarray) -> np.ndarray:
        """At most one tile of rows, transformed as one full tile."""
        size, block = min(self.tile, self.row_count), np.asarray(block, dtype=np.float32)
        with in_postprocessor(self.postprocessor, "transform"):
            out = self.postprocessor.transform(padded(block, size))
        if np.ndim(out) != 2 or np.shape(out)[0] != size:
            raise VPRBenchError(f"Post-processor {type(self.postprocessor).__name__} returned shape {np.shape(out)} "
                                f"for {size} rows; expected one row per row.")
        # the rows kept must be finite numbers, as a method's own (the padding rows are dropped unseen)
        return kept_undescribed(zero_rows(block, "descriptors"), checked(f"Post-processor {type(self.postprocessor).__name__}",
                                               out[:len(block)], len(block)))

    def read_cost(self) -> tuple[int, int]:
        return transformed_cost(self.source, self.dim, self.state_bytes)

    def read_rows(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.dim), dtype=np.float32)
        self.read_rows_into(start, stop, out)
        return out

    def read_rows_into(self, start: int, stop: int, out: np.ndarray) -> None:
        for a in range(start - start % self.tile, stop, self.tile):
            b = min(a + self.tile, self.row_count)
            part = self._transform(self.source.read_rows(a, b))
            lo, hi = max(start, a), min(stop, b)
            out[lo - start:hi - start] = part[lo - a:hi - a]

    def read_rows_at(self, indices) -> np.ndarray:
        # a tile of source rows at a time, as read_cost says: all of them at once were the source's
        # dimension times the rows asked (a training sample of 16,384 PCA'd rows: 3.2 GB)
        indices = np.asarray(indices, dtype=np.int64)
        out = np.empty((len(indices), self.dim), dtype=np.float32)
        for a in range(0, len(indices), self.tile):
            out[a:a + self.tile] = self._transform(self.source.read_rows_at(indices[a:a + self.tile]))
        return out


def transformed_cost(source: RowSource, dim: int, state_bytes: int) -> tuple[int, int]:
    """(bytes per row, fixed bytes) of reading `source` through a post-processor to `dim` dims that holds
    `state_bytes` of state: a tile read, padded, and computed in float64 (PCA-whitening does), with its
    output, and a float64 block of PCA's projection. From shapes only: the run's plan reads it before the fit."""
    block = min(PROJECTION_BLOCK_BYTES, 8 * source.dim * dim)
    tile = transform_rows(source.dim) * (read_bytes_per_row(source) + 12 * source.dim + 20 * dim)
    return dim * 4, tile + block + state_bytes


class PlannedRows:
    """The rows a post-processor will make of `source`, by shape and read cost only (no row): what the
    run's budget plan reads before the post-processor is fitted."""

    def __init__(self, source: RowSource, dim: int, state_bytes: int = 0):
        self.source, self.dim, self.state_bytes = source, int(dim), int(state_bytes)
        self.row_count, self.folder, self.dtype = int(source.row_count), source.folder, np.dtype(np.float32)

    def read_cost(self) -> tuple[int, int]:
        return transformed_cost(self.source, self.dim, self.state_bytes)

    def read_rows(self, start, stop):
        raise VPRBenchError("Rows planned before the post-processor is fitted have a shape, not values.")


def _number_said(postprocessor, hook: str, rows, *args, least: int = 0) -> int | None:
    """`postprocessor.<hook>(rows, *args)` when it has that hook (None when not): a whole number >= `least`."""
    if not callable(getattr(postprocessor, hook, None)):
        return None
    with in_postprocessor(postprocessor, hook):
        found = getattr(postprocessor, hook)(rows, *args)
    return said_number(found, f"Post-processor {type(postprocessor).__name__}: {hook}()", "post-processor", least)


def planned(postprocessor, database: RowSource, queries: RowSource, fit_rows, memory_budget: int):
    """(database, queries, parts) before `postprocessor` is fitted on `fit_rows` (a row source or its shape):
    the rows it will make of both (PlannedRows), and its fit's least budget as (part, bytes) when it says it
    (`least_budget`). None when it cannot say its output dim before the fit (`output_dim`): the plan is
    then made after the fit."""
    dim = _number_said(postprocessor, "output_dim", fit_rows, least=1)
    if dim is None:
        return None
    state = _number_said(postprocessor, "state_bytes", fit_rows) or 0  # none said: counted once it is fitted
    need = _number_said(postprocessor, "least_budget", fit_rows, memory_budget)
    parts = [] if need is None else [(f"the {type(postprocessor).__name__} fit", need)]
    return PlannedRows(database, dim, state), PlannedRows(queries, dim), parts


def _state_bytes(postprocessor) -> int:
    """Bytes of a fitted post-processor's state arrays (0 when it keeps none)."""
    if not callable(getattr(postprocessor, "state", None)):
        return 0
    with in_postprocessor(postprocessor, "state"):
        return sum(int(np.asarray(array).nbytes) for array in postprocessor.state().values())


def in_postprocessor(postprocessor, part: str):
    """Runs a call into `postprocessor`'s code: a plugin's failure is one line naming it (`plugin_part`)."""
    return plugin_part(postprocessor, part, f"Post-processor {type(postprocessor).__name__}")


def postprocessor_key(postprocessor, rows, memory_budget: int):
    """`postprocessor.key(rows, memory_budget)` as exact plain data (`exact_data`): as text, two arrays
    would print alike and share one fitted state."""
    with in_postprocessor(postprocessor, "key"):
        found = postprocessor.key(rows, memory_budget)
    return exact_data(found, f"Post-processor {type(postprocessor).__name__}: key()")


def fit_postprocessor(postprocessor, database: RowSource, memory_budget: int, state_folder=None,
                      before_fit=None) -> dict:
    """Fit on the database rows, or load the state a previous run saved in `state_folder`
    (default: the database's folder) under a name keyed by what defines it: the post-processor,
    and the rows' shape and content (a store's `content_key`). A saved state is used only if the
    key saved in it is that key (a file copied from another store under this name is refitted).
    `before_fit()`, if given, runs when the state is to be fitted, before the fit (the run's plan)."""
    content = getattr(database, "content_key", None)
    key = {"postprocessor": postprocessor_key(postprocessor, database, memory_budget),
           "rows": {"count": int(database.row_count), "dim": int(database.dim), "dtype": str(np.dtype(database.dtype)),
                    "content": content() if content else None}}
    text = json.dumps(key, sort_keys=True)
    folder = Path(state_folder) if state_folder is not None else database.folder
    path = Path(folder) / f"postprocess-{hashlib.sha256(text.encode()).hexdigest()[:16]}.npz" if folder else None
    info = {"key": key, "file": str(path) if path else None}
    if path is not None and path.is_file():
        unusable = _load_state(postprocessor, path, text, int(database.dim), int(database.row_count))
        if unusable is None:
            return {**info, "state": "loaded"}
        warnings.warn(f"Refitting: {unusable}", stacklevel=2)  # the fit below replaces the file
    if before_fit is not None:
        before_fit()
    started = time.perf_counter()
    with in_postprocessor(postprocessor, "fit"):
        postprocessor.fit(database, memory_budget)
    info.update(state="fitted", fit_s=round(time.perf_counter() - started, 3))
    if path is not None:
        with in_postprocessor(postprocessor, "state"):
            state = postprocessor.state()

        def save(into: Path) -> None:
            with atomic_path(into) as temporary, open(temporary, "wb") as file:
                np.savez(file, **state, key=np.array(text))

        write_in_turn(path, save, f"the state {path}")
    return info


def _load_state(postprocessor, path: Path, text: str, dim: int, rows: int) -> str | None:
    """None when `postprocessor` loaded the state saved at `path` under the key `text` and applies
    it to `rows` x `dim` rows, else a line saying why that state is unusable (refitted); what else its
    load_state raises is its one line (`in_postprocessor`)."""
    from ..datasets.layouts.npy import NPZ_MAX_BYTES, read_npz

    unusable = f"the post-processing state {path} is unusable"
    try:
        # the one guarded reader: a header claiming terabytes, objects or a torn zip are a line, not a traceback.
        # A state of these rows may be as big as a (D x D) matrix or the rows themselves, and a mean, in
        # float64 (PCA of 196,608-dim VLAD to 4,096: 3 GB), whatever the budget it is loaded under
        saved = read_npz(path, "post-processing state", "the arrays vprbench saves (it is fitted again and replaced)",
                         max_bytes=max(NPZ_MAX_BYTES, 8 * dim * (max(rows, dim) + 1)))
    except OSError as error:
        return f"{unusable} ({error})."
    except VPRBenchError as error:
        return str(error)
    key = saved.pop("key", None)
    if key is None or key.shape != () or key.dtype.kind != "U":
        return f"{unusable} (it holds no key text: it was not saved by vprbench)."
    if str(key) != text:
        return f"{unusable} (it was fitted on other rows or settings than these)."
    with in_postprocessor(postprocessor, "load_state"):
        try:
            postprocessor.load_state(saved)
        # a state it refuses (PCA's own checks are VPRBenchErrors), as a damaged file
        except (VPRBenchError, OSError, ValueError, KeyError) as error:
            return f"{unusable} ({error})."
    try:
        # a state of another input width (its key rewritten) is named here, not at the first transform;
        # a zero row is what any transform takes (tiles are padded with them)
        with in_postprocessor(postprocessor, "transform"):
            postprocessor.transform(np.zeros((1, dim), dtype=np.float32))
    except VPRBenchError as error:
        return f"{unusable} for these {dim}-dimensional descriptors ({str(error).rstrip('.')})."
    return None


class RowShape:
    """A row source's shape without its rows: all a post-processor's key is computed from."""

    folder = None

    def __init__(self, rows: dict):
        self.row_count, self.dim, self.dtype = int(rows["count"]), int(rows["dim"]), np.dtype(rows["dtype"])

    def read_rows(self, start, stop):
        raise VPRBenchError("A post-processor's key is computed from the rows' shape, not from their values.")


def fits_as_recorded(postprocessor, record: dict, memory_budget: int) -> bool:
    """Whether the post-processing `record` fitted (its search's postprocess key) is the one
    `postprocessor` would fit now under `memory_budget`, from the record's row count, dim and dtype
    (no descriptor read): the budget picks PCA's solver, exact or randomized, which no spec names.
    True when the record fitted nothing keyed (no post-processor, a plugin's whole-matrix hook)."""
    found = ((record.get("search") or {}).get("postprocess") or {}).get("key")
    if postprocessor is None or not isinstance(found, dict):
        return True
    try:
        return postprocessor_key(postprocessor, RowShape(found["rows"]), memory_budget) == found.get("postprocessor")
    except Exception:  # noqa: BLE001 - a key that needs the rows cannot be told from the record: run again
        return False


def overrides_postprocess(method) -> bool:
    from ..methods.base import Method

    return getattr(type(method), "postprocess", Method.postprocess) is not Method.postprocess


def fits_on_database(method) -> bool:
    """Whether `method` learns anything from database images: a vocabulary, a post-processor, or a plugin's
    whole-matrix `postprocess` (which is handed the database)."""
    return bool(method.needs_fit) or overrides_postprocess(method) or postprocessor_of(method) is not None


def check_database_size(method, rows: int, where: str) -> None:
    """Before any descriptor is computed: a post-processor that cannot be fitted on `rows` database rows (PCA
    wider than them) is refused, naming `where` they come from."""
    post = postprocessor_of(method)
    if post is not None and hasattr(post, "check_rows"):
        with in_postprocessor(post, "check_rows"):
            post.check_rows(rows, where)


def check_fit_budget(method, rows: int, described: RowSource, memory_budget: int) -> None:
    """Before more databases are described for it: a post-processor whose fit on `rows` rows like
    `described` (its width and dtype) does not fit the budget is refused (its `check_budget`)."""
    post = postprocessor_of(method)
    if post is not None and hasattr(post, "check_budget"):
        with in_postprocessor(post, "check_budget"):
            post.check_budget(RowShape({"count": rows, "dim": described.dim, "dtype": described.dtype}), memory_budget)


def check_joint_budget(method, rows: int, stores: dict, memory_budget: int, plan) -> None:
    """Before a stack's other databases are described: `plan(database, queries, parts)` of the fit on
    `rows` rows like the evaluated database (`stores`), when its post-processor says its output's shape
    (`planned`), else that fit's own `check_budget`."""
    post = postprocessor_of(method)
    database, queries = stores["database"], stores["queries"]
    shape = RowShape({"count": rows, "dim": database.dim, "dtype": database.dtype})
    found = None if post is None else planned(post, database, queries, shape, memory_budget)
    if found is not None:
        plan(*found)
    else:
        check_fit_budget(method, rows, database, memory_budget)


def postprocessed(method, database: RowSource, queries: RowSource, memory_budget: int, state_folder=None,
                  fit_on: RowSource | None = None, plan=None):
    """(database, queries, info): both row sources as `method` post-processes them (its
    post-processor fitted on the database, or on `fit_on` (several databases stacked, joint.py), or
    a plugin's whole-matrix `postprocess`); info None when there is nothing to do. `retrieve` and
    `vprbench describe` share it. `plan(database, queries, parts)`, if given, sees the rows as the
    post-processor will make them and its fit's need (`planned`) before it is fitted."""
    postprocessor = postprocessor_of(method) if method is not None else None
    if method is not None and overrides_postprocess(method):  # a plugin's whole-matrix hook
        db, q = database.read_rows(0, database.row_count), queries.read_rows(0, queries.row_count)
        undescribed = zero_rows(db, "database descriptors"), zero_rows(q, "query descriptors")
        with plugin_part(method, "postprocess"):
            db, q = method.postprocess(db, q)
        hook = f"Method {method.name!r} (its postprocess)"
        db = kept_undescribed(undescribed[0], checked(hook, db, database.row_count))  # finite, as the method's own
        database, queries = ArrayRows(db), ArrayRows(kept_undescribed(undescribed[1], checked(hook, q, queries.row_count,
                                                                                               db.shape[1])))
        return database, queries, {"kind": f"{type(method).__name__}.postprocess", "in_memory": True}
    if postprocessor is not None:
        fit_rows = database if fit_on is None else fit_on

        def before_fit():
            found = planned(postprocessor, database, queries, fit_rows, memory_budget)
            if found is not None:
                plan(*found)
        info = fit_postprocessor(postprocessor, fit_rows, memory_budget, state_folder,
                                 before_fit if plan is not None else None)
        return TransformedRows(database, postprocessor, counts_state=True), TransformedRows(queries, postprocessor), info
    return database, queries, None
