"""Sequence matching over stored descriptors, a block of queries at a time (no re-extraction).

The query-by-database matrix is never whole: each block of queries (its rows widened by the
sequence window, so a block's trajectories see the frames they need) is computed against the
database streamed in chunks, enhanced, searched, and reduced to its top K before the next.
Memory is set by a budget in bytes (block rows follow from it), not by the traverse's length.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ...errors import VPRBenchError
from ...methods.attributes import COMPARES
from ...row_sources import DEFAULT_MEMORY_BUDGET, READ_BYTES, as_rows, chunks, format_budget, format_bytes, parse_memory
from ...search.exact import read_cost, rounded_scores
from ...search.row_checks import check_finite
from ...search.threads import ProductThreads, blas_controller, search_threads
from .matching import (SEQSLAM_DEFAULTS, enhance, query_offsets, second_best, top_k, trajectories,
                       trajectory_costs, velocities)

#: how a sequence stage ranks (its costs on the exact search's grid, see search/exact.py)
TIE_ORDER = "cost rounded to 2^-16 ascending, then database index ascending"

SCORES = ("seqslam", "diagonal")
#: bytes per database column held for each query row of a block: cost row, enhancement's float64
#: temporaries, the trajectory sums, their mean and the best (measured peak about 60 N per row)
BYTES_PER_CELL = 96
#: query rows per product: a fixed tile of the traverse (zero rows pad it), so a query's products,
#: and so its costs, are the same whatever block the budget puts it in (a product's last bits
#: change with its shape and a row's place in it)
PRODUCT_ROWS = 64
#: a product's database rows, and its scores, are at most this many bytes (or 256 rows): the rows
#: stay in the CPU's cache while every tile of query rows meets them
PRODUCT_BYTES = 4 * 2**20
#: bytes per database column of a window's extra row under SeqSLAM: its cost row, the enhancement's
#: float64 copy, means, deviations and running sums, and the enhanced row
ENHANCED_BYTES_PER_CELL = 48


@dataclass
class SequenceResult:
    indices: np.ndarray   # (Q, K) int64 database indices, best first
    scores: np.ndarray    # (Q, K) float32, higher is better
    info: dict = field(default_factory=dict)


def similarities_or_distances(queries: np.ndarray, database: np.ndarray, compare: str) -> np.ndarray:
    """(q, n) float32: inner products (cosine) or mean absolute differences (sad)."""
    if compare == "cosine":
        return queries @ database.T
    import faiss

    return faiss.pairwise_distances(np.ascontiguousarray(queries), np.ascontiguousarray(database),
                                    metric=faiss.METRIC_L1) / np.float32(queries.shape[1])


def product_columns(dim: int) -> int:
    """Database rows per product (`PRODUCT_BYTES`)."""
    return max(256, PRODUCT_BYTES // (4 * max(dim, PRODUCT_ROWS)))


def traverse_tiles(rows: np.ndarray, order: np.ndarray, first: int) -> tuple[np.ndarray, int]:
    """(tiles, offset): rows[order], the queries at traverse positions first, first + 1, ..., placed
    at their positions in whole PRODUCT_ROWS tiles of the traverse (zero rows around them) from
    row `offset` on."""
    offset = first % PRODUCT_ROWS
    tiles = np.zeros((-(-(offset + len(order)) // PRODUCT_ROWS) * PRODUCT_ROWS, rows.shape[1]), dtype=np.float32)
    np.take(rows, order, axis=0, out=tiles[offset:offset + len(order)], mode="clip")  # no copy beside it
    return tiles, offset


def cost_rows(tiles: np.ndarray, offset: int, count: int, database, database_order: np.ndarray, score: str,
              compare: str, chunk_rows: int, enhance_window: int, threads: ProductThreads,
              check: bool = True) -> np.ndarray:
    """(count, N) float32 costs (lower is better) of the query rows in `tiles` (`traverse_tiles`)
    against every database image, in database traverse order: SeqSLAM's enhanced difference (distance
    = sqrt(2 - 2 cos) for unit descriptors, the mean absolute difference for sad); the diagonal's
    -similarity (the distance for sad)."""
    out = np.empty((count, database.row_count), dtype=np.float32)
    for start, block in chunks(database, chunk_rows):
        if check:  # once per search: every block of queries reads the same rows
            check_finite(block, "Database", start)
        step = product_columns(block.shape[1])
        threads.run(partial(_tile_product, tiles, offset, count, block, start, step, compare, out),
                    [(column, at) for column in range(0, len(block), step)
                     for at in range(0, len(tiles), PRODUCT_ROWS)])
        del block  # before the next chunk is read: the budget holds one
    out = out[:, database_order]
    if compare == "cosine":
        if score == "diagonal":
            return np.negative(out, out=out)
        out = np.sqrt(np.maximum(2 - 2 * out, 0, out=out), out=out)
    return enhance(out, enhance_window) if score == "seqslam" else out


def _costs(database, queries, span: int, k: int, chunk_rows: int, enhanced: bool) -> tuple[int, int]:
    """(bytes held whatever the block, bytes per query row of a block) of `plan_blocks`."""
    n_queries, n_database, dim = queries.row_count, database.row_count, database.dim
    (db_row, db_fixed), (q_row, q_fixed) = read_cost(database), read_cost(queries)
    # query rows are read before the database's; beside a database chunk, the zero rows of the query
    # rows' tiles (two part tiles at most) and one tile's products
    product = PRODUCT_ROWS * (2 * dim + 2 * min(chunk_rows, n_database, product_columns(dim))) * 4
    reading = max(chunk_rows * db_row + db_fixed + product, q_fixed)
    held = n_queries * (12 * k + 128)  # the top K (int64 index, float32 cost) and a little per query
    per_row = BYTES_PER_CELL * n_database + q_row + 4 * dim
    # the window's extra rows beside a database chunk as they are computed, then (SeqSLAM) enhanced
    extra = max(reading + span * (4 * n_database + q_row + 4 * dim),
                span * (ENHANCED_BYTES_PER_CELL * n_database + q_row + 4 * dim) if enhanced else 0)
    return held + extra, per_row


def database_chunk_rows(database) -> int:
    """Database rows the search reads at a time."""
    return max(1, min(database.row_count, READ_BYTES // (4 * database.dim)))


def sequence_need(database, queries, k: int, *, score: str = "seqslam", length: int = SEQSLAM_DEFAULTS["length"],
                  mode: str = "offline") -> int:
    """The least budget `sequence_search` takes on these rows (only their shapes and read costs are
    used): one block of one query row, beside every query's top `k`. A run checks it before any search."""
    fixed, per_row = _costs(database, queries, len(query_offsets(length, mode)) - 1, min(int(k), database.row_count),
                            database_chunk_rows(database), score == "seqslam")
    return fixed + per_row


def plan_blocks(database, queries, span: int, budget: int, k: int, chunk_rows: int, enhanced: bool) -> int:
    """Query rows per block within `budget`: each costs BYTES_PER_CELL per database image
    and its descriptor twice (read, then put in traverse order); the window's
    extra rows a cost row each, or ENHANCED_BYTES_PER_CELL once the database is read (`enhanced`:
    SeqSLAM enhances them too). Rows cost what `read_cost` says (a post-processed source transforms
    as it reads), the database read `chunk_rows` at a time. Beside them every query's top `k`, and
    the scores are made from them in place."""
    n_queries, n_database = queries.row_count, database.row_count
    fixed, per_row = _costs(database, queries, span, k, chunk_rows, enhanced)
    rows = (budget - fixed) // per_row
    if rows < 1:
        need = fixed + per_row
        what = "sequence matching" if span else "comparing queries"  # sequences of one frame: a distance search
        raise VPRBenchError(f"A memory budget of {format_bytes(budget)} is too small for {what} against "
                            f"{n_database:,} database images: one block and the top {k} of {n_queries:,} queries need "
                            f"{format_bytes(need)}. Raise --search-memory (memory_budget) to at least "
                            f"{format_budget(need)}.")
    # whole tiles of the traverse: a block's products then waste only the window's two part tiles
    return int(min(rows if rows < PRODUCT_ROWS else rows - rows % PRODUCT_ROWS, n_queries))


def sequence_search(database, queries, k: int, *, score: str = "seqslam", compare: str = "cosine",
                    length: int = SEQSLAM_DEFAULTS["length"], mode: str = "offline", database_order=None,
                    query_order=None, enhance_window: int = SEQSLAM_DEFAULTS["enhance_window"],
                    v_min: float = SEQSLAM_DEFAULTS["v_min"], v_max: float = SEQSLAM_DEFAULTS["v_max"],
                    v_step: float = SEQSLAM_DEFAULTS["v_step"],
                    uniqueness_window: int = SEQSLAM_DEFAULTS["uniqueness_window"],
                    memory_budget=DEFAULT_MEMORY_BUDGET, grid: bool = False) -> SequenceResult:
    """Top-k database images per query by sequence matching (see matching.py for the scores).

    `database_order`/`query_order` are each split's row indices in traverse (capture) order
    (default: the rows' own order); results are per query row, database indices as stored.
    SeqSLAM's scores are -(cost - m) / (second - m): the top-1 score is minus OpenSeqSLAM's match
    quality (its cost over the best cost outside the uniqueness window, m the enhanced matrix's
    minimum), so a PR curve over top-1 scores thresholds that ratio. The diagonal's scores are
    the mean similarity (minus the mean distance for sad). `grid`: costs rounded to the exact
    search's grid (`rounded_scores`) before they are ranked (ties to the lower database index)."""
    database, queries = as_rows(database, "database"), as_rows(queries, "queries")
    if score not in SCORES or compare not in COMPARES:
        raise VPRBenchError(f"Sequence matching scores by one of {SCORES} and compares descriptors by one of "
                            f"{COMPARES}; got {score!r} and {compare!r}.")
    if database.dim != queries.dim:
        raise VPRBenchError(f"Database descriptors have {database.dim} dims, queries {queries.dim}.")
    n, q = database.row_count, queries.row_count
    database_order = _order(database_order, n, "database")
    query_order = _order(query_order, q, "query")
    offsets = query_offsets(length, mode)
    speeds = velocities(v_min, v_max, v_step) if score == "seqslam" else velocities(1, 1, 1)
    paths = trajectories(offsets, speeds)
    budget = parse_memory(memory_budget)
    chunk_rows = database_chunk_rows(database)
    k = min(int(k), n)
    block = plan_blocks(database, queries, len(offsets) - 1, budget, k, chunk_rows, score == "seqslam")
    indices = np.empty((q, k), dtype=np.int64)
    costs = np.empty((q, k), dtype=np.float32)
    second = np.full(q, np.inf, dtype=np.float32)
    lowest = np.inf
    # each fixed-shape product on one thread, as exact search's (a BLAS on several splits a product's sums
    # by their count: 1,000-dim rows gave costs a grid step apart at 1 and 2 threads); one pool and one
    # look for the BLAS a search: made per block of queries, they were most of its time
    blas = blas_controller()
    with ProductThreads(search_threads(blas), blas, "vprbench-sequence") as threads:
        for start in range(0, q, block):
            stop = min(q, start + block)
            first, last = max(0, start + int(offsets[0])), min(q, stop + int(offsets[-1]))
            wanted = query_order[first:last]
            sorted_rows = np.unique(wanted)
            tiles, offset = traverse_tiles(queries.read_rows_at(sorted_rows), np.searchsorted(sorted_rows, wanted), first)
            check_finite(tiles[offset:offset + len(wanted)], "Query", numbers=wanted)
            matrix = cost_rows(tiles, offset, len(wanted), database, database_order, score, compare, chunk_rows,
                               enhance_window, threads, check=start == 0)
            del tiles  # not held while the next block's rows are read
            lowest = min(lowest, float(matrix.min()))
            best = trajectory_costs(matrix, first, start, stop, q, offsets, paths)
            del matrix
            if grid:
                rounded_scores(best, out=best)  # in place: the block is the search's largest array
            places, values = top_k(best, k, ties=database_order)
            at = query_order[start:stop]  # results by query row and database row as stored
            indices[at], costs[at] = database_order[places], values
            if score == "seqslam":
                second[at] = second_best(best, places[:, 0], uniqueness_window)
            del best, places, values
    scores = costs  # made in place: the results are the search's largest arrays at K = N
    if score == "seqslam":
        spread = second - np.float32(lowest)
        spread = np.where(np.isfinite(spread), np.maximum(spread, np.float32(1e-12)), np.float32(1))
        np.divide(np.subtract(costs, np.float32(lowest), out=scores), spread[:, None], out=scores)
    np.negative(scores, out=scores)
    info = {"score": score, "compare": compare, "length": int(length), "mode": mode,
            "query_offsets": [int(offsets[0]), int(offsets[-1])], "trajectories": int(len(paths)),
            "velocities": [str(v) for v in speeds], "block_rows": int(block), "blocks": -(-q // block),
            "memory_budget": budget, "tie_order": TIE_ORDER if grid else "cost ascending, then database index ascending"}
    if score == "seqslam":
        info.update(enhance_window=int(enhance_window), uniqueness_window=int(uniqueness_window),
                    enhanced_minimum=round(lowest, 6))
    return SequenceResult(indices, scores, info)


def _order(order, count: int, split: str) -> np.ndarray:
    if order is None:
        return np.arange(count, dtype=np.int64)
    order = np.asarray(order, dtype=np.int64)
    if order.shape != (count,) or not np.array_equal(np.sort(order), np.arange(count)):
        raise VPRBenchError(f"The {split} traverse order must name each of its {count} images once.")
    return order


def _tile_product(tiles, offset: int, count: int, block, start: int, step: int, compare: str, out, column: int,
                  at: int) -> None:
    """Into `out` (the cost rows) the products of the tile of query rows at `at` with the rows column ..
    column + step of the database chunk `block` (from row `start`): always a whole tile's product, a whole
    tile's written where it lands (no copy held beside it), a part tile's cut from it."""
    rows, tile = block[column:column + step], tiles[at:at + PRODUCT_ROWS]
    out = out[:, start + column:start + column + len(rows)]
    lo, hi = max(at, offset), min(at + PRODUCT_ROWS, offset + count)
    if compare == "cosine" and hi - lo == PRODUCT_ROWS:
        np.matmul(tile, rows.T, out=out[lo - offset:hi - offset])
    else:
        out[lo - offset:hi - offset] = similarities_or_distances(tile, rows, compare)[lo - at:hi - at]
