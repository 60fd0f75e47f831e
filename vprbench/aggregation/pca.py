"""PCA-whitening of global descriptors (AnyLoc's -PCA presets: 49,152 -> 512 dims).

As AnyLoc: PCA with whitening fitted on the dataset's database descriptors (never the queries),
applied to database and queries, then L2 normalisation; the exact PCA (what sklearn's
`PCA(dim, svd_solver="full", whiten=True)` computes). The authors' script calls
`PCA(n_components=512, whiten=True)`, whose "auto" solver is sklearn's randomized one at their
shapes (unseeded): an approximation of this. Fitted from a row source chunk by chunk, with memory bounded by a budget
whatever N is, along one of three paths:

- "covariance" (D <= N, D x D fits the budget): the covariance streamed in float64, its top
  eigenvectors. Exact up to rounding.
- "gram" (N < D, N x N fits): the Gram matrix streamed block by block, its top
  eigenvectors, components from one more pass. Exact up to rounding.
- "randomized" (neither fits): randomized subspace iteration on the streamed covariance,
  a sketch of 2 x dim columns, PASSES passes, seeded. Approximate (docs/evaluation.md
  states the tolerance).

Components follow sklearn's sign convention (each one's largest-magnitude entry positive).
"""
from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from ..errors import VPRBenchError
from ..row_sources import (DEFAULT_MEMORY_BUDGET, READ_BYTES, as_rows, chunks, format_budget, format_bytes, parse_memory,
                           read_bytes_per_row)

DEFAULT_PCA_DIM = 512
PASSES = 10
#: variances below this share of the largest are float32 rounding, not directions of the data
RANK_TOLERANCE = 1e-6
#: a chunk (centred in place) and one product of at most its size
ROW_COPIES = 2
#: rows per sum and product of a fit (fewer where 64 MiB reads fewer): a fixed tile of the database,
#: so any budget that reads whole tiles fits the same state, bit for bit
FIT_TILE = 1024
#: the projection is applied in float64 this many bytes of it at a time: a float64 copy of all of
#: it (201 MB at AnyLoc's 49,152 -> 512 dims) would sit beside whatever budget a search runs in
PROJECTION_BLOCK_BYTES = 32 * 2**20


def _solver_memory(solver: str, n: int, d: int, dim: int) -> int:
    """Bytes a path holds besides its chunk of rows."""
    if solver == "covariance":  # float64 sums, a float32 chunk product, eigenvectors
        return 12 * d * d + 8 * d * dim
    if solver == "gram":  # float64 Gram + eigenvectors, then eigenvectors + float64 components, then those + float32
        return max(8 * n * n + 8 * n * dim, 8 * d * dim + 8 * n * dim, 12 * d * dim)
    return 20 * d * min(d, n, 2 * dim)  # float32 basis, float64 product, and a float64 temporary or its QR


def _chunks_held(solver: str) -> int:
    return 2 if solver == "gram" else 1  # the Gram path holds two chunks of rows


def _path_need(solver: str, rows, dim: int) -> int:
    """The least budget `solver`'s path takes on `rows`: what it holds, and its chunks of one row."""
    return (_solver_memory(solver, rows.row_count, rows.dim, dim)
            + ROW_COPIES * read_bytes_per_row(rows) * _chunks_held(solver))


def _exact_path(rows) -> str:
    """The exact path on the smaller side: D x D when D <= N, else N x N."""
    return "covariance" if rows.dim <= rows.row_count else "gram"


def _flip(components: np.ndarray) -> None:
    """sklearn's svd_flip(u_based_decision=False), in place: each row's largest-|.| entry positive.
    Row by row: |components| at once would be one more dim x D matrix than the budget holds."""
    for row in components:
        if row[np.argmax(np.abs(row))] < 0:
            row *= -1


def _top_eigen(matrix: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Largest `dim` eigenvalues (descending) and their eigenvectors (columns) of a symmetric matrix."""
    from scipy.linalg import eigh

    size = matrix.shape[0]
    # LAPACK reads Fortran order: it would copy a C-ordered matrix (the Gram matrix of the urban stack, 1.1 GB),
    # while the transpose view is that order already, and its upper triangle is this matrix's lower one
    values, vectors = eigh(matrix.T, lower=False, subset_by_index=[size - dim, size - 1], overwrite_a=True,
                           check_finite=False)
    return values[::-1], vectors[:, ::-1]


class PCAWhitening:
    """The post-processor of AnyLoc's -PCA presets: fit on database rows, transform any rows;
    its state is plain numpy arrays (see `vprbench.methods.base.PostProcessor`)."""

    def __init__(self, dim: int = DEFAULT_PCA_DIM, *, seed: int = 0):
        if dim < 1:
            raise VPRBenchError(f"PCA dimension must be at least 1, got {dim}.")
        self.dim, self.seed = int(dim), int(seed)
        self.mean: np.ndarray | None = None
        self.projection: np.ndarray | None = None  # (dim, D): components / sqrt(explained variance)

    # ------------------------------------------------------------ planning
    def solver(self, rows, memory_budget: int) -> str:
        """The exact path on the smaller side when it fits the budget (with one chunk of rows),
        else the randomized one."""
        return _exact_path(rows) if self.exact_memory(rows) <= memory_budget else "randomized"

    def exact_memory(self, rows) -> int:
        """The least budget the exact path on the smaller side takes (with one chunk of rows)."""
        return _path_need(_exact_path(rows), rows, self.dim)

    def least_budget(self, rows, memory_budget: int) -> int:
        """The least budget a fit on `rows` (their shape only) takes: the exact path's where `memory_budget`
        holds it (the path taken there), else the smaller of the two paths' (below the exact one's, the
        randomized one is taken). The run's budget plan reads it before the fit; `check_budget` refuses below it."""
        exact = self.exact_memory(rows)
        if exact <= parse_memory(memory_budget):
            return exact
        return min(exact, _path_need("randomized", rows, self.dim))

    def output_dim(self, rows) -> int:
        """The dimension of the rows it makes, known before the fit (the run's budget plan reads it)."""
        return self.dim

    def state_bytes(self, rows) -> int:
        """Bytes of the state a fit on `rows` keeps (a float32 mean and projection), known before the fit."""
        return 4 * rows.dim * (self.dim + 1)

    def check_budget(self, rows, memory_budget: int) -> tuple[str, int]:
        """(solver, rows per chunk) of a fit on `rows` (a row source, or only its shape) within the budget, or
        a clear error when even the randomized path does not fit: said before the rows are described."""
        n, d, budget = rows.row_count, rows.dim, parse_memory(memory_budget)
        solver = self.solver(rows, budget)
        row_cost = ROW_COPIES * read_bytes_per_row(rows)
        blocks = _chunks_held(solver)
        # a chunk of one row at the path's least need, one more row for each row's cost beyond it
        spare = budget - _path_need(solver, rows, self.dim)
        chunk_rows = min(READ_BYTES // row_cost, 1 + spare // (row_cost * blocks))
        tile = fit_tile(rows)
        chunk_rows -= chunk_rows % tile if chunk_rows >= tile else 0  # whole tiles (a tighter budget: smaller sums)
        if chunk_rows < 1:
            raise VPRBenchError(
                f"A memory budget of {format_bytes(budget)} is too small to fit PCA-whitening of {n:,} x {d:,} "
                f"descriptors to {self.dim} dims: its {solver} path needs at least "
                f"{format_budget(_path_need(solver, rows, self.dim))}, the exact one "
                f"{format_budget(self.exact_memory(rows))}. Raise --search-memory (memory_budget).")
        return solver, int(chunk_rows)

    def key(self, rows, memory_budget: int = DEFAULT_MEMORY_BUDGET) -> dict:
        """What defines the fitted state (its file name in the store folder)."""
        solver = self.solver(rows, memory_budget)
        key = {"kind": "pca-whitening", "dim": self.dim, "solver": solver}
        if solver == "randomized":
            key.update(sketch=min(rows.dim, rows.row_count, 2 * self.dim), passes=PASSES, seed=self.seed)
        return key

    def check_rows(self, n: int, where: str = "the database") -> None:
        """Before any descriptor is computed: whitening to `dim` needs more than `dim` database rows
        (centred on their mean, N rows span at most N - 1 directions)."""
        if self.dim > n - 1:
            do = f"choose pca_dim <= {n - 1}" if n > 1 else "give at least 2 database images, or no PCA"
            raise VPRBenchError(f"PCA dimension {self.dim} is larger than the number of database images of {where} "
                                f"({n}) less one (centring leaves {max(n - 1, 0)} directions): {do}.")

    # ------------------------------------------------------------ fitting
    def fit(self, database, memory_budget=DEFAULT_MEMORY_BUDGET) -> "PCAWhitening":
        """Fit on database descriptors: an (N, D) array or a row source, streamed within the budget."""
        rows, budget = as_rows(database, "database descriptors"), parse_memory(memory_budget)
        n, d = rows.row_count, rows.dim
        if self.dim > min(n - 1, d):  # centred, N rows span at most N - 1 directions
            do = f"choose pca_dim <= {min(n - 1, d)}" if min(n - 1, d) > 0 else "give at least 2 database images, or no PCA"
            raise VPRBenchError(
                f"PCA dimension {self.dim} is larger than the number of database images ({n}) less one or the "
                f"descriptor dimension ({d}): {do}.")
        solver, chunk_rows = self.check_budget(rows, budget)
        if solver == "randomized":  # the exact fit is the one reproduced by any run, whatever its budget
            warnings.warn(f"PCA-whitening of {n:,} x {d:,} descriptors is fitted by randomized subspace iteration "
                          f"(approximate) within the {format_bytes(budget)} memory budget; a budget of "
                          f"{format_budget(self.exact_memory(rows))} (--search-memory) fits it exactly.", stacklevel=2)
        fit = {"covariance": _fit_covariance, "gram": _fit_gram, "randomized": _fit_randomized}[solver]
        mean, components, variances = fit(rows, self.dim, _Reads(int(chunk_rows), fit_tile(rows)), self.seed)
        floor = RANK_TOLERANCE * max(variances[0], 1e-300)
        if not variances[-1] > floor:
            rank = int(np.sum(variances > floor))
            raise VPRBenchError(f"The database descriptors vary along only {rank} directions; whitening to {self.dim} "
                                f"dims would divide by zero: choose pca_dim <= {rank}.")
        self.mean = mean.astype(np.float32)
        _flip(components)  # in place: the fits' own arrays, and a copy would be one matrix past the budget
        components /= np.sqrt(variances)[:, None]
        self.projection = components.astype(np.float32)
        return self

    # ------------------------------------------------------------ applying
    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, dim) float32, whitened and L2-normalised, row by row. Computed in
        float64 and rounded to float32 once: BLAS sums a row differently by its place in the
        matrix and by CPU (float32 results differ in the last bit), and float64's differences
        are 2^29 times smaller, so the rounded rows are the same wherever a row falls."""
        if self.projection is None:
            raise VPRBenchError("PCA-whitening was used before being fitted on database descriptors.")
        descriptors = np.asarray(descriptors)
        if descriptors.ndim != 2 or descriptors.shape[1] != self.projection.shape[1]:
            raise VPRBenchError(
                f"PCA was fitted on {self.projection.shape[1]}-dimensional descriptors, got shape {descriptors.shape}: "
                "fit it on descriptors of this method, or load the state fitted on them.")
        centred = descriptors.astype(np.float64)
        centred -= self.mean
        out = np.empty((len(centred), len(self.projection)))
        step = max(1, PROJECTION_BLOCK_BYTES // (8 * self.projection.shape[1]))
        for start in range(0, len(self.projection), step):  # by output columns: each value still sums a whole row
            out[:, start:start + step] = centred @ self.projection[start:start + step].astype(np.float64).T
        del centred
        out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
        return out.astype(np.float32)

    def state(self) -> dict[str, np.ndarray]:
        if self.projection is None:
            raise VPRBenchError("PCA-whitening has no state before it is fitted.")
        return {"pca_mean": self.mean, "pca_projection": self.projection}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        projection = np.asarray(state["pca_projection"], dtype=np.float32)
        mean = np.asarray(state["pca_mean"], dtype=np.float32)
        if projection.ndim != 2:
            raise VPRBenchError(f"Saved PCA state has a projection of shape {projection.shape}, expected ({self.dim}, D).")
        if projection.shape[0] != self.dim:
            raise VPRBenchError(f"Saved PCA state has {projection.shape[0]} dims, this PCA {self.dim}.")
        if mean.shape != projection.shape[1:]:  # a file rewritten by hand would fail deep in transform
            raise VPRBenchError(f"Saved PCA state has a mean of shape {mean.shape} for a projection of shape "
                                f"{projection.shape}: one mean per input dimension expected.")
        if not (np.isfinite(projection).all() and np.isfinite(mean).all()):
            raise VPRBenchError("Saved PCA state holds NaN or infinite values.")
        self.mean, self.projection = mean, projection


def fit_tile(rows) -> int:
    """Rows per sum and product of a fit on `rows` (FIT_TILE, or what 64 MiB reads): set by their shape."""
    return max(1, min(FIT_TILE, READ_BYTES // (ROW_COPIES * read_bytes_per_row(rows))))


class _Reads(NamedTuple):
    """How a fit reads its rows: `chunk` rows at a time, computed on tiles of `tile` rows."""
    chunk: int
    tile: int


def _shifted(rows, reads: _Reads):
    """(start, tile, shift): tiles of the rows minus `shift`, the first tile's mean (a shift keeps float32 sums
    well conditioned), read a chunk at a time and shifted in place; callers drop each chunk's tiles
    before the next is read."""
    shift = None
    for start, block in chunks(rows, reads.chunk):
        if shift is None:
            shift = block[:reads.tile].mean(axis=0, dtype=np.float64).astype(np.float32)
        block -= shift
        for at in range(0, len(block), reads.tile):
            yield start + at, block[at:at + reads.tile], shift
        del block


def _fit_covariance(rows, dim: int, reads: _Reads, seed: int):
    n, d = rows.row_count, rows.dim
    sums, products = np.zeros(d), np.zeros((d, d))
    for _, x, shift in _shifted(rows, reads):
        sums += x.sum(axis=0, dtype=np.float64)
        products += x.T @ x
        del x
    m = sums / n
    for i in range(0, d, 256):  # products -= n m m^T, a band at a time (no D x D temporary)
        products[i:i + 256] -= n * np.outer(m[i:i + 256], m)
    products /= n - 1
    variances, vectors = _top_eigen(products, dim)
    return shift + m, vectors.T, variances


def _fit_gram(rows, dim: int, reads: _Reads, seed: int):
    from scipy.linalg.blas import dgemm

    n, d = rows.row_count, rows.dim
    gram, sums = np.zeros((n, n)), np.zeros(d)
    for i, xi, shift in _shifted(rows, reads):
        sums += xi.sum(axis=0, dtype=np.float64)
        gram[i:i + len(xi), i:i + len(xi)] = xi @ xi.T
        for j in range(i + len(xi), n, reads.chunk):
            xj = np.asarray(rows.read_rows(j, min(j + reads.chunk, n)), dtype=np.float32)
            xj -= shift
            for at in range(j, j + len(xj), reads.tile):  # tile by tile, as every product of the fit
                block = xi @ xj[at - j:at - j + reads.tile].T
                gram[i:i + len(xi), at:at + len(block.T)] = block
                gram[at:at + len(block.T), i:i + len(xi)] = block.T
            del xj, block
        del xi
    means = gram.mean(axis=0)  # double centring: X_c X_c^T = J G J
    gram -= means[:, None]
    gram -= means[None, :]
    gram += means.mean()
    values, vectors = _top_eigen(gram, dim)
    del gram
    m = sums / n
    components = np.zeros((d, dim), order="F")
    for start, x, _ in _shifted(rows, reads):
        x -= m.astype(np.float32)
        # accumulated by BLAS in place: `components += x.T @ v` makes a D x dim temporary each chunk
        dgemm(1.0, x.astype(np.float64).T, vectors[start:start + len(x)], beta=1.0, c=components, overwrite_c=True)
        del x
    components /= np.sqrt(np.maximum(values, 1e-300))
    return shift + m, components.T, values / (n - 1)


def _gaussian(seed: int, d: int, sketch: int) -> np.ndarray:
    """`default_rng(seed).standard_normal((d, sketch))` drawn straight into Fortran order, a band of
    rows at a time (the same values): QR copied the C-ordered one, 24 bytes a cell where the path holds 20."""
    rng, out = np.random.default_rng(seed), np.empty((d, sketch), order="F")
    for i in range(0, d, 1024):
        out[i:i + 1024] = rng.standard_normal((min(1024, d - i), sketch))
    return out


def _fit_randomized(rows, dim: int, reads: _Reads, seed: int):
    from scipy.linalg import qr

    n, d = rows.row_count, rows.dim
    sketch = min(d, n, 2 * dim)
    basis = qr(_gaussian(seed, d, sketch), mode="economic", overwrite_a=True, check_finite=False)[0].astype(np.float32)
    for p in range(PASSES):  # basis <- orth(C basis), C the covariance, never formed
        product, sums = np.zeros((d, sketch), order="F"), np.zeros(d)
        for _, x, shift in _shifted(rows, reads):
            sums += x.sum(axis=0, dtype=np.float64)
            product += x.T @ (x @ basis)
            del x
        m = sums / n
        product -= n * np.outer(m, m @ basis)
        product /= n - 1
        if p < PASSES - 1:
            basis = None  # freed before its successor is made
            basis = qr(product, mode="economic", overwrite_a=True, check_finite=False)[0].astype(np.float32)
    small = basis.T.astype(np.float64) @ product  # Rayleigh-Ritz on the final basis
    del product
    values, vectors = _top_eigen((small + small.T) / 2, dim)
    return shift + m, (basis @ vectors.astype(np.float32)).T, values


def pca_whiten(database: np.ndarray, queries: np.ndarray, dim: int = DEFAULT_PCA_DIM) -> tuple[np.ndarray, np.ndarray]:
    """Fit on `database`, return (database, queries) whitened to `dim` and L2-normalised
    (whole matrices in memory; pipelines use the post-processor hook instead)."""
    pca = PCAWhitening(dim).fit(database)
    return pca.transform(database), pca.transform(queries)
