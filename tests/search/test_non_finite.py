"""Rows search cannot rank (NaN, infinity, products beyond float32) are refused on every
route, naming the row: never ranked last (a NaN query came back with index -1) or first."""
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation.retrieve import retrieve
from vprbench.search.exact import exact_search
from search_rows import unit


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("index, n", [("exact", 600), ("hnsw", 600), ("ivf-pq", 10_000)])
def test_a_non_finite_row_is_refused_naming_it(index, n, bad):
    db, q = unit(n, 16, 1), unit(300, 16, 2)
    broken = db.copy()
    broken[517, 3] = bad
    with pytest.raises(VPRBenchError, match=r"^Database row 517 holds NaN or infinity, which search cannot rank"):
        retrieve(None, broken, q, 5, index=index)
    broken = q.copy()
    broken[260, 0] = bad
    with pytest.raises(VPRBenchError, match=r"^Query row 260 holds NaN or infinity"):
        retrieve(None, db, broken, 5, index=index)


def test_rows_whose_products_overflow_are_refused(tiles_of_1024):
    db, q = unit(3000, 8, 3), unit(40, 8, 4)
    db[2500] *= np.float32(1e18)  # finite, but its product with itself (in 2^-16 steps) exceeds float32
    q[7] = db[2500]
    with pytest.raises(VPRBenchError, match=r"^Inner products of the descriptors exceed float32's range: .* "
                                            r"L2-normalise them"):
        exact_search(db, q, 5)


def test_an_approximate_shortlist_whose_products_overflow_is_refused():
    db, q = unit(600, 16, 5), unit(20, 16, 6)
    db *= np.float32(1e17)  # finite rows, but products (in 2^-16 steps) beyond float32
    q[3] *= np.float32(1e17)
    with pytest.raises(VPRBenchError, match=r"^Inner products of query row 3 and its shortlist exceed float32's range"):
        retrieve(None, db, q, 5, index="hnsw")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("score", ["diagonal", "seqslam"])
def test_sequence_matching_refuses_a_non_finite_row(bad, score):
    """Before: sad's search and the sequence stages dropped a NaN database row from every top K."""
    from vprbench.stages.sequence.search import sequence_search

    db, q = unit(60, 16, 7), unit(30, 16, 8)
    broken = db.copy()
    broken[41, 2] = bad
    with pytest.raises(VPRBenchError, match=r"^Database row 41 holds NaN or infinity"):
        sequence_search(broken, q, 5, score=score, length=3)
    broken = q.copy()
    broken[17, 0] = bad
    with pytest.raises(VPRBenchError, match=r"^Query row 17 holds NaN or infinity"):
        sequence_search(db, broken, 5, score=score, length=3, compare="mean-absolute-difference")
