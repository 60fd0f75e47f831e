"""A sequence search's costs do not depend on the BLAS's thread count (a run's spec does not name it)."""
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vprbench.stages.sequence.search import sequence_search


@pytest.mark.parametrize("score", ["seqslam", "diagonal"])
def test_cosine_costs_are_the_same_bit_for_bit_on_1_2_and_3_blas_threads(score):
    """Products of 1,000-dim rows (an inner length the BLAS splits by its thread count): 2 threads gave
    half the scores different in their last bits, some a grid step apart. Each fixed-shape product now
    runs on one thread of its own, as exact search's."""
    rng = np.random.default_rng(0)
    database = rng.standard_normal((400, 1000)).astype(np.float32)
    database /= np.linalg.norm(database, axis=1, keepdims=True)
    queries = database[50:250] + 0.3 * rng.standard_normal((200, 1000)).astype(np.float32)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    found = {}
    for threads in (1, 2, 3):
        with threadpool_limits(threads):
            result = sequence_search(database, queries, 10, score=score, length=5)
        found[threads] = result.indices, result.scores
    for threads in (2, 3):
        assert np.array_equal(found[threads][0], found[1][0])
        assert np.array_equal(found[threads][1], found[1][1]), np.count_nonzero(found[threads][1] != found[1][1])
