"""SeqSLAM and the descriptor-sequence score: against plain loops over their definitions,
blocks against one block, traverse orders, and memory within the budget."""
import re
from fractions import Fraction

import numpy as np
import pytest

from traced import peak_of
from vprbench.errors import VPRBenchError
from vprbench.row_sources import parse_memory
from vprbench.stages.sequence.matching import (enhance, query_offsets, second_best, top_k, trajectories,
                                               trajectory_costs, velocities)
from vprbench.stages.sequence.search import sequence_search

TOLERANCE = 1e-4  # float32 sums of a few terms, and BLAS products, on any CPU


def traverse(n_places=120, dim=32, noise=0.9, seed=0):
    """Two traverses of one route: smoothly changing unit descriptors, the query traverse's noisy."""
    rng = np.random.default_rng(seed)
    route = np.cumsum(rng.standard_normal((n_places, dim)), axis=0)
    route += 3 * rng.standard_normal((n_places, dim))
    database = route / np.linalg.norm(route, axis=1, keepdims=True)
    queries = route + noise * np.linalg.norm(route, axis=1, keepdims=True) / np.sqrt(dim) * rng.standard_normal(route.shape)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    return database.astype(np.float32), queries.astype(np.float32)


def named_budget(error) -> int:
    """The least budget a refusal names ("to at least 75.0 MB"), in bytes."""
    return parse_memory(re.search(r"to at least ([0-9.]+ [kMG]B)", str(error)).group(1).replace(" ", ""))


def naive_enhance(d, window):
    out = np.empty_like(d, dtype=np.float64)
    for i in range(d.shape[0]):
        for j in range(d.shape[1]):
            part = d[i, max(0, j - window // 2):j + window // 2 + 1].astype(np.float64)
            out[i, j] = (d[i, j] - part.mean()) / max(part.std(ddof=1), 1e-6)
    return out


def naive_costs(c, offsets, paths):
    q, n = c.shape
    out = np.full((q, n), np.inf)
    for t in range(q):
        for d in range(n):
            for path in paths:
                terms = [c[t + k, d + o] for k, o in zip(offsets, path) if 0 <= t + k < q and 0 <= d + o < n]
                out[t, d] = min(out[t, d], np.mean(terms))
    return out


def test_windows_offline_centred_and_causal_past_only():
    assert query_offsets(3, "offline").tolist() == [-1, 0, 1]
    assert query_offsets(10, "offline").tolist() == list(range(-4, 6))
    assert query_offsets(5, "causal").tolist() == [-4, -3, -2, -1, 0]
    assert query_offsets(1, "causal").tolist() == [0]
    with pytest.raises(ValueError):
        query_offsets(3, "future")


def test_velocities_and_trajectories_are_exact():
    speeds = velocities(0.8, 1.2, 0.1)
    assert speeds == [Fraction(8, 10), Fraction(9, 10), Fraction(1), Fraction(11, 10), Fraction(12, 10)]
    paths = trajectories(query_offsets(5, "offline"), speeds)
    # -2..2 at 0.8..1.2 (e.g. 0.8 x -2 = -1.6 -> -2): one distinct path
    assert paths.tolist() == [[-2, -1, 0, 1, 2]]
    paths = trajectories(query_offsets(10, "causal"), speeds)
    assert paths[:, -1].tolist() == [0] * len(paths)  # the query is always matched with d itself
    assert paths[-1].tolist() == [-7, -6, -6, -5, -4, -3, -2, -2, -1, 0]  # v = 0.8: -7.2, -6.4, -5.6, -4.8...
    assert len(paths) == 5


def test_enhancement_matches_its_definition():
    d = np.random.default_rng(1).random((4, 23)).astype(np.float32)
    for columns in (23, 11, 7, 2):  # windows cut at both ends, and rows shorter than a window
        np.testing.assert_allclose(enhance(d[:, :columns], 10), naive_enhance(d[:, :columns], 10), atol=TOLERANCE)
    assert enhance(d[:, :1], 10).tolist() == [[0.0]] * 4  # one database image: no contrast, not NaN
    flat = np.ones((1, 12), dtype=np.float32)
    assert np.isfinite(enhance(flat, 10)).all() and np.abs(enhance(flat, 10)).max() == 0


def test_trajectory_costs_match_plain_loops_in_blocks():
    rng = np.random.default_rng(2)
    c = rng.random((17, 19)).astype(np.float32)
    for length, mode in ((4, "offline"), (5, "causal"), (1, "offline")):
        offsets = query_offsets(length, mode)
        paths = trajectories(offsets, velocities(0.8, 1.2, 0.1))
        expected = naive_costs(c, offsets, paths)
        for start, stop in ((0, 17), (0, 6), (6, 11), (11, 17)):
            first, last = max(0, start + offsets[0]), min(17, stop + offsets[-1])
            got = trajectory_costs(c[first:last], first, start, stop, 17, offsets, paths)
            np.testing.assert_allclose(got, expected[start:stop], atol=TOLERANCE)


def test_top_k_ties_go_to_the_lower_index_and_second_best_skips_the_window():
    costs = np.array([[3, 1, 2, 1, 0, 1, 5]], dtype=np.float32)
    indices, values = top_k(costs, 3)
    assert indices.tolist() == [[4, 1, 3]] and values.tolist() == [[0, 1, 1]]
    assert second_best(costs, np.array([4]), 2).tolist() == [1.0]  # 3..5 skipped: index 1
    assert second_best(costs, np.array([4]), 20).tolist() == [np.inf]


@pytest.mark.parametrize("score", ["seqslam", "diagonal"])
def test_sequences_beat_single_frames_on_a_noisy_traverse(score):
    database, queries = traverse()
    single = np.argmax(queries @ database.T, axis=1)
    truth = np.arange(len(queries))
    alone = np.mean(np.abs(single - truth) <= 1)
    found = sequence_search(database, queries, 5, score=score, length=10, mode="offline")
    matched = np.mean(np.abs(found.indices[:, 0] - truth) <= 1)
    assert alone < 0.7 and matched > alone + 0.2, (alone, matched)
    assert found.indices.shape == (120, 5) and found.scores.dtype == np.float32
    assert (np.diff(found.scores, axis=1) <= 0).all()  # best first
    causal = sequence_search(database, queries, 5, score=score, length=10, mode="causal")
    assert causal.info["mode"] == "causal" and causal.info["query_offsets"] == [-9, 0]
    assert not np.array_equal(causal.indices, found.indices)


def test_seqslam_top1_score_is_minus_openseqslams_quality_ratio():
    database, queries = traverse(60)
    found = sequence_search(database, queries, 60, score="seqslam", length=5)
    # the whole ranking is returned (k = N): recompute the ratio from the returned scores' order
    m = found.info["enhanced_minimum"]
    assert m < 0  # enhanced differences are z-scores
    top = found.scores[:, 0]
    assert (top <= 0).all() and (top >= -1).all()  # cost over the second-best outside the window


def test_blocks_and_orders_do_not_change_results():
    database, queries = traverse(90, dim=16)
    whole = sequence_search(database, queries, 4, length=6, memory_budget="1GB")
    blocked = sequence_search(database, queries, 4, length=6, memory_budget=200_000)
    assert whole.info["blocks"] == 1 and blocked.info["blocks"] >= 5
    np.testing.assert_array_equal(whole.indices, blocked.indices)
    np.testing.assert_allclose(whole.scores, blocked.scores, atol=TOLERANCE)
    # the same traverses stored shuffled, with their orders: the same matches, as stored
    rng = np.random.default_rng(3)
    db_perm, q_perm = rng.permutation(90), rng.permutation(90)
    shuffled = sequence_search(database[db_perm], queries[q_perm], 4, length=6,
                               database_order=np.argsort(db_perm), query_order=np.argsort(q_perm))
    np.testing.assert_array_equal(db_perm[shuffled.indices], whole.indices[q_perm])


def test_memory_stays_within_the_budget_never_the_whole_matrix():
    database, queries = traverse(2000, dim=8)
    budget = 8_000_000  # the whole 2,000 x 2,000 matrix and its temporaries would need ~200 MB
    found, peak = peak_of(lambda: sequence_search(database, queries, 5, length=10, memory_budget=budget))
    assert found.info["blocks"] > 10
    assert peak < budget, peak


def test_too_small_a_budget_and_bad_orders_are_refused():
    database, queries = traverse(50, dim=8)
    with pytest.raises(VPRBenchError, match="too small for sequence matching.*Raise --search-memory"):
        sequence_search(database, queries, 1, memory_budget=10_000)
    with pytest.raises(VPRBenchError, match="query traverse order must name each of its 50"):
        sequence_search(database, queries, 1, query_order=np.zeros(50, dtype=int))


def test_mean_absolute_difference_compare():
    rng = np.random.default_rng(4)
    database = rng.standard_normal((40, 24)).astype(np.float32)
    queries = database + 0.1 * rng.standard_normal(database.shape).astype(np.float32)
    found = sequence_search(database, queries, 3, score="diagonal", compare="mean-absolute-difference", length=1)
    mad = np.abs(queries[:, None, :] - database[None, :, :]).mean(axis=2)
    np.testing.assert_array_equal(found.indices[:, 0], mad.argmin(axis=1))
    np.testing.assert_allclose(found.scores[:, 0], -mad.min(axis=1), atol=TOLERANCE)


def test_a_stages_costs_are_ranked_on_the_grid_ties_to_the_lower_database_index():
    """Before: costs were ranked as computed and ties went to the lower traverse position, so a
    last-bit difference between two CPUs' products could swap two near-equal candidates."""
    from vprbench.stages.registry import create_stage

    rng = np.random.default_rng(3)
    a, b = rng.standard_normal(16), rng.standard_normal(16)
    near = a + 1e-3 * b  # cosine with `a` about 1 - 5e-7: below the grid's 2^-16, above float32's last bit
    rows = np.stack([rng.standard_normal(16), near, a, rng.standard_normal(16)])
    database = (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)
    queries = database[[2, 2, 2]]
    order = np.array([3, 2, 1, 0])  # captured in reverse: traverse positions differ from indices
    raw = sequence_search(database, queries, 2, score="diagonal", length=1, database_order=order, query_order=np.arange(3))
    assert raw.indices[:, 0].tolist() == [2, 2, 2]  # the nearer by its last bits
    found = sequence_search(database, queries, 2, score="diagonal", length=1, database_order=order,
                            query_order=np.arange(3), grid=True)
    assert found.indices.tolist() == [[1, 2]] * 3 and found.info["tie_order"].startswith("cost rounded to 2^-16")
    assert create_stage("diagonal", {}).fingerprint()["version"] == 3  # 3: products on one thread each


def test_second_best_skips_both_ends_of_the_window():
    # best at 2, window 2: columns 1..3 skipped, so the cheap neighbours 1 and 3 are never the second best
    costs = np.array([[5, 1, 0, 2, 6, 7]], dtype=np.float32)
    assert second_best(costs, np.array([2]), 2).tolist() == [5.0]
    assert second_best(costs, np.array([2]), 4).tolist() == [7.0]  # 0..4 skipped
    assert second_best(costs, np.array([2]), 1).tolist() == [1.0]  # window 1: only the best itself


def test_a_tight_budget_holds_one_database_chunk_and_the_query_rows(monkeypatch):
    """High-dimensional rows and few database images: each block's query rows (read, then put in
    traverse order) went uncounted, and each database chunk was held while the next was read (1.9 x
    the budget at 1,000 x 16,384)."""
    from vprbench.stages.sequence import search

    monkeypatch.setattr(search, "READ_BYTES", 4 * 2**20)  # several chunks of this small database
    database, queries = traverse(600, dim=8192)
    queries = queries[:200]
    n, dim, span = len(database), database.shape[1], len(query_offsets(10, "offline")) - 1
    row = search.BYTES_PER_CELL * n + 8 * dim
    tile = search.PRODUCT_ROWS * (2 * dim + 2 * 128) * 4  # two part tiles' zero rows, a tile's products (128 rows a chunk)
    budget = 4 * 2**20 + tile + 200 * (12 * 5 + 128) + span * (4 * n + 8 * dim) + 10 * row
    found, peak = peak_of(lambda: sequence_search(database, queries, 5, length=10, memory_budget=budget))
    assert peak < budget, (peak, budget)
    assert found.info["blocks"] == 20  # ten query rows a block, as the budget was made for


def test_many_queries_top_k_are_held_within_the_budget_or_refused_naming_one_that_holds_them():
    """Many queries, a deep K and a small database: every query's top K (and, at the end, the results
    put in query order beside them) went uncounted beside blocks sized to the whole budget (3.6 x a
    20 MB budget at 20,000 queries x K = 100)."""
    database, _ = traverse(300, dim=8)
    queries = np.tile(traverse(300, dim=8)[1], (67, 1))[:20_000]
    sequence_search(database, queries[:300], 100, score="diagonal", length=1)  # a warm-up, as below
    with pytest.raises(VPRBenchError, match="top 100 of 20,000 queries") as refused:
        sequence_search(database, queries, 100, score="diagonal", length=1, memory_budget=20_000_000)
    named = named_budget(refused.value)
    found, peak = peak_of(lambda: sequence_search(database, queries, 100, score="diagonal", length=1,
                                                  memory_budget=named))
    assert found.indices.shape == (20_000, 100) and peak < named, (peak, named)


def test_post_processed_rows_are_read_within_the_budget_or_refused_naming_one_that_holds_them():
    """A stage's rows post-processed as the search's (PCA-whitening, transformed a tile at a time as
    they are read): the transform's tile, its float64 copies and a block of the projection went
    uncounted beside blocks sized to the whole budget (1.2 x a 60 MB budget at 4,096 -> 256 dims)."""
    from vprbench.aggregation.pca import PCAWhitening
    from vprbench.evaluation.postprocess import TransformedRows
    from vprbench.row_sources import ArrayRows

    rng = np.random.default_rng(5)
    # 100 queries: each block of them reads (and transforms) the whole database again; a block's memory is
    # the same as at 1,000 queries
    database, queries = (rng.standard_normal((rows, 4096)).astype(np.float32) for rows in (1000, 100))
    pca = PCAWhitening(256).fit(database, "2GB")
    database, queries = TransformedRows(ArrayRows(database), pca), TransformedRows(ArrayRows(queries), pca)
    sequence_search(database, queries, 5, length=3)  # a warm-up: nothing first-time in the traced calls
    with pytest.raises(VPRBenchError, match="too small for sequence matching") as refused:
        sequence_search(database, queries, 5, length=10, memory_budget=60_000_000)
    named = named_budget(refused.value)
    found, peak = peak_of(lambda: sequence_search(database, queries, 5, length=10, memory_budget=named))
    assert found.indices.shape == (100, 5) and peak < named, (peak, named)


def test_seqslam_at_the_least_budget_it_names_enhances_the_windows_rows_within_it():
    """A long database and blocks of a few queries: SeqSLAM enhances the window's extra rows too (float64
    copies and running sums), which were counted as one cost row each, so the least budget a refusal
    named was 1.25 x exceeded (at 20,000 database images, a window of 10)."""
    rng = np.random.default_rng(6)
    database, queries = (rng.standard_normal((rows, 64)).astype(np.float32) for rows in (20_000, 300))
    sequence_search(database[:100], queries[:30], 5, length=10)  # a warm-up: nothing first-time in the traced call
    with pytest.raises(VPRBenchError, match="too small for sequence matching") as refused:
        sequence_search(database, queries, 5, length=10, memory_budget=1000)
    named = named_budget(refused.value)
    found, peak = peak_of(lambda: sequence_search(database, queries, 5, length=10, memory_budget=named))
    assert found.info["block_rows"] < 10 and peak < named, (peak, named, found.info["block_rows"])


def test_ranking_the_whole_database_stays_within_the_least_budget_it_names():
    """At K = N the results are the search's largest arrays: the scores were made from the costs in
    three copies and the results put in query order in two more, beside blocks sized to the whole
    budget (1.07 x the least budget a refusal named, at 1,500 x 1,500)."""
    database, queries = traverse(1500, dim=8)
    sequence_search(database[:100], queries[:100], 100)  # a warm-up: nothing first-time in the traced call
    rng = np.random.default_rng(7)
    query_order = rng.permutation(1500)
    whole = sequence_search(database, queries, 1500, query_order=query_order, grid=True)  # as the stage
    with pytest.raises(VPRBenchError, match="top 1500 of 1,500 queries") as refused:
        sequence_search(database, queries, 1500, query_order=query_order, memory_budget=1000)
    named = named_budget(refused.value)
    found, peak = peak_of(lambda: sequence_search(database, queries, 1500, query_order=query_order,
                                                  memory_budget=named, grid=True))
    assert peak < named, (peak, named)
    np.testing.assert_array_equal(found.indices, whole.indices)
    np.testing.assert_array_equal(found.scores, whole.scores)


@pytest.mark.parametrize("score, compare", [("seqslam", "cosine"), ("diagonal", "cosine"),
                                            ("seqslam", "mean-absolute-difference")])
def test_results_are_the_same_for_every_budget(score, compare):
    """The budget sets the block of queries, which set the shape of every product: a product's last
    bits moved some costs across a grid step, and the order of up to 4 of the top 20 of 1,500
    queries changed with --search-memory, a run setting that must not change a result."""
    database, queries = traverse(1500, dim=256)
    runs = [sequence_search(database, queries, 20, score=score, compare=compare, length=10, grid=True,
                            memory_budget=budget) for budget in (10**9, 30_000_000, 9_000_000)]
    blocks = [run.info["block_rows"] for run in runs]
    assert blocks[0] == 1500 and 64 < blocks[1] < 1500 and blocks[2] < 64  # whole, several tiles, part of one
    for run in runs[1:]:
        np.testing.assert_array_equal(run.indices, runs[0].indices)
        np.testing.assert_array_equal(run.scores, runs[0].scores)
