"""Retrieval with post-processing (PCA-whitening) fitted once on the database, saved, reused
and applied chunk by chunk."""
import json

import numpy as np
import pytest

from vprbench.aggregation import PCAWhitening
from vprbench.errors import VPRBenchError
from vprbench.evaluation.postprocess import TransformedRows, transform_rows
from vprbench.search.exact import ArrayRows, exact_search
from vprbench.evaluation.retrieve import retrieve
from vprbench.methods import Method
from search_rows import budget_for, h5_rows, unit


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
    # in float32 numpy and torch round the same product differently (on the x86 CPUs seen: their BLAS differ)
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
    assert [p.suffix for p in tmp_path.iterdir()] == [".lock"]  # nothing half-written to load; its writers' lock
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
        "import sys\nfrom vprbench.search.exact import ArrayRows\nfrom vprbench.evaluation.retrieve import retrieve\n"
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




class _ByTile:
    """A post-processor whose output shows the tile it was given: its row count (`shape`) or its
    rows' sum (`neighbours`). The fixed, padded grid must hide both from the rows read."""

    def __init__(self, kind):
        self.kind = kind

    def transform(self, x):
        return x * len(x) if self.kind == "shape" else x + x.sum(axis=0)


def test_transformed_rows_come_from_one_fixed_padded_grid():
    db = np.arange(40 * 4, dtype=np.float32).reshape(40, 4) / 100
    by_shape = TransformedRows(ArrayRows(db), _ByTile("shape"))
    assert by_shape.tile == 1024  # one tile, padded to the 40 rows
    whole = by_shape.read_rows(0, 40)
    np.testing.assert_array_equal(whole, db * 40)
    np.testing.assert_array_equal(by_shape.read_rows_at(np.array([3, 17])), whole[[3, 17]])
    by_neighbours = TransformedRows(ArrayRows(db), _ByTile("neighbours"))
    np.testing.assert_array_equal(by_neighbours.read_rows(5, 9), by_neighbours.read_rows(0, 40)[5:9])


def test_transformed_rows_read_at_indices_within_their_read_cost():
    """Rows at indices are read and transformed a tile at a time, as read_cost budgets: all the source
    rows at once were an approximate index's whole training sample at the source's dimension."""
    from traced import peak_of
    from vprbench.search.exact import read_cost

    db = unit(20000, 512, 0)
    rows = TransformedRows(ArrayRows(db), PCAWhitening(32).fit(db[:2000]))
    indices = np.arange(0, 20000, 1)
    per_row, fixed = read_cost(rows)
    picked, peak = peak_of(lambda: rows.read_rows_at(indices))
    assert peak < 1.05 * (len(indices) * per_row + fixed), (peak, len(indices) * per_row + fixed)
    np.testing.assert_array_equal(picked[5000:7000], rows.read_rows(5000, 7000))


def test_a_transform_holds_no_float64_copy_of_the_projection(monkeypatch):
    """PCA's projection is applied in float64 a block at a time, within read_cost, and nothing of it is
    kept: a float64 copy of all of it (201 MB at AnyLoc's 49,152 -> 512 dims) was held from the first
    transform on, beside any search's budget."""
    import tracemalloc

    from vprbench.aggregation import pca as pca_module
    from vprbench.evaluation import postprocess
    from vprbench.search.exact import read_cost

    db = unit(1000, 2048, 0)
    pca, at_once = PCAWhitening(256).fit(db), PCAWhitening(256)  # its float64 projection: 4 MB
    at_once.load_state(pca.state())
    whole = TransformedRows(ArrayRows(db), at_once).read_rows(0, 1000)  # projected in one block
    for module in (pca_module, postprocess):  # applied and counted a MiB at a time
        monkeypatch.setattr(module, "PROJECTION_BLOCK_BYTES", 2**20)
    tracemalloc.start()
    try:
        rows = TransformedRows(ArrayRows(db), pca)
        got = rows.read_rows(0, 1000)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held < got.nbytes + 2**20, held
    per_row, fixed = read_cost(rows)
    assert peak < 1.05 * (len(got) * per_row + fixed), (peak, len(got) * per_row + fixed)
    np.testing.assert_array_equal(got, whole)  # the blocks' sums are the whole projection's


def test_the_fitted_state_is_counted_once_in_the_search_budget():
    """A fitted post-processor's state is held while rows are read through it: the database counts it
    (the queries share it), so a search plans for it and a budget without room for it is refused
    (PCA's projection at AnyLoc's 49,152 -> 512: 100 MB, uncounted beside the search before)."""
    from vprbench.evaluation.postprocess import postprocessed
    from vprbench.search.exact import _least

    db, q = spectrum(600, 2048, 3), spectrum(50, 2048, 4)
    database, queries, _ = postprocessed(Whitened(256), ArrayRows(db), ArrayRows(q), 10**9)
    state = 256 * 2048 * 4 + 2048 * 4  # the projection and the mean, float32
    assert (database.state_bytes, queries.state_bytes) == (state, 0)
    uncounted = TransformedRows(ArrayRows(db), database.postprocessor)
    without = _least(uncounted, queries, 5).need
    assert _least(database, queries, 5).need == without + state
    with pytest.raises(VPRBenchError, match="too small for this search"):
        exact_search(database, queries, 5, memory_budget=without)
    assert exact_search(database, queries, 5, memory_budget=without + state).indices.shape == (50, 5)
