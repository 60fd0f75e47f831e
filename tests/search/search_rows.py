"""Row sources and data of known inner products for the search tests."""
import h5py
import numpy as np

from vprbench.errors import VPRBenchError
from vprbench.search.exact import _plan
from vprbench.row_sources import as_rows


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

