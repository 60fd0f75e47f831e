"""Retrieval with bounded memory: the method's post-processing fitted on the database and
applied chunk by chunk, then exact top-K search streamed from row sources (or an approximate
index, see approximate.py). Peak memory is set by a budget in bytes, not by the data size.

What is promised, on every CPU:

- Scores are float32 inner products rounded to the grid of SCORE_TOLERANCE (2^-16, about
  1.5e-5), and results are ordered by rounded score descending, then by the lower database
  index: rows within rounding of each other are a tie, and a tie goes to the lower index.
- On one machine and BLAS configuration, results are bitwise identical for every memory
  budget: every product has one shape, a fixed grid of rows (aligned to row 0, its size a
  function of the dimension only) with the last tile padded with zero rows, so neither the
  budget nor a row's place in a read decides anything.
- Across arithmetic paths (BLAS thread counts, numpy or torch, CPUs with other kernels, a
  row at a tile's edge or in its middle) float32 products differ in their last bits (up to
  about 1e-7 for unit descriptors of 49,152 dims). Rounded to the grid they agree, except
  where a score lies within that error of a grid boundary: there it differs by one step,
  and the order can change only between rows within one step of each other.
"""
from __future__ import annotations

import hashlib
import json
import time
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from ..fsutil import atomic_path
from ..rows import (DEFAULT_MEMORY_BUDGET, READ_BYTES, ArrayRows, RowSource, as_rows, chunks, format_bytes,
                    parse_memory, read_bytes_per_row)

INDEXES = ("exact", "ivf-pq", "hnsw")
#: scores are rounded to multiples of this before they are ranked (a power of two: exact in float32)
SCORE_TOLERANCE = 2.0 ** -16
TIE_ORDER = "score rounded to 2^-16 descending, then database index ascending"
#: a tile of rows is at most this large (and 64..1024 rows, a power of two)
TILE_BYTES = 32 * 2**20

__all__ = ["ArrayRows", "DEFAULT_MEMORY_BUDGET", "INDEXES", "SCORE_TOLERANCE", "SearchResult", "TransformedRows", "exact_search",
           "retrieve", "search", "tile_rows"]


@dataclass
class SearchResult:
    scores: np.ndarray    # (Q, k) float32, best first
    indices: np.ndarray   # (Q, k) int64 database rows
    info: dict = field(default_factory=dict)  # how it ran: goes into the result record's "search"


def tile_rows(dim: int) -> int:
    """Rows per tile of the grid scores are computed on; depends on the dimension only."""
    rows = max(1, TILE_BYTES // (4 * int(dim)))
    return int(min(1024, max(64, 1 << (rows.bit_length() - 1))))


def read_cost(rows) -> tuple[int, int]:
    """(bytes per row held, fixed bytes while reading) of reading `rows`."""
    if isinstance(rows, TransformedRows):
        return rows.read_cost()
    return read_bytes_per_row(rows), 0


def rounded_scores(scores: np.ndarray) -> np.ndarray:
    """Scores on the grid of SCORE_TOLERANCE (round half to even), float32."""
    return (np.rint(np.asarray(scores, dtype=np.float32) / np.float32(SCORE_TOLERANCE))
            * np.float32(SCORE_TOLERANCE)).astype(np.float32)


def inner_products(queries: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(Q, D) x (N, D) -> (Q, N) float32: the one place scores are computed."""
    return queries @ rows.T


def order_results(scores: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows sorted by score descending, then index ascending (the tie order)."""
    order = np.lexsort((indices, -scores), axis=-1)
    return np.take_along_axis(scores, order, -1), np.take_along_axis(indices, order, -1)


def check_pair(database: RowSource, queries: RowSource, k: int) -> None:
    if database.dim != queries.dim:
        raise VPRBenchError(f"Database descriptors have {database.dim} dims, queries {queries.dim}")
    if queries.row_count < 1:
        raise VPRBenchError("There are no query descriptors to search with.")
    if not 1 <= int(k) <= database.row_count:
        raise VPRBenchError(f"K = {k} must be between 1 and the {database.row_count} database rows; use a smaller --k.")


def _plan(database, queries, k: int, budget: int) -> dict:
    """Query and database chunk rows (whole tiles) for the budget; a clear error when too small."""
    tile, dim = tile_rows(database.dim), database.dim
    (db_row, db_fixed), (q_row, q_fixed) = read_cost(database), read_cost(queries)
    n, q = int(database.row_count), int(queries.row_count)
    results = q * k * 12  # float32 score + int64 index per result
    db_min, q_min = min(n, tile), min(q, tile)
    # + a score tile (and its trimmed copy), a negated database tile, a padded query tile
    fixed = results + db_fixed + q_fixed + 2 * q_min * db_min * 4 + (db_min + q_min) * dim * 4
    need = fixed + db_min * db_row + q_min * q_row
    if budget < need:
        raise VPRBenchError(
            f"A memory budget of {format_bytes(budget)} is too small for this search: it must hold the top-{k} "
            f"results of {q:,} queries ({format_bytes(results)}) plus one tile of {db_min} database rows and {q_min} "
            f"query rows of {dim:,} dims with their scores ({format_bytes(need - results)}), {format_bytes(need)} in "
            f"all. Raise --search-memory (memory_budget) to at least {format_bytes(need)}.")
    avail = budget - fixed

    def whole_tiles(rows: int, total: int, least: int) -> int:
        return total if rows >= total else max(least, rows // tile * tile)

    db_chunk = whole_tiles(min(READ_BYTES, avail - q_min * q_row) // db_row, n, db_min)
    q_chunk = whole_tiles((avail - db_chunk * db_row) // q_row, q, q_min)
    return {"tile_rows": int(tile), "chunk_rows": int(db_chunk), "chunks": int(-(-n // db_chunk)),
            "query_chunk_rows": int(q_chunk), "query_chunks": int(-(-q // q_chunk))}


def padded(block: np.ndarray, rows: int) -> np.ndarray:
    """`block` with zero rows appended up to `rows` (itself when it has them)."""
    if len(block) == rows:
        return block
    out = np.zeros((rows, block.shape[1]), dtype=np.float32)
    out[:len(block)] = block
    return out


def grid_distances(scores: np.ndarray) -> np.ndarray:
    """Scores as negated whole numbers of SCORE_TOLERANCE steps (what the heaps keep: the
    smallest distance is the best score), C-contiguous float32, computed in place when it can."""
    out = np.ascontiguousarray(scores, dtype=np.float32)
    if out is scores and not out.flags.writeable:
        out = out.copy()
    np.multiply(out, np.float32(-1 / SCORE_TOLERANCE), out=out)  # a power of two: exact
    return np.rint(out, out=out)


def _heap(distances: np.ndarray, ids: np.ndarray):
    """faiss max-heaps over rows of (negated) scores: they keep the k smallest distances and,
    fed in ascending id order, the lower id on ties (faiss's min-heaps would keep the higher)."""
    import faiss

    heap = faiss.float_maxheap_array_t()
    heap.nh, heap.k = distances.shape
    heap.val, heap.ids = faiss.swig_ptr(distances), faiss.swig_ptr(ids)
    heap.heapify()
    return heap


def exact_search(database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET) -> SearchResult:
    """Exact top-k by inner product, streamed from row sources (or arrays) within the budget."""
    import faiss

    database, queries = as_rows(database, "database"), as_rows(queries, "queries")
    k, budget = int(k), parse_memory(memory_budget)
    check_pair(database, queries, k)
    plan = _plan(database, queries, k, budget)
    tile, q_chunk = plan["tile_rows"], plan["query_chunk_rows"]
    n_queries = queries.row_count
    q_tile, d_tile = min(n_queries, tile), min(database.row_count, tile)  # the one product shape
    distances = np.empty((n_queries, k), dtype=np.float32)  # negated scores while merging
    indices = np.empty((n_queries, k), dtype=np.int64)
    for q0, block in chunks(queries, q_chunk):
        q1 = q0 + len(block)
        heap = _heap(distances[q0:q1], indices[q0:q1])
        q_tiles = [padded(block[a:a + tile], q_tile) for a in range(0, len(block), tile)]
        for d0, rows in chunks(database, plan["chunk_rows"]):
            for t0 in range(0, len(rows), tile):
                n = min(tile, len(rows) - t0)
                d_rows = padded(rows[t0:t0 + n], d_tile)
                for a, q_rows in zip(range(0, len(block), tile), q_tiles):
                    m = min(tile, len(block) - a)
                    tile_distances = grid_distances(inner_products(q_rows, d_rows)[:m, :n])
                    heap.addn(n, faiss.swig_ptr(tile_distances), d0 + t0, a, m)
            del rows, d_rows, tile_distances  # before the next chunk is read: the budget holds one
        heap.reorder()
        del block, q_tiles
    scores = (distances * np.float32(-SCORE_TOLERANCE)).astype(np.float32)
    scores, indices = order_results(scores, indices)
    return SearchResult(scores, indices, {"index": "exact", "memory_budget": budget, **plan, "tie_order": TIE_ORDER})


def search(database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET) -> tuple[np.ndarray, np.ndarray]:
    """(scores, indices) of the top-k database rows per query by inner product (cosine on
    L2-normalised descriptors): `exact_search` without its info."""
    result = exact_search(database, queries, k, memory_budget=memory_budget)
    return result.scores, result.indices


class TransformedRows:
    """A row source seen through a fitted post-processor, transformed tile by tile on the grid
    of `tile_rows(source.dim)` (aligned to row 0, short tiles padded with zero rows), so a
    row's values depend neither on how a caller chunks its reads nor on its neighbours."""

    def __init__(self, source: RowSource, postprocessor):
        self.source, self.postprocessor = source, postprocessor
        self.row_count, self.folder, self.dtype = int(source.row_count), source.folder, np.dtype(np.float32)
        self.tile = tile_rows(source.dim)
        self.dim = int(self._transform(source.read_rows(0, 1)).shape[1])

    def _transform(self, block: np.ndarray) -> np.ndarray:
        """At most one tile of rows, transformed as one full tile."""
        size = min(self.tile, self.row_count)
        out = np.asarray(self.postprocessor.transform(padded(np.asarray(block, dtype=np.float32), size)),
                         dtype=np.float32)
        if out.ndim != 2 or out.shape[0] != size:
            raise VPRBenchError(f"Post-processor {type(self.postprocessor).__name__} returned shape {out.shape} "
                                f"for {size} rows; expected one row per row.")
        return out[:len(block)]

    def read_cost(self) -> tuple[int, int]:
        # a tile read, padded, and computed in float64 (PCA-whitening does), with its output
        return self.dim * 4, self.tile * (read_bytes_per_row(self.source) + 12 * self.source.dim + 20 * self.dim)

    def read_rows(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.dim), dtype=np.float32)
        for a in range(start - start % self.tile, stop, self.tile):
            b = min(a + self.tile, self.row_count)
            part = self._transform(self.source.read_rows(a, b))
            lo, hi = max(start, a), min(stop, b)
            out[lo - start:hi - start] = part[lo - a:hi - a]
        return out

    def read_rows_at(self, indices) -> np.ndarray:
        rows = self.source.read_rows_at(indices)
        return np.concatenate([self._transform(rows[a:a + self.tile]) for a in range(0, len(rows), self.tile)]
                              or [np.zeros((0, self.dim), dtype=np.float32)])


# ---------------------------------------------------------------- post-processing state
def fit_postprocessor(postprocessor, database: RowSource, memory_budget: int, state_folder=None) -> dict:
    """Fit on the database rows, or load the state a previous run saved in `state_folder`
    (default: the database's folder) under a name keyed by what defines it."""
    key = {"postprocessor": postprocessor.key(database, memory_budget),
           "rows": {"count": database.row_count, "dim": database.dim, "dtype": str(np.dtype(database.dtype))}}
    text = json.dumps(key, sort_keys=True, default=str)
    folder = Path(state_folder) if state_folder is not None else database.folder
    path = Path(folder) / f"postprocess-{hashlib.sha256(text.encode()).hexdigest()[:16]}.npz" if folder else None
    info = {"key": key, "file": str(path) if path else None}
    if path is not None and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as saved:
                postprocessor.load_state({name: saved[name] for name in saved.files if name != "key"})
            return {**info, "state": "loaded"}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as error:
            warnings.warn(f"Refitting: the post-processing state {path} is unreadable ({error}).", stacklevel=2)
    started = time.perf_counter()
    postprocessor.fit(database, memory_budget)
    info.update(state="fitted", fit_s=round(time.perf_counter() - started, 3))
    if path is not None:
        with atomic_path(path) as temporary, open(temporary, "wb") as file:
            np.savez(file, **postprocessor.state(), key=np.array(text))
    return info


def _overrides_postprocess(method) -> bool:
    from ..methods.base import Method

    return getattr(type(method), "postprocess", Method.postprocess) is not Method.postprocess


def postprocessed(method, database: RowSource, queries: RowSource, memory_budget: int, state_folder=None):
    """(database, queries, info): both row sources as `method` post-processes them (its
    post-processor fitted on the database, or a plugin's whole-matrix `postprocess`); info
    None when there is nothing to do. `retrieve` and `vprbench describe` share it."""
    postprocessor = method.postprocessor() if method is not None else None
    if method is not None and _overrides_postprocess(method):  # a plugin's whole-matrix hook
        db, q = method.postprocess(database.read_rows(0, database.row_count), queries.read_rows(0, queries.row_count))
        database, queries = ArrayRows(np.asarray(db, dtype=np.float32)), ArrayRows(np.asarray(q, dtype=np.float32))
        return database, queries, {"kind": f"{type(method).__name__}.postprocess", "in_memory": True}
    if postprocessor is not None:
        info = fit_postprocessor(postprocessor, database, memory_budget, state_folder)
        return TransformedRows(database, postprocessor), TransformedRows(queries, postprocessor), info
    return database, queries, None


def retrieve(method, database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET, index: str = "exact",
             state_folder=None, index_options: dict | None = None) -> SearchResult:
    """Top-k database rows per query for `method`'s descriptors, within `memory_budget` bytes
    (or "1GB"): its post-processor fitted on the database (or loaded from `state_folder`,
    default the database's folder), applied chunk by chunk, then searched with `index`
    ("exact", "ivf-pq" or "hnsw"; `index_options` tune the approximate ones, see
    approximate.py). `method` None searches the rows as they are. The result's info is the
    result record's "search" section."""
    budget = parse_memory(memory_budget)
    if index not in INDEXES:
        raise VPRBenchError(f"Unknown index {index!r}: use one of {', '.join(INDEXES)}.")
    database, queries = as_rows(database, "database"), as_rows(queries, "queries")
    database, queries, postprocess = postprocessed(method, database, queries, budget, state_folder)
    started = time.perf_counter()
    if index == "exact":
        if index_options:
            raise VPRBenchError(f"index='exact' takes no index options, got {sorted(index_options)}.")
        result = exact_search(database, queries, k, memory_budget=budget)
    else:
        from .approximate import approximate_search

        result = approximate_search(database, queries, k, kind=index, memory_budget=budget, options=index_options)
    result.info.update(dim=database.dim, postprocess=postprocess, search_s=round(time.perf_counter() - started, 3))
    return result
