"""Exact search streamed from row sources: its tie order, its identity across budgets, threads
and arithmetic paths, and its memory budget."""

import os

import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.search.exact import SCORE_TOLERANCE, ArrayRows, exact_search, search
from vprbench.row_sources import parse_memory
from search_rows import budget_for, h5_rows, lattice, ranked, reference_topk, torch_products, unit


def test_tie_order_is_score_then_lower_index_across_chunk_and_query_borders(tiles_of_1024):
    # small integers: every kernel computes the scores exactly, and ties are everywhere,
    # so every chunk border (multiples of 1,024 rows here) cuts through tied groups
    rng = np.random.default_rng(0)
    db = rng.integers(-2, 3, size=(5000, 8)).astype(np.float32)
    q = rng.integers(-2, 3, size=(2500, 8)).astype(np.float32)
    ref_scores, ref_indices = reference_topk(db, q, 20)
    for budget in (10**9, budget_for(db, q, 20, chunks=2, query_chunks=2), budget_for(db, q, 20, chunks=5, query_chunks=3)):
        result = exact_search(db, q, 20, memory_budget=budget)
        np.testing.assert_array_equal(result.indices, ref_indices)
        np.testing.assert_array_equal(result.scores, ref_scores.astype(np.float32))
        assert result.indices.dtype == np.int64 and result.scores.dtype == np.float32
    assert result.info["chunks"] == 5 and result.info["query_chunks"] == 3 and result.info["chunk_rows"] == 1024
    # small integers: some queries tie more rows at their K-th score than there are candidates
    assert 0 < result.info["queries_searched_again_for_ties"] < 2500
    assert result.info["tie_order"] == "score rounded to 2^-16 descending, then database index ascending"


def test_identical_for_every_budget_with_duplicated_rows_on_tile_borders(tmp_path, tiles_of_1024):
    # 12 x 1,024 rows + 1: with small budgets the last chunk is a single row, where BLAS
    # switches kernels (a product of one row differs from a large one by a few ulps)
    db = unit(12_289, 64, 1)
    db[1020:1031] = db[1020]     # 11 copies across the 1,024-row border
    db[4090:4100] = db[7]        # copies of row 7 across the 4,096 border
    db[8191:8193] = db[12_288]   # the last row duplicated across 8,192
    q = unit(700, 64, 2)
    q[0], q[1], q[2] = db[1020], db[7], db[12_288]
    database, queries = h5_rows(tmp_path, "db", db), h5_rows(tmp_path, "q", q)
    whole = exact_search(database, queries, 20, memory_budget=10**9)
    assert whole.info["chunks"] == 1
    for chunks in (4, 13):
        budget = budget_for(db, q, 20, chunks=chunks)
        database.reads.clear()
        split = exact_search(database, queries, 20, memory_budget=budget)
        assert split.info["chunks"] == chunks and max(database.reads) == split.info["chunk_rows"]
        np.testing.assert_array_equal(split.scores, whole.scores)
        np.testing.assert_array_equal(split.indices, whole.indices)
    assert whole.indices[0, :11].tolist() == list(range(1020, 1031))
    assert len(set(whole.scores[0, :11].tolist())) == 1 and whole.scores[0, 11] < whole.scores[0, 10]
    assert whole.indices[1, :11].tolist() == [7, *range(4090, 4100)]
    assert whole.indices[2, :3].tolist() == [8191, 8192, 12_288] and len(set(whole.scores[2, :3].tolist())) == 1
    # everywhere: equal scores are in ascending index order
    same = np.diff(whole.scores, axis=1) == 0
    assert np.all(np.diff(whole.indices, axis=1)[same] > 0)


def test_a_short_last_tile_is_computed_at_its_own_rows_or_padded_to_256(monkeypatch, tiles_of_1024):
    """The grid's last tile is not padded to a whole tile (up to a tile's worth of products
    computed in vain: 20 % of the work at MSLS-val's shape): it is computed at its own rows,
    or at 256 rows (zero padding) when it has fewer. The same for rows lent where they are
    (float32 arrays) and rows read into buffers (float64 arrays), bit for bit."""
    import vprbench.search.exact as search_module

    shapes = []
    real = search_module.inner_products
    monkeypatch.setattr(search_module, "inner_products",
                        lambda q, d, out, scale: (shapes.append(out.shape), real(q, d, out, scale)))
    for tail, padded in ((300, 300), (100, 256)):
        db, q = unit(3 * 1024 + tail, 32, 1), unit(1024 + 5, 32, 2)
        runs = []
        for dtype in (np.float32, np.float64):
            shapes.clear()
            runs.append(exact_search(db.astype(dtype), q.astype(dtype), 10))
            assert sorted(set(shapes)) == sorted({(256, padded), (256, 1024), (1024, padded), (1024, 1024)})
            assert len(shapes) == 8  # 2 query tiles x 4 database tiles
        np.testing.assert_array_equal(runs[0].scores, runs[1].scores)
        np.testing.assert_array_equal(runs[0].indices, runs[1].indices)
        best = np.argmax(q @ db.T, axis=1)
        assert np.mean(runs[0].indices[:, 0] == best) > 0.99  # the top-1 (up to ties on the grid)


def test_search_threads_compute_on_one_thread_each_and_leave_torch_as_it_was():
    """Each search thread runs oneDNN (and faiss) on one OpenMP thread, set for that thread
    only: the caller's torch thread count, and a new thread's, are what they were."""
    import threading

    import torch
    from threadpoolctl import threadpool_limits

    import vprbench.search.exact as search_module

    def counts():
        seen = []
        thread = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
        thread.start(), thread.join()
        return torch.get_num_threads(), seen[0]

    before, inside = counts(), []
    real = search_module.products
    with threadpool_limits(2), pytest.MonkeyPatch.context() as patch:
        patch.setattr(search_module, "products", lambda a, b: (inside.append(torch.get_num_threads()), real(a, b))[1])
        exact_search(unit(3000, 48, 5), unit(1300, 48, 6), 5)
    assert inside and set(inside) == {1}
    assert counts() == before


def test_a_search_on_the_calling_thread_computes_on_one_thread_too(monkeypatch):
    """A search of one slice (fewer queries than two slices' rows, or a BLAS seen on one thread) ran its
    products on the calling thread with all of torch's threads: oneDNN before torch 2.11 splits a product's
    sums by their count, so 1 and 2 threads ranked a tie at the K-th place differently (dba's scores)."""
    import torch
    from threadpoolctl import threadpool_limits

    import vprbench.search.exact as search_module

    inside, real = [], search_module.products
    monkeypatch.setattr(search_module, "products", lambda a, b: (inside.append(torch.get_num_threads()), real(a, b))[1])
    with threadpool_limits(2):
        exact_search(unit(3000, 48, 5), unit(50, 48, 6), 5)  # 50 queries: one slice
        monkeypatch.setattr(search_module, "search_threads", lambda libraries=None: 1)  # a BLAS capped at 1
        exact_search(unit(3000, 48, 5), unit(1300, 48, 6), 5)
    assert inside and set(inside) == {1}


def test_a_thread_limit_set_before_torch_first_runs_holds_in_the_search():
    """A caller's limit set before torch was loaded does not reach torch's OpenMP: in a fresh process the
    search's products ran on every core (the order-dependent failures of the thread tests)."""
    import subprocess
    import sys

    script = """
from threadpoolctl import threadpool_limits
import numpy as np
with threadpool_limits(1):
    import torch
    import vprbench.search.exact as search_module
    rows, seen, real = np.eye(300, 48, dtype=np.float32), [], search_module.products
    search_module.products = lambda a, b: (seen.append(torch.get_num_threads()), real(a, b))[1]
    search_module.exact_search(rows, rows[:100], 5)
print(sorted(set(seen)))
"""
    found = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                           env={k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")})
    assert found.returncode == 0, found.stderr
    assert found.stdout.strip() == "[1]"


def test_a_blas_that_keeps_to_one_thread_does_not_set_the_search_threads():
    """OpenCV 4.8 ships an OpenBLAS that stays on one thread whatever it is told: loaded beside numpy's
    (a run that imported cv2), every search ran on one thread."""
    from vprbench.search.threads import search_threads

    class Libraries:
        def __init__(self, *counts):
            self.counts = counts

        def info(self):
            return [{"user_api": "blas", "num_threads": n} for n in self.counts] + [{"user_api": "openmp", "num_threads": 8}]

    assert (search_threads(Libraries(2, 1)), search_threads(Libraries(1, 1)), search_threads(Libraries())) == (2, 1, 1)


def test_threads_take_slices_of_each_query_tile_and_change_nothing(monkeypatch, tmp_path, tiles_of_1024):
    """With 2 threads each computes its half of every query tile (one-thread BLAS, its own heap
    rows): bitwise the same for every budget, and the same ranking as one thread."""
    from threadpoolctl import threadpool_limits

    import vprbench.search.exact as search_module

    db, q = unit(3 * 1024 + 300, 48, 5), unit(1024 + 300, 48, 6)
    db[1030:1040] = db[1029]  # ties across a tile's rows
    q[700] = db[1029]
    database = h5_rows(tmp_path, "db", db)
    with threadpool_limits(1):
        alone = exact_search(database, q, 20)
    shapes = []
    real = search_module.inner_products
    monkeypatch.setattr(search_module, "inner_products",
                        lambda a, b, out, scale: (shapes.append(out.shape), real(a, b, out, scale)))
    with threadpool_limits(2):
        assert search_module.search_threads() == 2
        runs = [exact_search(database, q, 20, memory_budget=budget_for(db, q, 20, chunks=c)) for c in (1, 2, 4)]
    assert {m for m, _ in shapes} == {512, 150}  # halves of the 1,024-row tile and of the 300-row last tile
    for found in runs[1:]:
        np.testing.assert_array_equal(found.scores, runs[0].scores)
        np.testing.assert_array_equal(found.indices, runs[0].indices)
    np.testing.assert_array_equal(runs[0].indices, alone.indices)
    np.testing.assert_allclose(runs[0].scores, alone.scores, atol=SCORE_TOLERANCE)
    assert runs[0].indices[700, :11].tolist() == list(range(1029, 1040))


def test_matches_faiss_flat_index_at_pitts250k_database_size():
    import faiss

    db, q = unit(250_000, 16, 3), unit(1000, 16, 4)
    result = exact_search(db, q, 20, memory_budget=budget_for(db, q, 20, chunks=40))
    assert result.info["chunks"] >= 30
    index = faiss.IndexFlatIP(16)
    index.add(db)
    scores, indices = index.search(q, 21)  # the 21st decides whether the 20th is a near-tie
    gaps = np.minimum(np.abs(np.diff(scores, axis=1, prepend=np.inf))[:, :20], np.abs(np.diff(scores, axis=1)))
    scores, indices = scores[:, :20], indices[:, :20]
    # scores on the grid: within half a step of faiss's (and its own float32 rounding)
    np.testing.assert_allclose(result.scores, scores, atol=SCORE_TOLERANCE / 2 + 2e-6)
    # ranks can differ only where two scores are within a step of each other (a tie on the grid)
    apart = gaps > 2 * SCORE_TOLERANCE
    assert apart.mean() > 0.5 and np.array_equal(result.indices[apart], indices[apart])


def test_queries_chunked_at_pitts250k_query_count(tiles_of_1024):
    db, q = unit(10_000, 32, 5), unit(8193, 32, 6)  # Pitts-250k has 8,280 queries; 8 x 1,024 + 1 ends on one
    q[8192] = q[5]
    whole = exact_search(db, q, 5)
    chunked = exact_search(db, q, 5, memory_budget=budget_for(db, q, 5, chunks=10, query_chunks=9))
    assert chunked.info["query_chunks"] == 9 and chunked.info["query_chunk_rows"] == 1024
    np.testing.assert_array_equal(chunked.scores[8192], chunked.scores[5])
    np.testing.assert_array_equal(chunked.indices, whole.indices)
    np.testing.assert_array_equal(chunked.scores, whole.scores)




@pytest.mark.filterwarnings("ignore:TF32 acceleration")  # said by mkldnn.flags() on CPU builds
def test_results_are_the_same_along_every_arithmetic_path(monkeypatch, torch_threads):
    import torch
    from threadpoolctl import threadpool_limits

    import vprbench.search.exact as search_module
    import vprbench.gemm as gemm

    db, q = lattice(3000, 1024, 21, noise=5e-7), lattice(300, 1024, 22)
    db[1024], db[2999], db[1500] = db[700], db[5], db[1023]  # copies at tile edges of copies in tile middles
    q[0], q[1] = np.round(db[700] * 32) / 32, np.round(db[5] * 32) / 32  # the lattice points of those rows
    exact = q.astype(np.float64) @ db.astype(np.float64).T
    assert np.abs(exact * 2**10 - np.round(exact * 2**10)).max() * 2**-10 < 4e-6  # far from a 2^-16 boundary
    expected_scores, expected = ranked((np.round(exact * 2**16) * 2**-16).astype(np.float32), 10)
    assert len(np.unique(expected_scores)) < 0.5 * expected_scores.size  # ties everywhere

    # without the rule: the raw float32 products differ in their last bits between paths (on the x86 CPUs
    # seen; two libraries that happen to agree, e.g. both OpenBLAS, show nothing here, not a failure),
    # and so does the order they give tied rows
    raw_numpy, raw_torch = q @ db.T, torch_products(q, db)
    if not np.array_equal(raw_numpy, raw_torch):
        assert not np.array_equal(ranked(raw_numpy, 10)[1], ranked(raw_torch, 10)[1])
        assert not np.array_equal(ranked(raw_numpy, 10)[1], expected)

    def run(threads=1, product=None, tile=None, chunks=None, onednn=True):
        with (monkeypatch.context() as patch, threadpool_limits(threads),
              torch.backends.mkldnn.flags(enabled=onednn)):  # off: numpy's BLAS
            torch_threads(threads)
            patch.setattr(gemm, "onednn_faster", lambda: True)  # oneDNN on any CPU, when it is on
            if product is not None:
                patch.setattr(search_module, "inner_products", product)
            if tile is not None:
                patch.setattr(search_module, "tile_rows", lambda dim: tile)
            budget = budget_for(db, q, 10, chunks=chunks) if chunks else 10**9
            return exact_search(db, q, 10, memory_budget=budget)

    paths = {"oneDNN, 1 thread": run(), "oneDNN, 2 threads": run(threads=2), "numpy, 1 thread": run(onednn=False),
             "numpy, 2 threads": run(threads=2, onednn=False), "torch, 1 thread": run(product=torch_products),
             "torch, 2 threads": run(threads=2, product=torch_products), "tiles of 64 rows": run(tile=64),
             "tiles of 1,000 rows": run(tile=1000), "3 chunks": run(tile=1024, chunks=3)}
    assert paths["tiles of 64 rows"].info["tile_rows"] == 64 and paths["3 chunks"].info["chunks"] == 3
    for name, result in paths.items():
        assert np.array_equal(result.indices, expected), name
        assert np.array_equal(result.scores, expected_scores), name
    assert expected[0, :2].tolist() == [700, 1024] and expected[1, :2].tolist() == [5, 2999]


def test_float16_rows_are_computed_in_float32(tmp_path):
    db, q = unit(3000, 24, 7).astype(np.float16), unit(50, 24, 8)
    half = exact_search(h5_rows(tmp_path, "db16", db), q, 10)
    widened = exact_search(db.astype(np.float32), q, 10)
    np.testing.assert_array_equal(half.indices, widened.indices)
    np.testing.assert_array_equal(half.scores, widened.scores)


def test_search_keeps_its_tuple_form():
    db = np.eye(4, dtype=np.float32)
    scores, idx = search(db, np.array([[0.1, 0.9, 0.3, 0.0]], dtype=np.float32), 3)
    assert idx.tolist() == [[1, 2, 0]] and idx.dtype == np.int64
    np.testing.assert_allclose(scores, [[0.9, 0.3, 0.1]], rtol=0, atol=SCORE_TOLERANCE / 2)
    assert np.all(scores * 2**16 == np.round(scores * 2**16))  # on the grid


def test_budget_too_small_names_what_it_must_hold_and_the_option():
    db, q = unit(5000, 128, 9), unit(3000, 128, 10)
    # candidates 1.3 MB, two database tiles 4.2 MB, a query tile 1.5 MB, a score tile, a trimmed
    # copy and the products written into it 3 x 49.2 MB
    with pytest.raises(VPRBenchError, match=r"memory budget of 1\.0 MB is too small for this search: it must hold "
                                             r"the top-36 candidates of 3,000 queries \(1\.3 MB\) plus a tile of 3000 "
                                             r"query rows, two tiles of 4096 database rows of 128 dims.*"
                                             r"154\.5 MB in all\. Raise --search-memory \(memory_budget\) to at least "
                                             r"160\.0 MB"):
        exact_search(db, q, 20, memory_budget="1MB")
    with pytest.raises(VPRBenchError, match="K = 6000 must be between 1 and the 5000 database rows"):
        exact_search(db, q, 6000)
    with pytest.raises(VPRBenchError, match="Database descriptors have 128 dims, queries 3"):
        exact_search(db, np.zeros((2, 3), np.float32), 1)
    with pytest.raises(VPRBenchError, match="lacks row_count, dim, dtype, folder, read_rows, read_rows_at"):
        exact_search([[1.0]], q, 1)


@pytest.mark.parametrize("text, value", [("1GB", 10**9), ("512MiB", 2**29), ("2.5 gb", 2_500_000_000), (4096, 4096)])
def test_memory_sizes(text, value):
    assert parse_memory(text) == value


def test_the_budget_a_refusal_names_is_one_the_search_runs_in():
    """The least budget was named rounded to one decimal, often below it (29.9 MB for 29,902,716
    bytes): a run given it was refused again."""
    import re

    db, q = unit(3000, 64, 11), unit(777, 64, 12)
    with pytest.raises(VPRBenchError, match="too small for this search") as refused:
        exact_search(db, q, 5, memory_budget="1MB")
    named = re.search(r"to at least ([0-9.]+ [kMG]B)\.", str(refused.value)).group(1)
    assert exact_search(db, q, 5, memory_budget=named.replace(" ", "")).indices.shape == (777, 5)


def test_the_candidates_ordered_and_ties_searched_again_stay_within_the_budget(tiles_of_1024):
    """Ordering the candidates and searching tied queries again held memory beyond the budget
    (3.5 times the least budget here): the merged candidates, every sorting copy of them and a
    second search given the whole budget beside the first one's answers."""
    from traced import peak_of

    from vprbench.search.exact import least_budget

    db, q = lattice(10_000, 32, 1), lattice(2_000, 32, 2)  # most queries tie at their 500th row
    whole = exact_search(db, q, 500, memory_budget=10**9)
    assert whole.info["queries_searched_again_for_ties"] > 1_000
    least = least_budget(ArrayRows(db), len(q), 500)
    for budget in (least, 2 * least):
        result, peak = peak_of(lambda: exact_search(db, q, 500, memory_budget=budget))
        assert peak <= budget, (peak, budget)
        np.testing.assert_array_equal(result.indices, whole.indices)
        np.testing.assert_array_equal(result.scores, whole.scores)
