"""PCA-whitening fitted with bounded memory: each path against sklearn's exact fit, memory
bound, state, errors."""
import re
import warnings

import numpy as np
import pytest

from vprbench.aggregation import PCAWhitening, pca_whiten
from vprbench.aggregation.pca import ROW_COPIES
from vprbench.errors import VPRBenchError
from vprbench.methods import create_method
from vprbench.row_sources import ArrayRows, parse_memory

@pytest.fixture(autouse=True)
def one_thread():
    """BLAS and OpenMP on one thread: results do not depend on it, and on a shared 2-core
    machine two contending threads made these tests three times slower."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


#: stated tolerances against sklearn PCA(svd_solver="full", whiten=True) (docs/evaluation.md):
#: scores = inner products of whitened, L2-normalised queries and database rows
EXACT_SCORE_TOL, EXACT_VALUE_TOL = 1e-4, 1e-3
RANDOMIZED_SCORE_TOL = 5e-3  # for spectra decaying like 1/i; slower decay is looser


def data(n, d, seed):
    return np.random.default_rng(seed).normal(size=(n, d)).astype(np.float32)


def descriptors(n, d, seed, decay=1.0):
    """L2-normalised rows whose covariance spectrum decays like i^-decay (distinct eigenvalues),
    with an offset mean, as descriptors have; the same seed gives the same basis."""
    basis = np.linalg.qr(np.random.default_rng(0).normal(size=(d, d)))[0]
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(n, d)) * np.arange(1, d + 1) ** (-decay / 2)) @ basis.T + 0.3 * basis[:, 0]
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def sklearn_whitening(database, dim) -> PCAWhitening:
    from sklearn.decomposition import PCA

    fitted = PCA(dim, svd_solver="full", whiten=True).fit(database)
    components = fitted.components_
    # signs as scikit-learn 1.5+ sets them (each component's largest-|.| entry positive); 1.4 set them by the data's
    components = components * np.sign(components[np.arange(dim), np.abs(components).argmax(axis=1)])[:, None]
    pca = PCAWhitening(dim)
    pca.load_state({"pca_mean": fitted.mean_,
                    "pca_projection": components / np.sqrt(fitted.explained_variance_)[:, None]})
    return pca


class CountingRows(ArrayRows):
    def __init__(self, array):
        super().__init__(array)
        self.largest_read = 0

    def read_rows(self, start, stop):
        self.largest_read = max(self.largest_read, stop - start)
        return super().read_rows(start, stop)


@pytest.mark.parametrize("n, d, budget, solver", [
    (4000, 256, 10**9, "covariance"),    # D <= N
    (500, 1024, 10**9, "gram"),          # N < D
    (4000, 256, 600_000, "randomized"),  # neither D^2 nor N^2 fits
])
def test_each_path_matches_sklearn_within_the_stated_tolerance(n, d, budget, solver):
    database, queries = descriptors(n, d, 1), descriptors(300, d, 2)
    rows = CountingRows(database)
    pca = PCAWhitening(48)
    assert pca.solver(rows, budget) == solver and pca.key(rows, budget)["solver"] == solver
    if solver == "randomized":  # said, with a budget that takes the exact path
        with pytest.warns(UserWarning, match=r"PCA-whitening of 4,000 x 256 descriptors is fitted by randomized "
                                             r"subspace iteration \(approximate\) within the 600.0 kB memory budget; "
                                             r"a budget of (\S+ \S+) \(--search-memory\) fits it exactly") as said:
            pca.fit(rows, budget)
        enough = parse_memory(re.search(r"a budget of (\S+ \S+)", str(said[0].message)).group(1).replace(" ", ""))
        assert pca.solver(rows, enough) == "covariance" and pca.solver(rows, enough * 0.9) == "randomized"
    else:
        pca.fit(rows, budget)
    exact = sklearn_whitening(database, 48)
    ours_q, ours_db = pca.transform(queries), pca.transform(database)
    ref_q, ref_db = exact.transform(queries), exact.transform(database)
    score_error = np.abs(ours_q @ ours_db.T - ref_q @ ref_db.T).max()
    if solver == "randomized":
        assert score_error <= RANDOMIZED_SCORE_TOL
        assert pca.key(rows, budget) == {"kind": "pca-whitening", "dim": 48, "solver": "randomized", "sketch": 96,
                                         "passes": 10, "seed": 0}
        assert rows.largest_read * d * 4 * ROW_COPIES <= budget  # every chunk held within the budget
    else:
        assert score_error <= EXACT_SCORE_TOL
        assert np.abs(ours_q - ref_q).max() <= EXACT_VALUE_TOL  # same signs as sklearn, same values
        np.testing.assert_allclose(pca.mean, exact.mean, atol=1e-6)


def test_fit_is_bounded_by_the_budget_whatever_n():
    rows = CountingRows(descriptors(20_000, 64, 3))
    PCAWhitening(16).fit(rows, 400_000)
    # the covariance path holds 12 D^2 + 8 D dim bytes; the rest goes to chunks of rows
    assert 0 < rows.largest_read * 64 * 4 * ROW_COPIES <= 400_000 - 12 * 64 * 64 - 8 * 64 * 16


def test_whitened_database_is_white_and_outputs_unit_norm():
    db, q = descriptors(2000, 64, 4), descriptors(30, 64, 5)
    out_db, out_q = pca_whiten(db, q, 16)
    assert out_db.shape == (2000, 16) and out_q.shape == (30, 16) and out_db.dtype == np.float32
    assert np.allclose(np.linalg.norm(out_q, axis=1), 1, atol=1e-5)
    pca = PCAWhitening(16).fit(db)
    raw = (db - pca.mean) @ pca.projection.T  # before the final L2: unit variance, uncorrelated
    assert np.allclose(np.cov(raw, rowvar=False), np.eye(16), atol=1e-3)


def test_float16_rows_fit_like_their_float32_values():
    db = descriptors(1500, 32, 6).astype(np.float16)
    half = PCAWhitening(8).fit(ArrayRows(db))
    wide = PCAWhitening(8).fit(db.astype(np.float32))
    np.testing.assert_allclose(half.projection, wide.projection, rtol=1e-4, atol=1e-4)


def test_transform_is_row_by_row():
    db = descriptors(1000, 32, 7)
    pca = PCAWhitening(8).fit(db)
    whole = pca.transform(db)
    np.testing.assert_allclose(np.concatenate([pca.transform(db[i:i + 7]) for i in range(0, 1000, 7)]), whole,
                               atol=1e-6)


def test_state_roundtrip():
    db = descriptors(500, 20, 8)
    pca = PCAWhitening(8).fit(db)
    again = PCAWhitening(8)
    again.load_state(pca.state())
    assert np.array_equal(again.transform(db), pca.transform(db))
    with pytest.raises(VPRBenchError, match="Saved PCA state has 8 dims, this PCA 4"):
        PCAWhitening(4).load_state(pca.state())


def test_pca_errors():
    with pytest.raises(VPRBenchError, match="PCA dimension 512 is larger than the number of database images \\(100\\)"):
        PCAWhitening().fit(data(100, 1000, 0))
    with pytest.raises(VPRBenchError, match="descriptor dimension \\(10\\): choose pca_dim <= 10"):
        PCAWhitening(20).fit(data(100, 10, 0))
    with pytest.raises(VPRBenchError, match="at least 1"):
        PCAWhitening(0)
    with pytest.raises(VPRBenchError, match="before being fitted"):
        PCAWhitening(4).transform(data(3, 10, 0))
    pca = PCAWhitening(4).fit(data(30, 10, 0))
    with pytest.raises(VPRBenchError, match="fitted on 10-dimensional descriptors"):
        pca.transform(data(3, 11, 0))
    with pytest.raises(VPRBenchError, match=r"budget of 10\.0 kB is too small to fit PCA-whitening of 1,000 x 256 "
                                             r"descriptors to 48 dims: its randomized path needs at least \S+ kB, the "
                                             r"exact one \S+ kB\. Raise --search-memory") as refused:
        PCAWhitening(48).fit(descriptors(1000, 256, 9), 10_000)
    randomized, exact = (parse_memory(x.replace(" ", "")) for x in re.findall(r"[\d.]+ kB", str(refused.value))[1:])
    assert PCAWhitening(48).solver(ArrayRows(descriptors(1000, 256, 9)), exact) == "covariance" and randomized < exact
    flat = np.repeat(descriptors(50, 8, 10)[:3], 20, axis=0)  # 60 rows spanning a plane
    with pytest.raises(VPRBenchError, match="vary along only 2 directions; .* choose pca_dim <= 2"):
        PCAWhitening(4).fit(flat)


def test_anyloc_pca_presets_use_the_post_processor():
    method = create_method("anyloc-vlad-dinov2-pca")
    post = method.postprocessor()
    assert isinstance(post, PCAWhitening) and post.dim == method.pca_dim == 512
    assert create_method("anyloc-vlad-dinov2").postprocessor() is None


def test_as_many_dims_as_database_images_is_refused_before_describing():
    # centred on their mean, 40 rows span 39 directions: dim 40 used to pass the early check and
    # fail only at the fit, after every descriptor was computed
    with pytest.raises(VPRBenchError, match=r"PCA dimension 40 is larger than the number of database images of toy "
                                            r"\(40\) less one \(centring leaves 39 directions\): choose pca_dim <= 39\."):
        PCAWhitening(40).check_rows(40, "toy")
    PCAWhitening(39).check_rows(40, "toy")
    # was "choose pca_dim <= 0" for one image, a dimension PCA refuses
    with pytest.raises(VPRBenchError, match=r"\(1\) less one \(centring leaves 0 directions\): give at least 2 "
                                            r"database images, or no PCA\."):
        PCAWhitening(1).check_rows(1, "toy")
    with pytest.raises(VPRBenchError, match=r"descriptor dimension \(10\): give at least 2 database images, or no PCA\."):
        PCAWhitening(1).fit(data(1, 10, 0))
    with pytest.raises(VPRBenchError, match=r"images \(40\) less one or the descriptor dimension \(100\): choose "
                                            r"pca_dim <= 39\."):
        PCAWhitening(40).fit(data(40, 100, 0))
    assert PCAWhitening(39).fit(data(40, 100, 0)).projection.shape == (39, 100)


def test_the_eigen_solver_works_in_place_without_a_copy_of_the_matrix():
    """The fit budgets one D x D (or N x N) matrix; LAPACK copied it (C order to Fortran order): the
    urban stack's exact fit (11,762 x 49,152) peaked 1 GB above its 1.2 GB budget."""
    from traced import peak_of
    from vprbench.aggregation.pca import _top_eigen

    rng = np.random.default_rng(0)
    x = rng.standard_normal((1500, 1500))
    matrix = x @ x.T  # symmetric, C-ordered, 18 MB
    reference = np.linalg.eigvalsh(matrix)[::-1][:16]
    (values, vectors), peak = peak_of(lambda: _top_eigen(matrix, 16))
    assert peak < matrix.nbytes / 4, peak
    np.testing.assert_allclose(values, reference, rtol=1e-9)
    assert vectors.shape == (1500, 16)


@pytest.mark.parametrize("n, d, dim, solver", [(300, 8000, 64, "gram"), (2500, 1200, 64, "randomized")])
def test_a_fit_at_a_tight_budget_peaks_within_it(n, d, dim, solver):
    """tracemalloc's peak over a whole fit (its input excluded) at a budget of what the path holds plus
    ten rows. The Gram path made a D x dim product per chunk and three more to finish (3 x its budget
    at 600 x 20,000 to 256 dims); the randomized one QR'd a C-ordered Gaussian (a copy, 1.17 x)."""
    import scipy.linalg  # noqa: F401  (its import is no part of a fit's memory)

    from traced import peak_of
    from vprbench.aggregation.pca import _solver_memory

    rows = ArrayRows(data(n, d, 0))
    budget = _solver_memory(solver, n, d, dim) + 10 * ROW_COPIES * 4 * d * (2 if solver == "gram" else 1)
    pca = PCAWhitening(dim)
    assert pca.solver(rows, budget) == solver
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the randomized path's notice
        _, peak = peak_of(lambda: pca.fit(rows, budget))
    assert peak < 1.05 * budget, (peak, budget)


@pytest.mark.parametrize("n, d, solver", [(3000, 64, "covariance"), (600, 1024, "gram"), (3000, 512, "randomized")])
def test_every_budget_that_reads_whole_tiles_fits_the_same_state(n, d, solver, monkeypatch):
    """--search-memory is no part of a run's identity, but a fit summed its rows a chunk at a time and
    the budget set the chunk: the state changed in its last bits (4.8e-8 at 6,000 x 512 -> 128)."""
    import vprbench.aggregation.pca as pca_module

    monkeypatch.setattr(pca_module, "FIT_TILE", 64, raising=False)
    rows, states, chunks = ArrayRows(descriptors(n, d, 1)), [], []
    held = pca_module._solver_memory(solver, n, d, 32)
    per_row = ROW_COPIES * 4 * d * (2 if solver == "gram" else 1)  # the Gram path holds two chunks
    for tiles in (1, 2, 3):
        budget = held + per_row * (64 * tiles + 20)  # 20 rows beyond whole tiles: cut to the tiles
        chunks.append(PCAWhitening(32).check_budget(rows, budget))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the randomized path says it is approximate
            fitted = PCAWhitening(32).fit(rows, budget)
        states.append((fitted.mean, fitted.projection))
    for mean, projection in states[1:]:
        np.testing.assert_array_equal(mean, states[0][0])
        np.testing.assert_array_equal(projection, states[0][1])
    assert chunks == [(solver, 64), (solver, 128), (solver, 192)]
