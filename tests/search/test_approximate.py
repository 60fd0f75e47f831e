"""Approximate indexes (IVF-PQ, HNSW): their measured recall loss and the options refused."""
import functools
import json

import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.search.exact import exact_search
from vprbench.evaluation.retrieve import retrieve
from vprbench.row_sources import ArrayRows, parse_memory
from search_rows import h5_rows


def clustered(n, d, seed):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(200, d))
    x = centres[rng.integers(0, 200, n)] + 0.7 * rng.normal(size=(n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def near_copies(db, n, seed):
    rng = np.random.default_rng(seed)
    q = db[rng.choice(len(db), n, replace=False)] + 0.05 * rng.normal(size=(n, db.shape[1])).astype(np.float32)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.mark.parametrize("kind, n", [("ivf-pq", 12_000), ("hnsw", 4000)])
def test_approximate_index_reports_its_measured_recall_loss(tmp_path, kind, n):
    db = clustered(n, 32, 18)
    q = near_copies(db, 300, 19)
    database = h5_rows(tmp_path, "db", db)
    result = retrieve(None, database, q, 10, index=kind)
    info = result.info
    json.dumps(info)
    assert info["index"] == kind and info["options"]["shortlist"] == 100 and info["exact_fallback_queries"] == 0
    loss = info["recall_loss"]
    assert loss["queries"] == 200 and loss["seed"] == 0 and loss["k"] == 10
    # the reported figures are what a check against exact search gives
    sample = np.sort(np.random.default_rng(0).choice(300, 200, replace=False))
    exact = exact_search(db, q[sample], 10).indices
    assert loss["r1_agreement"] == pytest.approx(np.mean(result.indices[sample, 0] == exact[:, 0]))
    overlap = np.mean([len(np.intersect1d(a, e)) / 10 for a, e in zip(result.indices[sample], exact)])
    assert loss["topk_overlap"] == pytest.approx(overlap)
    assert loss["r1_agreement"] >= 0.95 and loss["topk_overlap"] >= 0.9
    # shortlists are re-scored exactly: the scores are true inner products, best first
    true = np.einsum("qd,qkd->qk", q, db[result.indices])
    np.testing.assert_allclose(result.scores, true, atol=1e-5)
    assert np.all(np.diff(result.scores, axis=1) <= 0)
    if kind == "ivf-pq":
        assert info["options"]["nlist"] == 128 and info["options"]["train_rows"] == 9984  # 39 x 256 PQ centroids
        assert max(database.reads) <= 12_000


def test_approximate_options_unsuited_to_the_database_are_refused():
    db, q = clustered(5000, 32, 20), clustered(10, 32, 21)
    with pytest.raises(VPRBenchError, match=r"index='ivf-pq' needs at least 9,984 database rows to train .* "
                                             r"this database has 5,000: use index='exact'"):
        retrieve(None, db, q, 5, index="ivf-pq")
    with pytest.raises(VPRBenchError, match="shortlist of 4 is smaller than K = 5: .*at least 5"):
        retrieve(None, db, q, 5, index="hnsw", index_options={"shortlist": 4})
    with pytest.raises(VPRBenchError, match="ef_search = 50 is smaller than the shortlist \\(100\\)"):
        retrieve(None, db, q, 5, index="hnsw", index_options={"ef_search": 50})
    with pytest.raises(VPRBenchError, match="does not take nprobe"):
        retrieve(None, db, q, 5, index="hnsw", index_options={"nprobe": 3})
    with pytest.raises(VPRBenchError, match="too small for index='hnsw' on 5,000 rows"):
        retrieve(None, db, q, 5, index="hnsw", memory_budget="1MB")
    with pytest.raises(VPRBenchError, match="Unknown index 'annoy': use one of exact, ivf-pq, hnsw"):
        retrieve(None, db, q, 5, index="annoy")
    with pytest.raises(VPRBenchError, match=r"index='exact' takes no index options, got \['nprobe'\]: drop them, or "
                                             r"choose an approximate index \(index='ivf-pq' or 'hnsw'\)"):
        retrieve(None, db, q, 5, index_options={"nprobe": 3})


def test_nprobe_beyond_the_lists_is_refused_not_lowered_in_silence():
    """Before: nprobe=64 on 32 lists ran as nprobe=32 under a spec naming 64 (a second name for one run)."""
    from vprbench.search.approximate import index_options

    assert index_options("ivf-pq", 20_000, 64, 5, {"nlist": 32})["nprobe"] == 32  # the default, within the lists
    assert index_options("ivf-pq", 20_000, 64, 5, {"nlist": 32, "nprobe": 8})["nprobe"] == 8
    with pytest.raises(VPRBenchError, match=r"^nprobe = 64 exceeds the index's 32 lists \(nlist\): give nprobe <= 32\.$"):
        index_options("ivf-pq", 20_000, 64, 5, {"nlist": 32, "nprobe": 64})


def test_the_index_searches_with_the_nprobe_and_ef_search_it_records():
    """What a record says the index probed is what faiss was told: nprobe lists, efSearch candidates."""
    from vprbench.search.approximate import _build, index_options
    from vprbench.row_sources import ArrayRows

    db = clustered(10_000, 16, 3)
    o = index_options("ivf-pq", len(db), 16, 5, {"nlist": 16, "nprobe": 5, "pq_m": 4})
    index, _, _ = _build("ivf-pq", ArrayRows(db), o)
    assert o["nprobe"] == 5 and index.nprobe == 5
    o = index_options("hnsw", 2000, 16, 5, {"ef_search": 77, "shortlist": 50})
    index, _, _ = _build("hnsw", ArrayRows(db[:2000]), o)
    assert o["ef_search"] == 77 and index.hnsw.efSearch == 77


def test_a_short_shortlist_is_searched_exactly_whatever_k_is(tmp_path, monkeypatch):
    """A query whose index answers fewer rows than the shortlist falls back to exact search at every K:
    `--k 1` and `--k 1 5` are one leaderboard row, so their top-1 must agree."""
    import vprbench.search.approximate as approximate

    db, q = clustered(4000, 16, 30), clustered(40, 16, 31)
    built = approximate._build

    def short_answers(kind, database, o):
        index, *rest = built(kind, database, o)

        class Short:  # every other query gets 3 arbitrary rows, padded with -1 as faiss pads
            def search(self, block, shortlist):
                scores, found = index.search(block, shortlist)
                found[::2, :3], found[::2, 3:] = np.arange(3), -1
                return scores, found
        return Short(), *rest

    monkeypatch.setattr(approximate, "_build", short_answers)
    exact = exact_search(db, q, 5)
    one, five = (retrieve(None, h5_rows(tmp_path, f"db{k}", db), q, k, index="hnsw") for k in (1, 5))
    assert one.info["exact_fallback_queries"] == five.info["exact_fallback_queries"] == 20
    np.testing.assert_array_equal(one.indices[:, 0], five.indices[:, 0])
    np.testing.assert_array_equal(one.indices[::2, 0], exact.indices[::2, 0])
    np.testing.assert_array_equal(five.indices[::2], exact.indices[::2])


@pytest.mark.parametrize("kind", ["hnsw", "ivf-pq"])
def test_an_approximate_search_at_a_tight_budget_holds_one_chunk_of_rows(kind):
    """tracemalloc's peak (numpy's arrays: faiss's index is counted apart, as index_bytes) within the
    budget less the index. Each loop held its last chunk while it read the next: twice the rows budgeted
    (ivf-pq on 100,000 x 256 at 25.8 MB: 34.7 MB of rows + the index)."""
    from traced import peak_of

    from vprbench.search.approximate import _index_bytes, add_rows, approximate_search, index_options
    from vprbench.search.exact import ArrayRows

    n, q, d, k = 70000, 300, 64, 5
    db = clustered(n, d, 0)
    o = index_options(kind, n, d, k, None)
    index_bytes = _index_bytes(kind, n, d, o)
    residual = 4 * d if kind == "ivf-pq" else 0
    # what the index asks (its training sample, or the rows it adds at a time), and the 12 MB its exact
    # recall check asks at this size
    rows = max(o["train_rows"], min(n, add_rows(kind, ArrayRows(db)))) * (4 * d + residual)
    budget = rows + index_bytes + q * k * 12 + 4 * d + o["shortlist"] * (4 * d + 12) + 12_100_000
    import faiss  # noqa: F401  (their imports, 4 MB and more, are no part of a search's memory)
    import vprbench.gemm  # noqa: F401
    queries = ArrayRows(near_copies(db, q, 1))
    found, peak = peak_of(lambda: approximate_search(ArrayRows(db), queries, k, kind=kind, memory_budget=budget))
    assert peak < 1.05 * (budget - index_bytes), (peak, budget - index_bytes)
    # faiss's own copy, untraced: IVF-PQ adds a chunk with the float32 residual of each row (VmHWM: 18.8 MB
    # to add 17.2 MB), so its chunks leave room for that
    assert found.info["chunk_rows"] * (4 * d + residual) <= budget - index_bytes


def test_the_exact_searches_beside_the_answers_fit_the_budget_or_are_refused_before_the_build(monkeypatch):
    """Queries searched exactly (the recall check, short shortlists) run beside the answers kept, within the
    budget: one too small for them is refused before the index is built, naming the budget they need (it
    took the whole budget again after the build, and refused it only then), and that budget is enough."""
    import re

    from traced import peak_of

    import vprbench.search.approximate as approximate
    from vprbench.search.exact import ArrayRows

    db, queries = ArrayRows(clustered(3000, 256, 0)), ArrayRows(clustered(300, 256, 1))
    search = functools.partial(approximate.approximate_search, db, queries, 5, kind="hnsw")
    search(memory_budget=1 << 30)  # faiss's and the products' first-call memory is no part of a search's
    built = approximate._build
    monkeypatch.setattr(approximate, "_build", lambda *args: pytest.fail("the index was built"))
    with pytest.raises(VPRBenchError, match=r"the exact search of 200 queries that checks its recall, beside the "
                                            r"answers, 13\.\d MB\. Raise --search-memory") as refused:
        search(memory_budget=8_000_000)
    need = parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1))
    monkeypatch.setattr(approximate, "_build", built)
    found, peak = peak_of(lambda: search(memory_budget=need))
    index_bytes = found.info["index_bytes"]
    assert peak <= need - index_bytes, (peak, need - index_bytes)  # faiss's index is untraced
    assert found.info["recall_loss"]["queries"] == 200


def test_an_hnsw_search_is_the_same_at_every_budget_it_runs_at():
    """HNSW inserts each batch of added rows by level, so another batching builds another graph: rows were
    added as many at a time as the budget held, and a tight budget (20,000 x 128 at the 5.3 MB it named)
    gave other shortlists (95 % of the top-10 of 300 queries changed). Now they are
    added a fixed number at a time, and the least budget named holds that many."""
    import re

    from vprbench.search.approximate import approximate_search
    from vprbench.search.exact import ArrayRows

    db, queries = ArrayRows(clustered(20_000, 128, 5)), ArrayRows(clustered(300, 128, 6))
    options = {"hnsw_m": 4, "ef_construction": 8, "ef_search": 20, "shortlist": 20, "train_rows": 1000,
               "recall_queries": 20}
    search = functools.partial(approximate_search, db, queries, 10, kind="hnsw", options=options)
    roomy = search(memory_budget=1 << 30)
    with pytest.raises(VPRBenchError, match="Raise --search-memory") as refused:
        search(memory_budget=1_000_000)
    tight = search(memory_budget=parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1)))
    np.testing.assert_array_equal(tight.indices, roomy.indices)
    np.testing.assert_array_equal(tight.scores, roomy.scores)
    assert tight.info["recall_loss"] == roomy.info["recall_loss"]


def ivf_pq_on_ties():
    """An IVF-PQ search (nprobe 1) of 600 queries each on the plane halfway between two lists' centroids:
    which list a query probes is a tie, settled by the last bits of its products with them."""
    import faiss

    from vprbench.search.approximate import _build, approximate_search, index_options
    from vprbench.search.exact import ArrayRows

    rows = clustered(6000, 512, 7)
    db = ArrayRows(np.concatenate([rows, rows[::-1]]))  # every row twice: ties the order settles
    # 16 codes a row: faiss trains the default 64 (8-dim sub-quantizers) ten times slower on fewer than about
    # 16,000 training rows (here 9,984); the lists are the same
    options = {"nprobe": 1, "recall_queries": 20, "pq_m": 16}
    index = _build("ivf-pq", db, index_options("ivf-pq", 12_000, 512, 10, options))[0]
    centroids = faiss.extract_index_ivf(index).quantizer.reconstruct_n(0, 128).astype(np.float64)
    rng = np.random.default_rng(8)
    a, b = rng.integers(0, 128, 600), rng.integers(0, 128, 600)
    a[a == b] = (b[a == b] + 1) % 128
    apart, middle = centroids[a] - centroids[b], (centroids[a] + centroids[b]) / 2
    queries = middle - (np.sum(middle * apart, 1) / np.sum(apart * apart, 1))[:, None] * apart
    return functools.partial(approximate_search, db, ArrayRows(queries.astype(np.float32)), 10, kind="ivf-pq",
                             options=options)


def test_an_ivf_pq_search_is_the_same_at_every_budget_it_runs_at():
    """The budget set how many queries faiss searched at once, and faiss picks its kernel by that count
    (BLAS for a large batch, its own loops for a small one): they round a query's products with the lists'
    centroids differently, so a query halfway between two lists probed one at one budget and the other at
    another: on one thread, of 600 such queries searched at once, 24 got other top-10s when searched 294 + 294
    + 12 at a time, and 185 when 237 at a time. Now faiss searches a fixed tile of queries at a time,
    whatever the budget."""
    import re

    search = ivf_pq_on_ties()
    with pytest.raises(VPRBenchError, match="Raise --search-memory") as refused:
        search(memory_budget=1_000_000)
    least = parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1))
    whole = search(memory_budget=1 << 30)
    assert whole.info["query_chunks"] == 1
    per_query = 512 * 4 + 100 * (512 * 4 + 12)  # a query's row and its shortlist's rows and answers
    # the fewest queries the least budget holds, and more (before: 294 + 294 + 12 at once, and 237)
    runs = [search(memory_budget=budget) for budget in (least + 57 * per_query, least)]
    assert len({run.info["query_chunk_rows"] for run in [whole, *runs]}) == 3
    assert all(run.info["query_chunks"] > 1 for run in runs)
    for run in runs:
        assert run.info["chunk_rows"] == whole.info["chunk_rows"]  # the index built the same way
        np.testing.assert_array_equal(run.indices, whole.indices)
        np.testing.assert_array_equal(run.scores, whole.scores)


def test_a_budget_too_small_for_a_tile_of_shortlists_reads_them_a_few_queries_at_a_time():
    """Under a budget that holds the shortlist rows of fewer queries than faiss searches at once, the
    index still searches whole tiles, and the rows are read for a few of their queries at a time."""
    import re

    from vprbench.search.approximate import QUERY_TILE, approximate_search
    from vprbench.search.exact import ArrayRows

    db, queries = ArrayRows(clustered(3000, 64, 9)), ArrayRows(clustered(150, 64, 10))
    options = {"shortlist": 1000, "ef_search": 1000, "recall_queries": 5}
    search = functools.partial(approximate_search, db, queries, 10, kind="hnsw", options=options)
    with pytest.raises(VPRBenchError, match="Raise --search-memory") as refused:
        search(memory_budget=1_000_000)
    least = parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1))
    tight, whole = search(memory_budget=least), search(memory_budget=1 << 30)
    assert tight.info["query_chunk_rows"] == QUERY_TILE and whole.info["query_chunks"] == 1
    assert (least - tight.info["index_bytes"]) // (1000 * 64 * 4) < QUERY_TILE  # rows of fewer queries than a tile
    np.testing.assert_array_equal(tight.indices, whole.indices)
    np.testing.assert_array_equal(tight.scores, whole.scores)


def on_one_and_two_threads(search) -> list:
    """`search` (an approximate search of fixed rows) run with faiss's and the BLAS's threads at 1, then 2."""
    import faiss
    from threadpoolctl import threadpool_limits

    threads, runs = faiss.omp_get_max_threads(), []
    try:
        for count in (1, 2):
            faiss.omp_set_num_threads(count)
            with threadpool_limits(count, user_api="blas"):
                runs.append(search(memory_budget=1 << 30))
    finally:
        faiss.omp_set_num_threads(threads)
    return runs


def test_an_ivf_pq_search_is_the_same_on_every_thread_count():
    """faiss's IVF search cut each tile of queries among its threads before it picked its kernel for the
    lists' centroids by a slice's size: at 2,048 dims, of 600 queries on ties between two lists, 277 got other
    shortlists on two threads than on one (BLAS for the 64 queries of a tile, faiss's own loops for a thread's
    32; from 2,000 dims on at faiss's threshold of 128,000). Here the threshold is lowered to show it at 512
    dims. Now the lists are picked in one product per tile on a thread of its own, whatever the thread count."""
    import faiss

    threshold = faiss.cvar.distance_compute_blas_threshold
    faiss.cvar.distance_compute_blas_threshold = 64 * 512  # as at 2,048 dims: a tile on BLAS, a thread's half not
    try:
        runs = on_one_and_two_threads(ivf_pq_on_ties())
    finally:
        faiss.cvar.distance_compute_blas_threshold = threshold
    np.testing.assert_array_equal(runs[1].indices, runs[0].indices)
    np.testing.assert_array_equal(runs[1].scores, runs[0].scores)
    assert runs[1].info["recall_loss"] == runs[0].info["recall_loss"]


def test_a_shortlist_is_rescored_the_same_on_every_thread_count(monkeypatch):
    """The shortlist's exact scores are products of long rows (8,192 dims here): a BLAS on several threads
    cut their sums by its thread count, 4 % of the scores a rounding apart at 1 and 2 or 3 threads (and a
    grid step where one lay on a boundary). Now they are computed on one BLAS thread, the rows read before."""
    from threadpoolctl import threadpool_limits

    import vprbench.search.approximate as approximate

    rng = np.random.default_rng(3)
    database = rng.standard_normal((600, 8192), dtype=np.float32)
    database /= np.linalg.norm(database, axis=1, keepdims=True)
    queries = database[:40] + 0.02 * rng.standard_normal((40, 8192), dtype=np.float32)
    raw, runs = [], []
    real = approximate.rounded_scores
    monkeypatch.setattr(approximate, "rounded_scores", lambda scores: raw[-1].append(scores.copy()) or real(scores))
    for count in (1, 3):
        raw.append([])
        with threadpool_limits(count, user_api="blas"):
            runs.append(approximate.approximate_search(ArrayRows(database), ArrayRows(queries), 10, kind="hnsw",
                                                       memory_budget=1 << 30, options={"recall_queries": 1}))
    assert len(raw[0]) == len(raw[1]) == 40
    for one, more in zip(*raw):
        np.testing.assert_array_equal(more, one)
    np.testing.assert_array_equal(runs[1].indices, runs[0].indices)
    np.testing.assert_array_equal(runs[1].scores, runs[0].scores)


def test_queries_searched_exactly_are_the_same_on_every_thread_count(monkeypatch):
    """A query whose shortlist comes back short, and the recall check's, are searched exactly, which computed
    with the BLAS's threads: its small query tiles here are one product each, cut by a BLAS on two threads
    (OpenBLAS's AVX2 kernels round by a part's shape: 2 of these 600 queries got other top-10s on two threads
    than on one). A BLAS whose products' last bits follow its thread count is stood in for, so this shows on
    any CPU; those queries are now searched on one thread, as the shortlists are re-scored."""

    import vprbench.search.exact as search_module

    def by_threads(queries, rows, out, scale):  # other last bits on more threads, magnified to show on the grid
        np.multiply(queries @ rows.T, scale * np.float32(1 + (search_module.search_threads() - 1) * 2**-16), out=out)

    monkeypatch.setattr(search_module, "inner_products", by_threads)
    runs = on_one_and_two_threads(ivf_pq_on_ties())
    assert runs[0].info["exact_fallback_queries"] > 300  # 355 or 356: the index is trained on the BLAS too
    np.testing.assert_array_equal(runs[1].scores, runs[0].scores)
    np.testing.assert_array_equal(runs[1].indices, runs[0].indices)
    assert runs[1].info["recall_loss"] == runs[0].info["recall_loss"]
