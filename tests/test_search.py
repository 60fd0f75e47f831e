"""Memory-bounded retrieval: exact search streamed from row sources, its tie order and its
identity across budgets, approximate indexes, post-processing fitted once and reused."""
import json

import h5py
import numpy as np
import pytest

from vprbench.aggregation import PCAWhitening
from vprbench.errors import VPRBenchError
from vprbench.evaluation.postprocess import TransformedRows, transform_rows
from vprbench.evaluation.search import SCORE_TOLERANCE, ArrayRows, _plan, exact_search, search, tile_rows
from vprbench.evaluation.retrieve import retrieve
from vprbench.methods import Method
from vprbench.row_sources import as_rows, parse_memory


@pytest.fixture(autouse=True)
def one_thread():
    """BLAS and OpenMP on one thread: results do not depend on it, and on a shared 2-core
    machine two contending threads made these tests three times slower."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


@pytest.fixture
def tiles_of_1024(monkeypatch):
    """Tiles of 1,024 rows (at these small dimensions the grid has 4,096), so that a few
    thousand rows cross several tile and chunk borders."""
    import vprbench.evaluation.search as search_module

    assert tile_rows(8) == tile_rows(1024) == 4096 and tile_rows(35_721) == 1792 and tile_rows(49_152) == 1280
    monkeypatch.setattr(search_module, "tile_rows", lambda dim: 1024)


class H5Rows:
    """A row source over an HDF5 dataset, as a descriptor store exposes it."""

    def __init__(self, path, folder=None):
        self.file = h5py.File(path, "r")
        self.data = self.file["descriptors"]
        self.row_count, self.dim = self.data.shape
        self.dtype, self.folder = self.data.dtype, folder
        self.reads = []

    def read_rows(self, start, stop):
        self.reads.append(stop - start)
        return self.data[start:stop].astype(np.float32)

    def read_rows_at(self, indices):
        assert np.all(np.diff(indices) > 0), "indices must be sorted ascending"
        self.reads.append(len(indices))
        return self.data[np.asarray(indices)].astype(np.float32)


def h5_rows(tmp_path, name, array, folder=None) -> H5Rows:
    with h5py.File(tmp_path / f"{name}.h5", "w") as f:
        f.create_dataset("descriptors", data=array, chunks=(min(len(array), 256), array.shape[1]))
    return H5Rows(tmp_path / f"{name}.h5", folder)


def unit(n, d, seed):
    x = np.random.default_rng(seed).normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def budget_for(database, queries, k, chunks, query_chunks=1):
    """The smallest budget (searched in 1 kB steps) whose plan has at most these chunk counts."""
    db, q = as_rows(database), as_rows(queries)
    budget = 10_000
    while True:
        try:
            plan = _plan(db, q, k, budget)
            if plan["chunks"] <= chunks and plan["query_chunks"] <= query_chunks:
                return budget
        except VPRBenchError:
            pass
        budget += 1000 if budget < 10**6 else 50_000


def reference_topk(database, queries, k):
    """Exact integer scores (float64), ordered by score descending, then index ascending."""
    scores = queries.astype(np.float64) @ database.astype(np.float64).T
    order = np.lexsort((np.broadcast_to(np.arange(len(database)), scores.shape), -scores), axis=1)[:, :k]
    return np.take_along_axis(scores, order, 1), order


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
    assert result.info["chunks"] == 5 and result.info["query_chunks"] == 2 and result.info["chunk_rows"] == 1024
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
    import vprbench.evaluation.search as search_module

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

    import vprbench.evaluation.search as search_module

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


def test_threads_take_slices_of_each_query_tile_and_change_nothing(monkeypatch, tmp_path, tiles_of_1024):
    """With 2 threads each computes its half of every query tile (one-thread BLAS, its own heap
    rows): bitwise the same for every budget, and the same ranking as one thread."""
    from threadpoolctl import threadpool_limits

    import vprbench.evaluation.search as search_module

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


# ---------------------------------------------------------------- the same results on any machine
def lattice(n, d, seed, noise=0.0):
    """Entries in {-1, 0, 1} x 2^-5, plus float32 noise of `noise` (standard deviation): the
    exact inner products of noisy rows with clean ones are multiples of 2^-10 give or take
    3e-6, far from a 2^-16 rounding boundary, while float32 sums of the noisy products round
    differently along every arithmetic path, and most scores tie with another row's."""
    rng = np.random.default_rng(seed)
    x = rng.integers(-1, 2, size=(n, d)).astype(np.float32) * np.float32(2**-5)
    return x + rng.normal(scale=noise, size=(n, d)).astype(np.float32) if noise else x


def torch_products(queries, rows, out=None, scale=np.float32(1)):
    """The same product through torch's own BLAS (another set of kernels, as another CPU has)."""
    import torch

    writable = [np.require(x, requirements=["C", "W"]) for x in (queries, rows)]  # search lends read-only rows
    product = torch.from_numpy(writable[0]) @ torch.from_numpy(writable[1]).T
    if out is None:
        return product.numpy()
    np.multiply(product.numpy(), scale, out=out)


def ranked(scores, k):
    """Rows by score descending, then lower index: the top k of each query."""
    order = np.lexsort((np.broadcast_to(np.arange(scores.shape[1]), scores.shape), -scores), axis=1)[:, :k]
    return np.take_along_axis(scores, order, 1), order


@pytest.fixture
def torch_threads():
    import torch

    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.mark.filterwarnings("ignore:TF32 acceleration")  # said by mkldnn.flags() on CPU builds
def test_results_are_the_same_along_every_arithmetic_path(monkeypatch, torch_threads):
    import torch
    from threadpoolctl import threadpool_limits

    import vprbench.evaluation.search as search_module

    db, q = lattice(3000, 1024, 21, noise=5e-7), lattice(300, 1024, 22)
    db[1024], db[2999], db[1500] = db[700], db[5], db[1023]  # copies at tile edges of copies in tile middles
    q[0], q[1] = np.round(db[700] * 32) / 32, np.round(db[5] * 32) / 32  # the lattice points of those rows
    exact = q.astype(np.float64) @ db.astype(np.float64).T
    assert np.abs(exact * 2**10 - np.round(exact * 2**10)).max() * 2**-10 < 4e-6  # far from a 2^-16 boundary
    expected_scores, expected = ranked((np.round(exact * 2**16) * 2**-16).astype(np.float32), 10)
    assert len(np.unique(expected_scores)) < 0.5 * expected_scores.size  # ties everywhere

    # without the rule: the raw float32 products differ in their last bits between paths,
    # and so does the order they give tied rows
    raw_numpy, raw_torch = q @ db.T, torch_products(q, db)
    assert not np.array_equal(raw_numpy, raw_torch)
    assert not np.array_equal(ranked(raw_numpy, 10)[1], ranked(raw_torch, 10)[1])
    assert not np.array_equal(ranked(raw_numpy, 10)[1], expected)

    def run(threads=1, product=None, tile=None, chunks=None, onednn=True):
        with (monkeypatch.context() as patch, threadpool_limits(threads),
              torch.backends.mkldnn.flags(enabled=onednn)):  # off: numpy's BLAS
            torch_threads(threads)
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
                                             r"Raise --search-memory \(memory_budget\) to at least 154\.5 MB"):
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


# ---------------------------------------------------------------- retrieve
class Whitened(Method):
    def __init__(self, dim=16):
        self.dim = dim

    def describe(self, images):  # pragma: no cover - never called here
        raise AssertionError

    def postprocessor(self):
        return PCAWhitening(self.dim)


class OldPlugin(Method):
    def describe(self, images):  # pragma: no cover
        raise AssertionError

    def postprocess(self, database, queries):
        return database[:, :8] * 2, queries[:, :8] * 2


def spectrum(n, d, seed):
    """Descriptors with a decaying spectrum (distinct eigenvalues), L2-normalised."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, d)) * np.arange(1, d + 1) ** -0.5 + 0.2
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_retrieve_fits_pca_once_and_is_identical_for_every_budget(tmp_path, monkeypatch, tiles_of_1024):
    db, q = spectrum(4097, 96, 11), spectrum(400, 96, 12)
    db[4096] = db[10]  # the copy is the last tile of the transform, a single row
    q[0] = db[10]
    database, queries = h5_rows(tmp_path, "db", db, folder=tmp_path), h5_rows(tmp_path, "q", q)
    first = retrieve(Whitened(), database, queries, 10)
    assert first.indices[0, :2].tolist() == [10, 4096] and first.scores[0, 0] == first.scores[0, 1]
    post = first.info["postprocess"]
    assert post["state"] == "fitted" and post["key"]["postprocessor"] == {"kind": "pca-whitening", "dim": 16,
                                                                          "solver": "covariance"}
    assert post["file"].startswith(str(tmp_path)) and first.info["dim"] == 16
    json.dumps(first.info)  # it goes into the JSON result record as is
    pca = PCAWhitening(16).fit(db)
    expected = exact_search(pca.transform(db), pca.transform(q), 10)
    np.testing.assert_array_equal(first.indices, expected.indices)
    np.testing.assert_allclose(first.scores, expected.scores, atol=1e-5)

    def no_refit(*args, **kwargs):
        raise AssertionError("a warm run refitted PCA")

    small = budget_for(TransformedRows(ArrayRows(db), pca), TransformedRows(ArrayRows(q), pca), 10, chunks=5)
    monkeypatch.setattr(PCAWhitening, "fit", no_refit)
    for budget in (10**9, small):  # one chunk; five
        warm = retrieve(Whitened(), database, queries, 10, memory_budget=budget)
        assert warm.info["postprocess"]["state"] == "loaded"
        np.testing.assert_array_equal(warm.indices, first.indices)
        np.testing.assert_array_equal(warm.scores, first.scores)
    assert warm.info["chunks"] == 5 and warm.info["memory_budget"] == small


def test_transformed_rows_depend_neither_on_reads_nor_on_neighbours():
    db = spectrum(4097, 96, 18)
    db[4096] = db[10]  # alone in the last tile of the grid
    rows = TransformedRows(ArrayRows(db), PCAWhitening(16).fit(db))
    whole = rows.read_rows(0, 4097)
    pieces = np.concatenate([rows.read_rows(a, min(a + 7, 4097)) for a in range(0, 4097, 7)])
    np.testing.assert_array_equal(pieces, whole)
    np.testing.assert_array_equal(whole[4096], whole[10])
    np.testing.assert_array_equal(rows.read_rows_at(np.array([3, 10, 4096])), whole[[3, 10, 4096]])


def test_a_rows_transform_is_the_same_along_every_arithmetic_path(monkeypatch, torch_threads):
    import torch
    from threadpoolctl import threadpool_limits

    import vprbench.evaluation.postprocess as postprocess_module

    db = spectrum(2000, 1024, 23)
    db[1024] = db[700]  # a copy at a tile's edge of a row in a tile's middle
    pca = PCAWhitening(64).fit(db)
    # in float32 numpy and torch round the same product differently
    centred = db - pca.mean
    assert not np.array_equal(centred @ pca.projection.T, torch_products(centred, pca.projection))
    # computed in float64 and rounded once, the rows are the same whichever path computes them
    x = torch.from_numpy(db.astype(np.float64)) - torch.from_numpy(pca.mean.astype(np.float64))
    out = x @ torch.from_numpy(pca.projection.astype(np.float64)).T
    through_torch = (out / torch.linalg.norm(out, dim=1, keepdim=True)).numpy().astype(np.float32)
    whole = pca.transform(db)
    np.testing.assert_array_equal(whole, through_torch)
    np.testing.assert_array_equal(whole[1024], whole[700])
    np.testing.assert_array_equal(np.concatenate([pca.transform(row[None]) for row in db[:50]]), whole[:50])
    for threads, tile in ((2, None), (1, 64), (2, 1000)):
        with monkeypatch.context() as patch, threadpool_limits(threads):
            if tile is not None:
                patch.setattr(postprocess_module, "transform_rows", lambda dim: tile)
            rows = TransformedRows(ArrayRows(db), pca)
            assert rows.tile == (tile or transform_rows(1024))
            np.testing.assert_array_equal(rows.read_rows(0, 2000), whole)


def test_unreadable_state_is_refitted(tmp_path):
    db = ArrayRows(spectrum(600, 32, 13), folder=tmp_path)
    first = retrieve(Whitened(8), db, db, 3)
    with open(first.info["postprocess"]["file"], "wb") as f:
        f.write(b"torn")
    with pytest.warns(UserWarning, match="Refitting"):
        again = retrieve(Whitened(8), db, db, 3)
    assert again.info["postprocess"]["state"] == "fitted"
    np.testing.assert_array_equal(again.indices, first.indices)


def test_a_crash_while_saving_the_state_leaves_nothing_behind(tmp_path, monkeypatch):
    db = ArrayRows(spectrum(600, 32, 13), folder=tmp_path)

    def torn_savez(f, **arrays):
        f.write(b"PK half a file")
        raise KeyboardInterrupt  # killed mid-write

    monkeypatch.setattr(np, "savez", torn_savez)
    with pytest.raises(KeyboardInterrupt):
        retrieve(Whitened(8), db, db, 3)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    assert retrieve(Whitened(8), db, db, 3).info["postprocess"]["state"] == "fitted"


CENTRING = """
import numpy as np
from vprbench.methods import Method
from vprbench.row_sources import chunks


class Centre:
    \"\"\"A small post-processor: subtract the database mean.\"\"\"
    def key(self, rows, memory_budget):
        return {"kind": "centre"}

    def fit(self, rows, memory_budget):
        self.mean = sum(block.sum(axis=0, dtype=np.float64) for _, block in chunks(rows, 100)) / rows.row_count

    def transform(self, x):
        return (x - self.mean).astype(np.float32)

    def state(self):
        return {"mean": self.mean}

    def load_state(self, state):
        self.mean = state["mean"]


class Centred(Method):
    def describe(self, images):
        raise AssertionError

    def postprocessor(self):
        return Centre()
"""


def test_two_processes_fitting_one_state_at_once(tmp_path):
    import subprocess
    import sys

    np.save(tmp_path / "db.npy", unit(5000, 32, 19))
    script = CENTRING + (
        "import sys\nfrom vprbench.evaluation.search import ArrayRows\nfrom vprbench.evaluation.retrieve import retrieve\n"
        f"db = ArrayRows(np.load({str(tmp_path / 'db.npy')!r}), folder={str(tmp_path)!r})\n"
        "np.save(sys.argv[1], retrieve(Centred(), db, db, 5).indices)\n")
    runs = [subprocess.Popen([sys.executable, "-c", script, str(tmp_path / f"out{i}.npy")]) for i in range(2)]
    assert [run.wait(timeout=120) for run in runs] == [0, 0]
    states = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("postprocess-"))
    assert len(states) == 1 and states[0].endswith(".npz")  # one whole file, no temporary left
    np.testing.assert_array_equal(np.load(tmp_path / "out0.npy"), np.load(tmp_path / "out1.npy"))
    namespace = {}
    exec(CENTRING, namespace)
    warm = retrieve(namespace["Centred"](), ArrayRows(np.load(tmp_path / "db.npy"), folder=tmp_path),
                    np.load(tmp_path / "db.npy"), 5)
    assert warm.info["postprocess"]["state"] == "loaded"
    np.testing.assert_array_equal(warm.indices, np.load(tmp_path / "out0.npy"))


def test_old_postprocess_override_still_runs_in_memory():
    db, q = unit(300, 16, 14), unit(20, 16, 15)
    result = retrieve(OldPlugin(), db, q, 5)
    assert result.info["postprocess"] == {"kind": "OldPlugin.postprocess", "in_memory": True}
    np.testing.assert_array_equal(result.indices, exact_search(db[:, :8] * 2, q[:, :8] * 2, 5).indices)


def test_base_postprocess_applies_the_postprocessor_in_memory():
    db, q = spectrum(500, 32, 16), spectrum(30, 32, 17)
    out_db, out_q = Whitened(8).postprocess(db, q)
    pca = PCAWhitening(8).fit(db)
    np.testing.assert_array_equal(out_q, pca.transform(q))
    assert out_db.shape == (500, 8)


# ---------------------------------------------------------------- approximate
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
