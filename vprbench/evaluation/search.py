"""Retrieval with bounded memory: the method's post-processing fitted on the database and
applied chunk by chunk, then exact top-K search streamed from row sources (or an approximate
index, see approximate.py). Peak memory is set by a budget in bytes, not by the data size.

What is promised, on every CPU:

- Scores are float32 inner products rounded to the grid of SCORE_TOLERANCE (2^-16, about
  1.5e-5), and results are ordered by rounded score descending, then by the lower database
  index: rows within rounding of each other are a tie, and a tie goes to the lower index.
- On one machine and BLAS configuration, results are bitwise identical for every memory
  budget: products are tiles of a fixed grid of rows (aligned to row 0, the tile size a
  function of the dimension only), the last tile of each side cut to a multiple of
  TILE_STEP rows (padded with zero rows), so a row's product has a shape set by the data's
  size, never by the budget or by the row's place in a read.
- Across arithmetic paths (BLAS thread counts, numpy or torch, CPUs with other kernels, a
  row at a tile's edge or in its middle) float32 products differ in their last bits (up to
  about 1e-7 for unit descriptors of 49,152 dims). Rounded to the grid they agree, except
  where a score lies within that error of a grid boundary: there it differs by one step,
  and the order can change only between rows within one step of each other.
"""
from __future__ import annotations

from contextlib import nullcontext as _nothing
from dataclasses import dataclass, field

import numpy as np

from ..errors import VPRBenchError
from ..row_sources import (DEFAULT_MEMORY_BUDGET, READ_BYTES, ArrayRows, RowSource, as_rows, format_bytes,
                    parse_memory, read_bytes_per_row)

INDEXES = ("exact", "ivf-pq", "hnsw")
#: scores are rounded to multiples of this before they are ranked (a power of two: exact in float32)
SCORE_TOLERANCE = 2.0 ** -16
TIE_ORDER = "score rounded to 2^-16 descending, then database index ascending"
#: a tile of rows is at most this large (and 256..4,096 rows, a multiple of 256): tiles this
#: big keep BLAS near its peak (a 1,024-row tile of 35,721 dims reaches 86 % of a whole product, 1,792 rows 90 %)
TILE_BYTES = 256 * 2**20
#: tiles are multiples of this many rows, a short last tile too (padded): never the one-row
#: or tiny products where BLAS switches kernels, and at most TILE_STEP - 1 rows computed in vain
TILE_STEP = 256
#: a thread's slice of a query tile is at least this many rows (see `slices`)
MIN_SLICE_ROWS = 64
#: candidates kept per query beyond K while merging raw scores: ties on the grid are settled among them
EXTRA_CANDIDATES = 16
#: queries are scaled by this before their products: exact (a power of two), and the products
#: are then the negated grid units the heaps keep, with no pass over the scores
_UNITS = np.float32(-1 / SCORE_TOLERANCE)

__all__ = ["ArrayRows", "DEFAULT_MEMORY_BUDGET", "INDEXES", "SCORE_TOLERANCE", "SearchResult",
           "exact_search", "search", "tile_rows"]


@dataclass
class SearchResult:
    scores: np.ndarray    # (Q, k) float32, best first
    indices: np.ndarray   # (Q, k) int64 database rows
    info: dict = field(default_factory=dict)  # how it ran: goes into the result record's "search"


def tile_rows(dim: int) -> int:
    """Rows per tile of the grid scores are computed on; depends on the dimension only."""
    rows = TILE_BYTES // (4 * int(dim))
    return int(min(4096, max(TILE_STEP, rows // TILE_STEP * TILE_STEP)))


def product_rows(rows: int, tile: int) -> int:
    """Rows a tile holding `rows` rows is computed with: a whole tile, or a short last tile
    rounded up to a multiple of TILE_STEP (within the tile)."""
    return min(tile, -(-int(rows) // TILE_STEP) * TILE_STEP)


def read_cost(rows) -> tuple[int, int]:
    """(bytes per row held, fixed bytes while reading) of reading `rows`: a source that computes
    its rows (postprocess.TransformedRows) says its own."""
    own = getattr(rows, "read_cost", None)
    return own() if own is not None else (read_bytes_per_row(rows), 0)


def rounded_scores(scores: np.ndarray) -> np.ndarray:
    """Scores on the grid of SCORE_TOLERANCE (round half to even), float32."""
    return (np.rint(np.asarray(scores, dtype=np.float32) / np.float32(SCORE_TOLERANCE))
            * np.float32(SCORE_TOLERANCE)).astype(np.float32)


def inner_products(queries: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """out[:] = queries @ rows.T, (Q, D) x (N, D) -> (Q, N) float32: the one place scores are computed."""
    np.matmul(queries, rows.T, out=out)


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
    """Chunk rows (whole tiles) for the budget, or a clear error when it is too small. The
    budget holds the candidates, one tile of scores, a chunk of queries and two chunks of the
    database (one searched while the next is read); queries get the most, as every chunk of
    queries is one more pass over the database."""
    tile, dim = tile_rows(database.dim), database.dim
    (db_row, db_fixed), (q_row, q_fixed) = read_cost(database), read_cost(queries)
    n, q = int(database.row_count), int(queries.row_count)
    keep = min(n, k + EXTRA_CANDIDATES)
    results = q * keep * 12  # float32 score + int64 index per candidate
    d_tile, q_tile = min(n, tile), min(q, tile)
    fixed = results + db_fixed + q_fixed + 2 * q_tile * d_tile * 4  # a score tile and a trimmed copy of it
    need = fixed + 2 * d_tile * db_row + q_tile * q_row
    if budget < need:
        raise VPRBenchError(
            f"A memory budget of {format_bytes(budget)} is too small for this search: it must hold the top-{keep} "
            f"candidates of {q:,} queries ({format_bytes(results)}) plus a tile of {q_tile} query rows, two tiles of "
            f"{d_tile} database rows of {dim:,} dims and their scores ({format_bytes(need - results)}), "
            f"{format_bytes(need)} in all. Raise --search-memory (memory_budget) to at least {format_bytes(need)}.")
    avail = budget - fixed
    q_tiles = max(1, (avail - 2 * d_tile * db_row) // (q_tile * q_row))
    q_chunk = min(q, q_tiles * q_tile)
    q_held = -(-q_chunk // q_tile) * q_tile
    d_tiles = max(1, min(READ_BYTES // (d_tile * db_row), (avail - q_held * q_row) // (2 * d_tile * db_row)))
    d_chunk = min(n, d_tiles * d_tile)
    return {"tile_rows": int(tile), "chunk_rows": int(d_chunk), "chunks": int(-(-n // d_chunk)),
            "query_chunk_rows": int(q_chunk), "query_chunks": int(-(-q // q_chunk)), "candidates": int(keep)}


def read_into(rows, start: int, stop: int, out: np.ndarray) -> None:
    """Rows start:stop of a row source into `out` (float32, stop - start rows): straight into
    it when the source can (`read_rows_into`), else through a fresh array."""
    reader = getattr(rows, "read_rows_into", None)
    if reader is not None:
        reader(start, stop, out)
        return
    block = np.asarray(rows.read_rows(start, stop), dtype=np.float32)
    if block.shape != (stop - start, rows.dim):
        raise VPRBenchError(f"Row source returned shape {block.shape} for rows {start}:{stop}; expected "
                            f"({stop - start}, {rows.dim}).")
    out[...] = block


class ChunkReader:
    """A row source read chunk by chunk into two buffers, `passes` times over, the next chunk
    always read in a thread while the caller computes on the current one (the first chunk of
    the next pass too). Buffers are whole tiles; rows past the source's end are zeros (the
    padding of the last tile). A source of one chunk is read once and kept."""

    def __init__(self, rows, chunk_rows: int, tile: int, passes: int):
        from concurrent.futures import ThreadPoolExecutor

        self.rows, self.chunk_rows = rows, int(chunk_rows)
        self.starts = list(range(0, rows.row_count, self.chunk_rows))
        held = -(-self.chunk_rows // tile) * tile
        self.buffers = [np.zeros((held, rows.dim), dtype=np.float32) for _ in range(min(2, len(self.starts)))]
        self.loaded = None  # (start, count, buffer) when there is one chunk
        self.reads = len(self.starts) * int(passes)  # chunk reads in all, in order 0, 1, .., 0, 1, ..
        self.step, self.next = 0, None
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="vprbench-read") if len(self.starts) > 1 else None

    def _fill(self, step: int) -> tuple[int, int, np.ndarray]:
        start = self.starts[step % len(self.starts)]
        count = min(self.chunk_rows, self.rows.row_count - start)
        buffer = self.buffers[step % len(self.buffers)]  # not the one the caller computes on
        read_into(self.rows, start, start + count, buffer[:count])
        buffer[count:] = 0
        return start, count, buffer

    def __iter__(self):
        """One pass over the source: (first row, rows, buffer) per chunk."""
        if self.pool is None:
            if self.loaded is None:
                self.loaded = self._fill(0)
            yield self.loaded
            return
        for _ in self.starts:
            chunk = (self.next or self.pool.submit(self._fill, self.step)).result()
            self.step += 1
            self.next = self.pool.submit(self._fill, self.step) if self.step < self.reads else None
            yield chunk

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)


def _heap(distances: np.ndarray, ids: np.ndarray):
    """faiss max-heaps over rows of (negated) scores: they keep the k smallest distances and,
    fed in ascending id order, the lower id on ties (faiss's min-heaps would keep the higher)."""
    import faiss

    heap = faiss.float_maxheap_array_t()
    heap.nh, heap.k = distances.shape
    heap.val, heap.ids = faiss.swig_ptr(distances), faiss.swig_ptr(ids)
    heap.heapify()
    return heap


def search_threads() -> int:
    """Threads a search computes on: as many as the BLAS would use (threadpoolctl sees its
    setting, e.g. OMP_NUM_THREADS or threadpool_limits)."""
    from threadpoolctl import threadpool_info

    found = [int(lib["num_threads"]) for lib in threadpool_info() if lib.get("user_api") == "blas"]
    return max(1, min(found) if found else 1)


def slices(rows: int, threads: int) -> list[tuple[int, int]]:
    """A query tile of `rows` rows cut among `threads` threads: equal slices of at least
    MIN_SLICE_ROWS rows (a tiny product would switch BLAS kernels), fixed by the tile and the
    thread count, never by the budget."""
    count = max(1, min(int(threads), int(rows) // MIN_SLICE_ROWS))
    bounds = [rows * i // count for i in range(count + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


def _one_openmp_thread() -> None:
    import faiss

    faiss.omp_set_num_threads(1)  # per thread: each search thread merges its own slice alone


def _scan(database, queries, keep: int, plan: dict, on_grid: bool) -> tuple[np.ndarray, np.ndarray]:
    """(negated grid units, indices) of the `keep` best rows per query, unordered: queries a
    chunk at a time, the database streamed past each, every product one tile of the grid.
    With several threads, each takes its own slice of every query tile, with one-thread BLAS
    and its own heap rows: products and merges run side by side and no thread waits on another
    within a chunk. `on_grid` rounds each tile of scores before it is merged (the tie rule
    exactly, at the cost of a pass over the scores); otherwise raw units are merged."""
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_limits

    tile, q_chunk = plan["tile_rows"], plan["query_chunk_rows"]
    n_queries = queries.row_count
    q_tile, d_tile = min(n_queries, tile), min(database.row_count, tile)
    distances = np.empty((n_queries, keep), dtype=np.float32)
    indices = np.empty((n_queries, keep), dtype=np.int64)
    threads = len(slices(q_tile, search_threads()))
    scan = _Scan(_heap(distances, indices), q_tile, d_tile, threads, on_grid)
    block = np.zeros((-(-q_chunk // q_tile) * q_tile, queries.dim), dtype=np.float32)
    reader = ChunkReader(database, plan["chunk_rows"], d_tile, passes=-(-n_queries // q_chunk))
    pool = ThreadPoolExecutor(threads, "vprbench-search", _one_openmp_thread) if threads > 1 else None
    try:
        with threadpool_limits(1, user_api="blas") if pool else _nothing():
            for q0 in range(0, n_queries, q_chunk):
                m_chunk = min(q_chunk, n_queries - q0)
                read_into(queries, q0, q0 + m_chunk, block[:m_chunk])
                block[m_chunk:] = 0
                block *= _UNITS
                for d0, count, rows in reader:
                    work = [(w, block, q0, m_chunk, rows, d0, count) for w in range(threads)]
                    list(pool.map(scan.chunk, *zip(*work))) if pool else scan.chunk(*work[0])
    finally:
        reader.close()
        if pool is not None:
            pool.shutdown(wait=True)
    return distances, indices


class _Scan:
    """What one search thread does with a chunk of the database: its slice of every query
    tile against every database tile of the chunk, merged into its heap rows."""

    def __init__(self, heap, q_tile: int, d_tile: int, threads: int, on_grid: bool):
        self.heap, self.q_tile, self.d_tile, self.threads, self.on_grid = heap, q_tile, d_tile, threads, on_grid
        tallest = max(hi - lo for lo, hi in slices(q_tile, threads))
        self.scores = [np.empty(tallest * d_tile, dtype=np.float32) for _ in range(threads)]  # each thread's output

    def chunk(self, worker: int, block, q0: int, m_chunk: int, rows, d0: int, count: int) -> None:
        import faiss

        for t0 in range(0, count, self.d_tile):
            n = min(self.d_tile, count - t0)
            n_held = product_rows(n, self.d_tile)
            for a in range(0, m_chunk, self.q_tile):
                m = min(self.q_tile, m_chunk - a)
                cut = slices(product_rows(m, self.q_tile), self.threads)
                if worker >= len(cut) or cut[worker][0] >= m:
                    continue
                lo, hi = cut[worker]
                real = min(hi, m) - lo  # rows past m are the tile's zero padding
                out = self.scores[worker][:(hi - lo) * n_held].reshape(hi - lo, n_held)
                inner_products(block[a + lo:a + hi], rows[t0:t0 + n_held], out)
                if self.on_grid:
                    np.rint(out, out=out)
                merged = out if n == n_held else np.ascontiguousarray(out[:real, :n])
                self.heap.addn(n, faiss.swig_ptr(merged), d0 + t0, q0 + a + lo, real)


def exact_search(database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET) -> SearchResult:
    """Exact top-k by inner product, streamed from row sources (or arrays) within the budget.
    Raw scores are merged keeping EXTRA_CANDIDATES more than k per query, then put on the grid
    and ordered by the tie rule; a query whose last candidate ties with its k-th (more tied
    rows than candidates) is searched again with every tile rounded before it is merged."""
    database, queries = as_rows(database, "database"), as_rows(queries, "queries")
    k, budget = int(k), parse_memory(memory_budget)
    check_pair(database, queries, k)
    plan = _plan(database, queries, k, budget)
    keep = plan["candidates"]
    distances, indices = _scan(database, queries, keep, plan, on_grid=False)
    units, indices = order_results(-np.rint(distances), indices)  # units: rounded scores in grid steps
    ambiguous = np.flatnonzero(units[:, keep - 1] == units[:, k - 1]) if keep < database.row_count else []
    units, indices = units[:, :k], indices[:, :k]
    if len(ambiguous):
        subset = ArrayRows(queries.read_rows_at(ambiguous))
        again = _plan(database, subset, k, budget)
        exact, exact_indices = _scan(database, subset, k, {**again, "candidates": k}, on_grid=True)
        units[ambiguous], indices[ambiguous] = order_results(-exact, exact_indices)
    scores = (units * np.float32(SCORE_TOLERANCE)).astype(np.float32)
    return SearchResult(scores, indices, {"index": "exact", "memory_budget": budget, **plan,
                                          "queries_searched_again_for_ties": len(ambiguous), "tie_order": TIE_ORDER})


def search(database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET) -> tuple[np.ndarray, np.ndarray]:
    """(scores, indices) of the top-k database rows per query by inner product (cosine on
    L2-normalised descriptors): `exact_search` without its info."""
    result = exact_search(database, queries, k, memory_budget=memory_budget)
    return result.scores, result.indices
