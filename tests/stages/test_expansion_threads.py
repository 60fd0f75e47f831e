"""aqe's and dba's scores do not depend on the BLAS's thread count (a run's spec does not name it)."""
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vprbench.row_sources import ArrayRows
from vprbench.stages import Candidates
from vprbench.stages.base import StageContext, reordered
from vprbench.stages.registry import create_stage


@pytest.mark.parametrize("stage", ["aqe", "dba"])
def test_expanded_scores_are_the_same_bit_for_bit_on_1_2_and_3_blas_threads(stage, monkeypatch):
    """8,192-dim rows, 100 candidates a query: the BLAS split each query's products with its candidates
    by its thread count (4 % of the scores differed at 1 and 2 threads, by up to 2.5e-8 in dba's float32
    products: a grid step apart where one lies at a boundary). They are summed without it now. The scores
    are compared before they are put on the grid, where such a difference is seen whatever its place."""
    import vprbench.stages.expansion as expansion

    raw = []
    monkeypatch.setattr(expansion, "reordered", lambda indices, scores, grid: (raw.append(scores), reordered(
        indices, scores, grid))[1])
    rng = np.random.default_rng(0)
    database = rng.standard_normal((600, 8192)).astype(np.float32)
    database /= np.linalg.norm(database, axis=1, keepdims=True)
    queries = database[:60] + 0.5 * rng.standard_normal((60, 8192)).astype(np.float32) / np.sqrt(8192)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    indices = np.stack([rng.choice(600, 100, replace=False) for _ in queries]).astype(np.int64)
    candidates = Candidates(indices, np.zeros(indices.shape, dtype=np.float32))
    context = StageContext(dataset=None, database=ArrayRows(database), queries=ArrayRows(queries),
                           memory_budget=1 << 30)
    found = {}
    for threads in (1, 2, 3):
        with threadpool_limits(threads):
            found[threads] = create_stage(stage, {"k": 100, "n": 10}).apply(candidates, context)
    for threads in (2, 3):
        np.testing.assert_array_equal(found[threads].indices, found[1].indices)
        np.testing.assert_array_equal(found[threads].scores, found[1].scores)
        np.testing.assert_array_equal(raw[threads - 1], raw[0])
