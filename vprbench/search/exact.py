"""Exact top-K search with bounded memory, streamed from row sources (an approximate index:
approximate.py; the post-processing before it: evaluation/postprocess.py). Peak memory is set
by a budget in bytes, not by the data size.

What is promised, on every CPU:

- Scores are float32 inner products rounded to the grid of SCORE_TOLERANCE (2^-16, about
  1.5e-5), and results are ordered by rounded score descending, then by the lower database
  index: rows within rounding of each other are a tie, and a tie goes to the lower index.
- On one machine and GEMM configuration (oneDNN or numpy's BLAS, gemm.py; thread count),
  results are bitwise identical for every memory budget: products are tiles of a fixed grid
  of rows (chunks.py), so a row's product has a shape set by the data's size, never by the
  budget or by the row's place in a read.
- Across arithmetic paths (thread counts, oneDNN, numpy or torch's BLAS, CPUs with other
  kernels, a row at a tile's edge or in its middle) float32 products differ in their last bits (up to
  about 1e-7 for unit descriptors of 49,152 dims). Rounded to the grid they agree, except
  where a score lies within that error of a grid boundary: there it differs by one step,
  and the order can change only between rows within one step of each other.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..errors import VPRBenchError
from ..features.allocator import keep_freed_memory
from ..row_sources import (DEFAULT_MEMORY_BUDGET, READ_BYTES, ArrayRows, as_rows, format_budget,
                    format_bytes, parse_memory, read_bytes_per_row)
from .chunks import Chunk, ChunkReader, tile_rows
from .row_checks import check_pair, check_products, checked
from .threads import ProductThreads, blas_controller, search_threads

INDEXES = ("exact", "ivf-pq", "hnsw")
#: scores are rounded to multiples of this before they are ranked (a power of two: exact in float32)
SCORE_TOLERANCE = 2.0 ** -16
TIE_ORDER = "score rounded to 2^-16 descending, then database index ascending"
#: a thread's slice of a query tile is at least this many rows (see `slices`)
MIN_SLICE_ROWS = 64
#: candidates kept per query beyond K while merging raw scores: ties on the grid are settled among them
EXTRA_CANDIDATES = 16
#: scores are scaled by this after their products: exact (a power of two), giving the negated
#: grid units the heaps keep
SCORE_UNITS = np.float32(-1 / SCORE_TOLERANCE)
#: the largest product computed at once (bytes of scores): below glibc's mmap threshold
PRODUCT_BYTES = 16 * 2**20
#: bytes one candidate takes while its query's candidates are put in order (its negated score twice,
#: the sort's order, the ordered score and index: 24 measured)
ORDER_BYTES = 32
#: bytes per query beside its candidates: whether it is all zero, whether it ties at k, a tied one's index
FLAG_BYTES = 10

__all__ = ["AllZero", "ArrayRows", "DEFAULT_MEMORY_BUDGET", "INDEXES", "SCORE_TOLERANCE", "SearchResult",
           "exact_search", "search", "tile_rows"]


class AllZero(NamedTuple):
    """The all-zero rows a search saw (after post-processing), each row counted once: such a query
    still gets the tie rule's candidates (rows 0, 1, ...) but matches nothing, so it counts as a
    failure at every K, whatever a re-ranker does with them (metrics.correct_at; but see `failures`)."""

    queries: np.ndarray   # (Q,) bool: the query's descriptor is all zero
    database: int         # database rows that are all zero

    def counts(self) -> dict[str, int]:
        """The record's counts of them."""
        return {"all_zero_queries": int(np.count_nonzero(self.queries)), "all_zero_database": int(self.database)}

    def failures(self, track: str) -> np.ndarray | None:
        """The queries that count as failures on `track`: none on the sequence track, where a stage
        places a query from its neighbours' descriptors too (a blank frame in a known sequence)."""
        return None if track == "sequence" else self.queries


@dataclass
class SearchResult:
    scores: np.ndarray    # (Q, k) float32, best first
    indices: np.ndarray   # (Q, k) int64 database rows
    info: dict = field(default_factory=dict)  # how it ran: goes into the result record's "search"
    all_zero: AllZero | None = None  # None where they were not counted (a distance search, an older candidates file)


def read_cost(rows) -> tuple[int, int]:
    """(bytes per row held, fixed bytes while reading) of reading `rows`: a source that computes
    its rows (postprocess.TransformedRows) says its own."""
    own = getattr(rows, "read_cost", None)
    return own() if own is not None else (read_bytes_per_row(rows), 0)


def rounded_scores(scores: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Scores on the grid of SCORE_TOLERANCE (round half to even), float32; into `out` (which may be
    `scores` itself: no copy of a large block) when given."""
    scores = np.asarray(scores, dtype=np.float32)
    out = np.empty_like(scores) if out is None else out
    with np.errstate(over="ignore"):  # a score beyond float32 in grid steps: refused by the caller
        np.divide(scores, np.float32(SCORE_TOLERANCE), out=out)
        np.rint(out, out=out)
        return np.multiply(out, np.float32(SCORE_TOLERANCE), out=out)


def products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b.T by gemm.products (imported when first used: it imports torch)."""
    from ..gemm import products as onednn_or_numpy

    return onednn_or_numpy(a, b)


def inner_products(queries: np.ndarray, rows: np.ndarray, out: np.ndarray, scale: np.float32) -> None:
    """out[:] = queries @ rows.T * scale, (Q, D) x (N, D) -> (Q, N) float32: the one place scores are
    computed (on oneDNN where torch has it, gemm.py). Products come a few columns at a time so each
    fresh product stays in memory the allocator reuses (features/allocator.py); the columns per
    product are set by the tile's shape, never by the budget."""
    step = max(1, PRODUCT_BYTES // (4 * max(1, len(queries))))
    with np.errstate(over="ignore"):  # rows too long to compare: an infinite score kept is refused
        for lo in range(0, len(rows), step):
            np.multiply(products(queries, rows[lo:lo + step]), scale, out=out[:, lo:lo + step])


def order_results(scores: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows sorted by score descending, then index ascending (the tie order)."""
    order = np.lexsort((indices, -scores), axis=-1)
    return np.take_along_axis(scores, order, -1), np.take_along_axis(indices, order, -1)


class _Least(NamedTuple):
    """What exact search holds whatever its budget: the candidates (`results`), and with the rest
    (`fixed`) a tile of scores; `need` adds one tile of query rows and two of database rows, or
    what ordering the candidates or searching a tied query again takes, if more."""
    tile: int
    keep: int
    results: int
    fixed: int
    need: int
    d_tile: int
    q_tile: int
    db_row: int
    q_row: int


def _in_memory(count: int, dim: int) -> ArrayRows:
    """`count` float32 rows held in memory, for sizing a search (no memory of its own)."""
    return ArrayRows(np.broadcast_to(np.float32(0), (count, dim)))


def _least(database, queries, k: int, again: bool = False) -> _Least:
    """`again`: a search of tied queries again, whose answers go into those held beside it."""
    tile = tile_rows(database.dim)
    (db_row, db_fixed), (q_row, q_fixed) = read_cost(database), read_cost(queries)
    n, q = int(database.row_count), int(queries.row_count)
    keep = min(n, k + EXTRA_CANDIDATES)
    results, answers = q * keep * 12, 0 if again else q * k * 12  # float32 score + int64 index each
    d_tile, q_tile = min(n, tile), min(q, tile)
    flags = q * FLAG_BYTES
    # a score tile, a trimmed copy of it, and the products being written into it (at most a tile)
    fixed = results + flags + db_fixed + q_fixed + 3 * q_tile * d_tile * 4
    need = max(fixed + 2 * d_tile * db_row + q_tile * q_row,
               results + answers + flags + ORDER_BYTES * keep)  # then the answers, a query's candidates at a time
    if not again:  # beside the answers, one query whose k-th ties searched again: its row and that search
        need = max(need, answers + flags + queries.dim * 4
                   + _least(database, _in_memory(1, queries.dim), k, True).need)
    return _Least(tile, keep, results, fixed, need, d_tile, q_tile, db_row, q_row)


def search_need(database, queries, k: int) -> int:
    """The least budget `exact_search` of these row sources takes (their shapes and read costs only)."""
    return _least(database, queries, k).need


def least_budget(database, query_count: int, k: int) -> int:
    """The least budget exact search of `query_count` float32 query rows held in memory takes."""
    return _least(database, _in_memory(query_count, database.dim), k).need


def most_that_fit(count: int, cost, budget: int) -> int:
    """`count`, halved until `cost(count)` fits `budget` (at least 1: the caller refuses what one costs)."""
    while count > 1 and cost(count) > budget:
        count = -(-count // 2)
    return count


def _plan(database, queries, k: int, budget: int, again: bool = False) -> dict:
    """Chunk rows (whole tiles) for the budget, or a clear error when it is too small. The
    budget holds the candidates, one tile of scores, a chunk of queries and two chunks of the
    database (one searched while the next is read); queries get the most, as every chunk of
    queries is one more pass over the database."""
    tile, keep, results, fixed, need, d_tile, q_tile, db_row, q_row = _least(database, queries, k, again)
    dim, n, q = database.dim, int(database.row_count), int(queries.row_count)
    if budget < need:
        raise VPRBenchError(
            f"A memory budget of {format_bytes(budget)} is too small for this search: it must hold the top-{keep} "
            f"candidates of {q:,} queries ({format_bytes(results)}) plus a tile of {q_tile} query rows, two tiles of "
            f"{d_tile} database rows of {dim:,} dims and their scores ({format_bytes(need - results)}), "
            f"{format_bytes(need)} in all. Raise --search-memory (memory_budget) to at least {format_budget(need)}.")
    avail = budget - fixed
    q_tiles = max(1, (avail - 2 * d_tile * db_row) // (q_tile * q_row))
    q_chunk = min(q, q_tiles * q_tile)
    q_held = -(-q_chunk // q_tile) * q_tile
    d_tiles = max(1, min(READ_BYTES // (d_tile * db_row), (avail - q_held * q_row) // (2 * d_tile * db_row)))
    d_chunk = min(n, d_tiles * d_tile)
    return {"tile_rows": int(tile), "chunk_rows": int(d_chunk), "chunks": int(-(-n // d_chunk)),
            "query_chunk_rows": int(q_chunk), "query_chunks": int(-(-q // q_chunk)), "candidates": int(keep)}


def top_heap(distances: np.ndarray, ids: np.ndarray):
    """faiss max-heaps over rows of (negated) scores: they keep the k smallest distances and,
    fed in ascending id order, the lower id on ties (faiss's min-heaps would keep the higher)."""
    import faiss

    heap = faiss.float_maxheap_array_t()
    heap.nh, heap.k = distances.shape
    heap.val, heap.ids = faiss.swig_ptr(distances), faiss.swig_ptr(ids)
    heap.heapify()
    return heap


def slices(rows: int, threads: int) -> list[tuple[int, int]]:
    """A query tile of `rows` rows cut among `threads` threads: equal slices of at least
    MIN_SLICE_ROWS rows (a tiny product would switch BLAS kernels), fixed by the tile and the
    thread count, never by the budget."""
    count = max(1, min(int(threads), int(rows) // MIN_SLICE_ROWS))
    bounds = [rows * i // count for i in range(count + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


def _scan(database, queries, keep: int, plan: dict, on_grid: bool) -> tuple[np.ndarray, np.ndarray, AllZero]:
    """(negated grid units, indices) of the `keep` best rows per query, unordered, and the all-zero
    rows (the database's counted on its first pass only): queries a
    chunk at a time, the database streamed past each, every product one tile of the grid.
    Each thread takes its own slice of every query tile, computes it on one thread (threads.py) and
    merges it into its own heap rows: products and merges run side by side and no thread waits on
    another within a chunk. `on_grid` rounds each tile of scores before it is merged (the tie rule
    exactly, at the cost of one more pass over the scores); otherwise raw units are merged."""
    keep_freed_memory()  # every product's scores reuse the last one's memory
    tile, q_chunk = plan["tile_rows"], plan["query_chunk_rows"]
    n_queries = queries.row_count
    q_tile, d_tile = min(n_queries, tile), min(database.row_count, tile)
    readers = []
    try:
        # both start reading now, side by side (the queries into one buffer: the plan holds one chunk)
        readers.append(query_reader := ChunkReader(queries, q_chunk, q_tile, passes=1, buffers=1))
        readers.append(reader := ChunkReader(database, plan["chunk_rows"], d_tile, passes=-(-n_queries // q_chunk)))
        distances = np.empty((n_queries, keep), dtype=np.float32)
        indices = np.empty((n_queries, keep), dtype=np.int64)
        libraries = blas_controller()
        threads = len(slices(q_tile, search_threads(libraries)))
        scan = _Scan(top_heap(distances, indices), q_tile, d_tile, threads, on_grid)
        zero_queries, zero_database = np.zeros(n_queries, dtype=bool), 0
        with ProductThreads(threads, libraries) as products_on:
            for number, query_chunk in enumerate(query_reader):
                zero_queries[checked(query_chunk, "Query")] = True
                for chunk in reader:
                    zeros = checked(chunk, "Database")
                    zero_database += len(zeros) if number == 0 else 0
                    products_on.run(scan.chunk, [(w, query_chunk, chunk) for w in range(threads)])
                    chunk = None  # let go before the next is read (ChunkReader)
                query_chunk = None
    finally:
        for opened in readers:
            opened.close()
    return distances, indices, AllZero(zero_queries, zero_database)


class _Scan:
    """What one search thread does with a chunk of the database: its slice of every query
    tile against every database tile of the chunk, merged into its heap rows."""

    def __init__(self, heap, q_tile: int, d_tile: int, threads: int, on_grid: bool):
        self.heap, self.q_tile, self.d_tile, self.threads, self.on_grid = heap, q_tile, d_tile, threads, on_grid
        tallest = max(hi - lo for lo, hi in slices(q_tile, threads))
        self.scores = [np.empty(tallest * d_tile, dtype=np.float32) for _ in range(threads)]  # each thread's output

    def chunk(self, worker: int, queries: Chunk, database: Chunk) -> None:
        import faiss

        for t, (rows, n) in enumerate(zip(database.tiles, database.real)):
            for a, (block, m) in enumerate(zip(queries.tiles, queries.real)):
                cut = slices(len(block), self.threads)
                if worker >= len(cut) or cut[worker][0] >= m:
                    continue
                lo, hi = cut[worker]
                real = min(hi, m) - lo  # rows past m are the tile's zero padding
                out = self.scores[worker][:(hi - lo) * len(rows)].reshape(hi - lo, len(rows))
                inner_products(block[lo:hi], rows, out, SCORE_UNITS)
                if self.on_grid:
                    np.rint(out, out=out)
                merged = out if n == len(rows) else np.ascontiguousarray(out[:real, :n])
                self.heap.addn(n, faiss.swig_ptr(merged), database.start + t * self.d_tile,
                               queries.start + a * self.q_tile + lo, real)


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
    distances, indices, all_zero = _scan(database, queries, keep, plan, on_grid=False)
    check_products(distances)
    units, answers = np.empty((queries.row_count, k), np.float32), np.empty((queries.row_count, k), np.int64)
    flags = queries.row_count * FLAG_BYTES
    tied = _order(distances, indices, units, answers, budget - distances.nbytes - indices.nbytes - units.nbytes
                  - answers.nbytes - flags, on_grid=False)
    distances = indices = None
    # an all-zero query ties everywhere, matches nothing: its list is not worth another pass over the database
    ambiguous = np.flatnonzero(tied & ~all_zero.queries) if keep < database.row_count else []
    if len(ambiguous):
        _search_again(database, queries, ambiguous, k, budget - units.nbytes - answers.nbytes - flags, units, answers)
    np.multiply(units, np.float32(SCORE_TOLERANCE), out=units)  # exact: a power of two
    return SearchResult(units, answers, {"index": "exact", "memory_budget": budget, **plan,
                                         "queries_searched_again_for_ties": len(ambiguous), "tie_order": TIE_ORDER},
                        all_zero)


def _order(raw, raw_indices, units, indices, budget: int, on_grid: bool, at=None) -> np.ndarray:
    """The top k of each query's candidates (negated units, rounded here unless `on_grid`), ordered
    by the tie rule, into rows `at` (all if None) of units and indices, as many queries at a time
    as `budget` bytes hold; whether each query's last candidate ties with its k-th."""
    count, keep = raw.shape
    k = units.shape[1]
    step = max(1, budget // (ORDER_BYTES * keep))
    tied = np.empty(count, dtype=bool)
    for lo in range(0, count, step):
        block = raw[lo:lo + step]
        ordered, order = order_results(-(block if on_grid else np.rint(block)), raw_indices[lo:lo + step])
        tied[lo:lo + step] = ordered[:, keep - 1] == ordered[:, k - 1]
        rows = slice(lo, lo + step) if at is None else at[lo:lo + step]
        units[rows], indices[rows] = ordered[:, :k], order[:, :k]
        ordered = order = None  # let go before the next are ordered
    return tied


def _search_again(database, queries, tied: np.ndarray, k: int, budget: int, units, indices) -> None:
    """The queries `tied` searched again, every tile rounded before it is merged (the tie rule
    exactly), into their rows of units and indices: as many at a time as `budget` holds."""
    q_row, q_fixed = read_cost(queries)

    def cost(count: int) -> int:  # reading the rows, then holding them beside their search
        return max(count * q_row + q_fixed,
                   count * queries.dim * 4 + _least(database, _in_memory(count, queries.dim), k, True).need)

    step = most_that_fit(len(tied), cost, budget)
    for lo in range(0, len(tied), step):
        rows = ArrayRows(queries.read_rows_at(tied[lo:lo + step]))
        left = budget - rows.array.nbytes
        plan = {**_plan(database, rows, k, left, again=True), "candidates": k}
        exact, exact_indices, _ = _scan(database, rows, k, plan, on_grid=True)
        check_products(exact)
        _order(exact, exact_indices, units, indices, left - exact.nbytes - exact_indices.nbytes, on_grid=True,
               at=tied[lo:lo + step])
        rows = exact = exact_indices = None  # let go before the next are read


def search(database, queries, k: int, *, memory_budget=DEFAULT_MEMORY_BUDGET) -> tuple[np.ndarray, np.ndarray]:
    """(scores, indices) of the top-k database rows per query by inner product (cosine on
    L2-normalised descriptors): `exact_search` without its info."""
    result = exact_search(database, queries, k, memory_budget=memory_budget)
    return result.scores, result.indices
