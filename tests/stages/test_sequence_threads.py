"""A sequence search's costs do not depend on the BLAS's thread count (a run's spec does not name it)."""
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vprbench.stages.sequence.search import sequence_search


@pytest.mark.parametrize("score,compare", [("seqslam", "cosine"), ("diagonal", "cosine"), ("seqslam", "mean-absolute-difference")])
def test_costs_are_the_same_bit_for_bit_on_1_2_and_3_blas_threads(score, compare):
    """Products of 1,000-dim rows (an inner length the BLAS splits by its thread count): 2 threads gave
    half the scores different in their last bits, some a grid step apart. Each fixed-shape product now
    runs on one thread of its own, as exact search's (mean absolute differences side by side too)."""
    rng = np.random.default_rng(0)
    database = rng.standard_normal((400, 1000)).astype(np.float32)
    database /= np.linalg.norm(database, axis=1, keepdims=True)
    queries = database[50:250] + 0.3 * rng.standard_normal((200, 1000)).astype(np.float32)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    found = {}
    for threads in (1, 2, 3):
        with threadpool_limits(threads):
            result = sequence_search(database, queries, 10, score=score, compare=compare, length=5)
        found[threads] = result.indices, result.scores
    for threads in (2, 3):
        assert np.array_equal(found[threads][0], found[1][0])
        assert np.array_equal(found[threads][1], found[1][1]), np.count_nonzero(found[threads][1] != found[1][1])


def test_products_on_the_calling_thread_run_on_one_blas_thread(monkeypatch):
    """With no threads of its own (the BLAS seen on one thread: here another library's, capped at 1) the
    products ran on the calling thread on every thread of numpy's BLAS, which splits their sums by count."""
    from threadpoolctl import threadpool_info

    import vprbench.stages.sequence.search as module

    seen, real = [], module._tile_product

    def spy(*args):
        seen.append(max(lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"))
        return real(*args)

    monkeypatch.setattr(module, "_tile_product", spy)
    monkeypatch.setattr(module, "search_threads", lambda libraries=None: 1)
    rng = np.random.default_rng(0)
    rows = rng.standard_normal((300, 64)).astype(np.float32)
    with threadpool_limits(2):
        sequence_search(rows, rows[:100], 5, score="seqslam", length=5)
    assert seen and set(seen) == {1}
