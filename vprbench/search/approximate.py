"""Approximate search for very large databases: a faiss IVF-PQ or HNSW index trained on a
seeded sample and filled chunk by chunk from the row source, each query's shortlist
re-scored exactly from the rows, and the recall lost against exact search measured on a
seeded sample of queries."""
from __future__ import annotations

import math
import time
from contextlib import contextmanager, nullcontext
from typing import NamedTuple

import numpy as np

from ..errors import VPRBenchError
from ..row_sources import READ_BYTES, ArrayRows, RowSource, chunks, format_budget, format_bytes
from .exact import (ORDER_BYTES, SCORE_UNITS, TIE_ORDER, AllZero, SearchResult, exact_search,
                    inner_products, least_budget, order_results, read_cost, rounded_scores, top_heap)
from .row_checks import check_finite, check_pair, zero_rows
from .threads import blas_controller, one_thread_each

APPROXIMATE = ("ivf-pq", "hnsw")
#: what an index's results depend on beyond its options, raised when the code changes them: a stored record
#: is served only while it is the one it was made with (a record without one: 1). ivf-pq 2: lists picked by
#: vprbench on fixed tiles of queries (`_Probes`), not by faiss; 3 (hnsw 2): queries searched exactly on one
#: thread (`_exact`)
VERSIONS = {"ivf-pq": 3, "hnsw": 2}
#: faiss's k-means wants at least 39 training points per centroid
POINTS_PER_CENTROID = 39
PQ_CENTROIDS = 256  # 8-bit PQ codes
#: queries faiss searches at once, whatever the budget: it picks its kernels by their count (BLAS for many
#: queries, its own loops for few), which round a query's products with the lists' centroids differently;
#: IVF's lists are picked here instead (`_Probes`), a tile of queries in one product of this shape
QUERY_TILE = 64
LARGEST = 2**31 - 1  # faiss takes its sizes as C int: a larger one overflowed in its setters
DEFAULTS = {"shortlist": 100, "recall_queries": 200, "seed": 0,
            "nprobe": 32, "hnsw_m": 32, "ef_construction": 40}
OPTIONS = {"ivf-pq": ("nlist", "pq_m", "nprobe", "train_rows", "shortlist", "recall_queries", "seed"),
           "hnsw": ("hnsw_m", "ef_construction", "ef_search", "train_rows", "shortlist", "recall_queries", "seed")}


def check_options(kind: str, options: dict) -> None:
    """Refuse (naming it) an option `kind` does not take, or a value that is not a whole number in
    its range (seed >= 0, hnsw_m >= 2, every other >= 1, all within faiss's 32-bit int): checked when
    the run is specified, before any work."""
    unknown = sorted(map(str, set(options) - set(OPTIONS[kind])))  # str: a name may be no text (5)
    if unknown:
        raise VPRBenchError(f"--index {kind} does not take {', '.join(unknown)}; its options: {', '.join(OPTIONS[kind])}.")
    for name, value in options.items():
        least = {"seed": 0, "hnsw_m": 2}.get(name, 1)  # faiss's HNSW of M = 1 kills the process (levels 1/log M)
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise VPRBenchError(f"--index {kind} option {name} takes a whole number >= {least}; got {value!r}.")
        if value > LARGEST and name != "seed":  # the seed goes to numpy, which takes any size
            raise VPRBenchError(f"--index {kind} option {name} takes at most {LARGEST}; got {value}.")


def searched_to(search, depth: int):
    """`search` (a SearchSpec) as it runs for `depth` candidates per query: an unset shortlist (and hnsw's
    ef_search after it) follows the depth past its default, so a deeper search is written out, in the spec's
    identity and its leaderboard row, not hidden in the row of a shallower one with other numbers."""
    if not search.approximate or "shortlist" in search.options or depth <= DEFAULTS["shortlist"]:
        return search
    return search.model_copy(update={"options": {**search.options, "shortlist": int(depth)}})


def index_options(kind: str, n: int, dim: int, k: int, given: dict | None) -> dict:
    """Every option of `kind`, defaults filled in for this database, checked against its size."""
    o = sized_options(kind, n, k, given)
    if kind == "ivf-pq":  # about 8 dims per sub-quantizer, at most 64 bytes per code
        o["pq_m"] = int((given or {}).get("pq_m", next(m for m in range(min(64, max(1, dim // 8)), 0, -1)
                                                       if dim % m == 0)))
        if o["pq_m"] < 1 or dim % o["pq_m"]:
            raise VPRBenchError(f"pq_m = {o['pq_m']} must divide the descriptor dimension {dim}.")
    return o


def sized_options(kind: str, n: int, k: int, given: dict | None) -> dict:
    """The options of `kind` that follow from the database's `n` rows and K alone (all but pq_m), checked:
    known before any descriptor is computed, so a database too small for the index is refused first."""
    given = dict(given or {})
    check_options(kind, given)
    o = {**{name: DEFAULTS[name] for name in OPTIONS[kind] if name in DEFAULTS}, **given}
    o["shortlist"] = int(given.get("shortlist", min(n, max(k, DEFAULTS["shortlist"]))))
    if o["shortlist"] < k:
        raise VPRBenchError(f"A shortlist of {o['shortlist']} is smaller than K = {k}: index={kind!r} needs a "
                            f"shortlist of at least {k} (or use index='exact').")
    if o["shortlist"] > n:
        raise VPRBenchError(f"A shortlist of {o['shortlist']} exceeds the {n:,} database rows: use index='exact' "
                            "(an approximate index buys nothing at this size).")
    if kind == "ivf-pq":
        if "nlist" not in given:  # about sqrt(n) lists, each trainable
            o["nlist"] = 1 << max(0, round(math.log2(math.sqrt(n))))
            while o["nlist"] > 1 and POINTS_PER_CENTROID * o["nlist"] > n:
                o["nlist"] //= 2
        least = POINTS_PER_CENTROID * max(int(o["nlist"]), PQ_CENTROIDS)
        if n < least:
            raise VPRBenchError(
                f"index='ivf-pq' needs at least {least:,} database rows to train its coarse quantizer "
                f"({POINTS_PER_CENTROID} per list x nlist={o['nlist']}) and PQ codebooks ({POINTS_PER_CENTROID} x "
                f"{PQ_CENTROIDS} centroids); this database has {n:,}: use index='exact'.")
        if int(given.get("nprobe", 0)) > int(o["nlist"]):  # probed as nlist: another name for that run
            chosen = "" if "nlist" in given else f", chosen for {n:,} database rows"  # a sweep's smaller datasets
            raise VPRBenchError(f"nprobe = {given['nprobe']} exceeds the index's {o['nlist']} lists (nlist{chosen}): "
                                f"give nprobe <= {o['nlist']}.")
        o["nprobe"] = min(int(o["nprobe"]), int(o["nlist"]))
        o["train_rows"] = int(given.get("train_rows", min(n, max(least, 64 * int(o["nlist"])))))
        if not least <= o["train_rows"] <= n:
            raise VPRBenchError(f"train_rows = {o['train_rows']:,} must be between {least:,} and the {n:,} database rows.")
    else:
        o["ef_search"] = int(given.get("ef_search", max(o["shortlist"], 64)))
        if o["ef_search"] < o["shortlist"]:
            raise VPRBenchError(f"ef_search = {o['ef_search']} is smaller than the shortlist ({o['shortlist']}): "
                                f"use ef_search >= {o['shortlist']}.")
        o["train_rows"] = int(given.get("train_rows", min(n, 10_000)))
        if not 1 <= o["train_rows"] <= n:
            raise VPRBenchError(f"train_rows = {o['train_rows']:,} must be between 1 and the {n:,} database rows.")
    if o["recall_queries"] < 1:
        raise VPRBenchError(f"recall_queries must be at least 1, got {o['recall_queries']}.")
    return {name: int(value) for name, value in o.items()}


def _index_bytes(kind: str, n: int, dim: int, o: dict) -> int:
    """Memory the filled index takes (inverted lists may hold twice their codes while growing)."""
    if kind == "ivf-pq":
        return 2 * n * (o["pq_m"] + 8) + (o["nlist"] + PQ_CENTROIDS) * dim * 4
    return n * (dim + 2 * o["hnsw_m"] * 4 + 16)  # 8-bit codes + level-0 links (+ upper levels)


def _residual_bytes(kind: str, dim: int) -> int:
    """Bytes per row faiss allocates while it trains on or adds rows: IVF-PQ encodes each row's
    residual, a float32 copy of it (measured: 18.8 MB to add a 17.2 MB chunk); HNSW-SQ8 none."""
    return 4 * dim if kind == "ivf-pq" else 0


def add_rows(kind: str, database: RowSource) -> int:
    """Rows added to the index at a time: set by the rows' size, never by the budget, as HNSW inserts each
    batch's rows by level (another batching builds another graph, other shortlists)."""
    return max(1, READ_BYTES // (read_cost(database)[0] + _residual_bytes(kind, database.dim)))


def _build(kind: str, database: RowSource, o: dict):
    import faiss

    dim, n = database.dim, database.row_count
    if kind == "ivf-pq":
        index = faiss.index_factory(dim, f"IVF{o['nlist']},PQ{o['pq_m']}", faiss.METRIC_INNER_PRODUCT)
        index.nprobe, index.do_polysemous_training = o["nprobe"], False  # polysemous codes: unused, slow
    else:
        index = faiss.index_factory(dim, f"HNSW{o['hnsw_m']},SQ8", faiss.METRIC_INNER_PRODUCT)
        index.hnsw.efConstruction, index.hnsw.efSearch = o["ef_construction"], o["ef_search"]
    sample = np.sort(np.random.default_rng(o["seed"]).choice(n, o["train_rows"], replace=False))
    training = np.ascontiguousarray(database.read_rows_at(sample), dtype=np.float32)
    check_finite(training, "Database", numbers=sample)  # before faiss trains on it
    index.train(training)
    del training
    chunk_rows = min(n, add_rows(kind, database))
    zeros = 0  # counted on this one pass over every row
    for start, rows in chunks(database, chunk_rows):
        zeros += int(np.count_nonzero(zero_rows(rows, "Database", start)))  # and faiss indexes no NaN row
        index.add(rows)
        del rows  # before the next chunk is read: the budget holds one
    return index, chunk_rows, zeros


class _Plan(NamedTuple):
    """An approximate search's memory on its rows' shapes: its options, the index, the training sample (or
    a chunk of rows added), a tile of queries, each query searched and its shortlist re-scored, the index's
    answers for a tile, IVF's coarse step (`_Probes`); the least budget of the index's part and of the recall
    check's exact search of `batch` queries."""
    options: dict
    index_bytes: int
    training: int
    tile: int
    searched: int
    rescored: int
    answers: int
    coarse: int
    need: int
    exact_need: int
    batch: int


def _plan(database, queries, k: int, kind: str, options: dict | None) -> _Plan:
    n, dim, n_queries = database.row_count, database.dim, queries.row_count
    o = index_options(kind, n, dim, k, options)
    index_bytes = _index_bytes(kind, n, dim, o)
    (row_bytes, fixed), (q_row, q_fixed) = read_cost(database), read_cost(queries)
    # training set + index, and per query: its row and shortlist (8 bytes each), then its shortlist's rows;
    # beside them the index's answers (12 bytes a candidate) for one tile of queries
    tile = min(n_queries, QUERY_TILE)
    searched, rescored, answers = q_row + o["shortlist"] * 8, o["shortlist"] * row_bytes, tile * o["shortlist"] * 12
    # the training sample, then (in its place) a chunk of rows being added
    training = max(o["train_rows"], min(n, add_rows(kind, database))) * (row_bytes + _residual_bytes(kind, dim))
    coarse = _coarse_bytes(dim, o) if kind == "ivf-pq" else 0
    need = training + fixed + index_bytes + coarse + q_fixed + n_queries * k * 12 + answers + tile * searched + rescored
    # then, beside the answers: queries searched exactly (short shortlists, the recall check), a batch at a time
    held, batch = n_queries * k * 12, min(n_queries, o["recall_queries"])
    exact_need = held + batch * q_row + q_fixed + least_budget(database, batch, k)
    return _Plan(o, index_bytes, training, tile, searched, rescored, answers, coarse, need, exact_need, batch)


def approximate_need(database, queries, k: int, kind: str, options: dict | None = None) -> int:
    """The least budget `approximate_search` of these rows takes (their shapes and read costs only)."""
    plan = _plan(database, queries, k, kind, options)
    return max(plan.need, plan.exact_need)


def approximate_search(database: RowSource, queries: RowSource, k: int, *, kind: str, memory_budget: int,
                       options: dict | None = None) -> SearchResult:
    if kind not in APPROXIMATE:
        raise VPRBenchError(f"Unknown approximate index {kind!r}: use one of {', '.join(APPROXIMATE)}.")
    check_pair(database, queries, k)
    n, dim, n_queries = database.row_count, database.dim, queries.row_count
    plan = _plan(database, queries, k, kind, options)
    o, least = plan.options, max(plan.need, plan.exact_need)
    q_fixed, held = read_cost(queries)[1], n_queries * k * 12  # the answers
    if memory_budget < least:
        raise VPRBenchError(
            f"A memory budget of {format_bytes(memory_budget)} is too small for index={kind!r} on {n:,} rows of {dim:,} "
            f"dims: the index takes about {format_bytes(plan.index_bytes)}, its training sample of "
            f"{o['train_rows']:,} rows or the rows it adds at a time (and faiss's work on them) "
            f"{format_bytes(plan.training)}, {format_bytes(plan.need)} in all; the exact search of {plan.batch:,} "
            f"queries that checks its recall, beside the answers, {format_bytes(plan.exact_need)}. Raise "
            f"--search-memory (memory_budget) to at least {format_budget(least)}, or lower train_rows / pq_m / "
            "recall_queries.")
    started = time.perf_counter()
    index, chunk_rows, zero_database = _build(kind, database, o)
    build_s = time.perf_counter() - started

    started = time.perf_counter()
    free = memory_budget - plan.index_bytes - plan.coarse - q_fixed - n_queries * k * 12 - plan.answers
    q_chunk, group = _query_chunks(free, plan.tile, plan.searched, plan.rescored)
    scores = np.empty((n_queries, k), dtype=np.float32)
    indices = np.empty((n_queries, k), dtype=np.int64)
    # queries whose shortlist came back short: searched exactly, whatever k is, so a run's top-1 does not
    # depend on the deepest K asked (the K list is not part of a leaderboard row)
    short = []
    zero_queries = np.zeros(n_queries, dtype=bool)
    probes = _Probes(index) if kind == "ivf-pq" else None
    blas = blas_controller()  # found once: a limit is then cheap, one per chunk and group of queries
    for q0, block in chunks(queries, q_chunk):
        zero_queries[q0:q0 + len(block)] = zero_rows(block, "Query", q0)
        found = _shortlists(index, probes, block, o["shortlist"], blas)
        for g0 in range(0, len(block), group):
            some = found[g0:g0 + group]
            rows_ids = np.unique(some[some >= 0])
            rows = database.read_rows_at(rows_ids)  # read with the BLAS's threads (a post-processed store's)
            # re-scored on one BLAS thread: a product of long rows is summed in pieces cut by the thread count
            with blas.limit(limits=1, user_api="blas"):
                for i in range(g0, min(g0 + group, len(block))):
                    candidates = found[i][found[i] >= 0]
                    if len(candidates) < o["shortlist"]:
                        short.append(q0 + i)
                        continue
                    exact = rounded_scores(rows[np.searchsorted(rows_ids, candidates)] @ block[i])  # as exact search
                    if not np.isfinite(exact).all():  # every row is finite (checked above): too long, they overflow
                        raise VPRBenchError(f"Inner products of query row {q0 + i} and its shortlist exceed "
                                            "float32's range: the descriptors are too long to compare; L2-normalise "
                                            "them.")
                    s, c = order_results(exact[None], candidates[None])
                    scores[q0 + i], indices[q0 + i] = s[0, :k], c[0, :k]
            del rows  # the budget holds one group's shortlist rows, not this and the next
        del block, found
    del probes, index
    for start in range(0, len(short), plan.batch):  # honest fallback: those queries are searched exactly
        some = np.array(short[start:start + plan.batch])
        scores[some], indices[some] = _exact(database, queries, some, k, memory_budget - held)
    query_s = time.perf_counter() - started

    info = {"index": kind, "version": VERSIONS[kind], "memory_budget": int(memory_budget), "options": o, "index_bytes": plan.index_bytes,
            "chunk_rows": int(chunk_rows), "chunks": -(-n // chunk_rows), "query_chunk_rows": int(min(q_chunk, n_queries)),
            "query_chunks": -(-n_queries // q_chunk), "exact_fallback_queries": len(short),
            "build_s": round(build_s, 3), "query_s": round(query_s, 3), "tie_order": TIE_ORDER,
            "recall_loss": recall_loss(database, queries, k, indices, o, memory_budget - held)}
    return SearchResult(scores, indices, info, AllZero(zero_queries, zero_database))


def _query_chunks(free: int, tile: int, searched: int, rescored: int) -> tuple[int, int]:
    """(queries read and searched at a time, queries whose shortlist rows are read at a time) in `free` bytes:
    whole tiles of queries, so each tile faiss searches starts at a multiple of the tile whatever the budget;
    a budget too small for a tile's shortlist rows takes one tile and reads its rows a few queries at a time."""
    fit = free // (searched + rescored)
    if fit >= tile:
        return fit // tile * tile, fit // tile * tile
    return tile, max(1, (free - tile * searched) // rescored)


def _shortlists(index, probes, block: np.ndarray, shortlist: int, blas) -> np.ndarray:
    """Each query's shortlist (-1 where the index found fewer), searched QUERY_TILE queries at a time; an IVF
    index's lists picked by `probes`, a tile at a time on a thread of its own."""
    found = np.empty((len(block), shortlist), dtype=np.int64)
    with _one_thread(blas) if probes is not None else nullcontext() as pool:
        for t0 in range(0, len(block), QUERY_TILE):
            tile = block[t0:t0 + QUERY_TILE]
            if probes is None:
                found[t0:t0 + QUERY_TILE] = index.search(tile, shortlist)[1]
                continue
            dis, lists = pool.submit(probes.lists, tile).result()
            found[t0:t0 + QUERY_TILE] = probes.ivf.search_preassigned(tile, shortlist, lists, dis)[1]
    return found


@contextmanager
def _one_thread(blas=None):
    """A thread that computes alone (one OpenMP thread for oneDNN, one BLAS thread: set as exact search sets
    its own), so a product's rounding does not depend on how many threads this machine gives it; `blas` from
    `blas_controller`."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, "vprbench-probes", one_thread_each) as pool, \
            (blas or blas_controller()).limit(limits=1, user_api="blas"):
        yield pool


class _Probes:
    """IVF's coarse step done here, not by faiss: faiss splits a tile of queries among its threads first and
    picks its kernel by a slice's size, so a query on a tie between two lists probed one or the other as the
    thread count went. Here a tile's products with the lists' centroids are one product of a fixed shape (the
    tile padded to QUERY_TILE rows) on one thread, and each query probes its `nprobe` best lists by exact
    search's tie rule (score on the grid, then the lower list); faiss scans each query's lists on its own."""

    def __init__(self, index):
        import faiss

        self.ivf = faiss.extract_index_ivf(index)
        self.centroids = self.ivf.quantizer.reconstruct_n(0, self.ivf.nlist)  # (nlist, dim) float32, held once

    def lists(self, tile: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(products with the centroids, list numbers) of the lists each query of `tile` probes, best first."""
        import faiss

        padded = np.zeros((QUERY_TILE, tile.shape[1]), dtype=np.float32)
        padded[:len(tile)] = tile
        raw = np.empty((QUERY_TILE, len(self.centroids)), dtype=np.float32)
        inner_products(padded, self.centroids, raw, np.float32(1))
        with np.errstate(over="ignore"):  # too long to compare: refused when the shortlist is scored
            units = np.rint(raw * SCORE_UNITS)  # negated grid units, as exact search merges them
        shape = (len(tile), self.ivf.nprobe)
        dis, lists = np.empty(shape, dtype=np.float32), np.empty(shape, dtype=np.int64)
        top_heap(dis, lists).addn(len(self.centroids), faiss.swig_ptr(units), 0, 0, len(tile))  # lower list on ties
        lists = order_results(-dis, lists)[1]
        return np.take_along_axis(raw[:len(tile)], lists, 1), lists


def _coarse_bytes(dim: int, o: dict) -> int:
    """`_Probes`' memory: the centroids, and for a tile their products (twice, and the product being
    written), then each query's lists put in order."""
    return o["nlist"] * dim * 4 + QUERY_TILE * (dim * 4 + 3 * o["nlist"] * 4 + o["nprobe"] * (ORDER_BYTES + 24))


def _exact(database: RowSource, queries: RowSource, picked: np.ndarray, k: int, budget: int):
    """(scores, indices) of exact search for the queries at `picked`, their rows read within `budget`, on one
    thread: exact search computes with the BLAS's threads (a tile's slices side by side, or a small tile as one
    product the BLAS cuts among them), and a product's last bits follow how it is cut (OpenBLAS's AVX2 kernels
    round by a part's shape), so the thread count moved these queries' scores across grid boundaries, and with
    them their answers and the recall check's."""
    rows = queries.read_rows_at(picked)
    with _one_thread() as pool:
        found = pool.submit(exact_search, database, ArrayRows(rows), k,
                            memory_budget=budget - rows.nbytes - read_cost(queries)[1]).result()
    return found.scores, found.indices


def recall_loss(database: RowSource, queries: RowSource, k: int, indices: np.ndarray, o: dict, budget: int) -> dict:
    """Agreement with exact search on a seeded sample of queries (searched within `budget`): the share
    whose top-1 is the exact top-1, and the mean share of the exact top-k found."""
    n_queries = queries.row_count
    sample = np.sort(np.random.default_rng(o["seed"]).choice(n_queries, min(n_queries, o["recall_queries"]),
                                                              replace=False))
    exact = _exact(database, queries, sample, k, budget)[1]
    approx = indices[sample]
    overlap = np.mean([len(np.intersect1d(a, e)) / k for a, e in zip(approx, exact)])
    agreement = float(np.mean(approx[:, 0] == exact[:, 0]))
    return {"queries": int(len(sample)), "seed": o["seed"], "k": int(k), "r1_agreement": round(agreement, 6),
            "topk_overlap": round(float(overlap), 6), "r1_loss": round(1 - agreement, 6)}


__all__ = ["APPROXIMATE", "approximate_search", "recall_loss"]
