"""Search and PCA-whitening workloads at benchmark size, each run in a fresh process.

`python tests/benchmarks/search_workloads.py make DATA_DIR` writes the seeded inputs into
DATA_DIR when they are missing (HDF5 files: a 1,000,000 x 512 database with 1,000 queries,
and 100,000 x 4,096 descriptors for PCA; the urban stack's 11,762 x 49,152 on its first use).
`... NAME DATA_DIR` runs one workload (see
WORKLOADS) and prints one JSON line: its time, the process's RSS when the workload starts (baseline: interpreter, libraries, open
files) and its peak RSS (the kernel's VmHWM, reset to the baseline through
/proc/self/clear_refs just before the workload runs).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import numpy as np
from memory import measured  # this folder is on sys.path (as a script and under pytest)

DB_ROWS, DIM, QUERIES, K = 1_000_000, 512, 1000, 20
PCA_ROWS, PCA_IN, PCA_OUT, EXACT_ROWS = 100_000, 4096, 512, 20_000
GENERATE_ROWS = 50_000


class H5Rows:
    """An HDF5 dataset as a row source (the shape a descriptor store exposes), optionally its first `stop` rows."""

    def __init__(self, path: Path, stop: int | None = None):
        self.file = h5py.File(path, "r")
        self.data = self.file["descriptors"]
        self.row_count = int(stop or self.data.shape[0])
        self.dim, self.dtype, self.folder = int(self.data.shape[1]), self.data.dtype, None

    def read_rows(self, start, stop):
        out = np.empty((stop - start, self.dim), dtype=np.float32)
        self.data.read_direct(out, np.s_[start:stop])
        return out

    def read_rows_at(self, indices):
        return self.data[np.asarray(indices)].astype(np.float32)


def _write(path: Path, rows: int, dim: int, block) -> None:
    """Rows generated GENERATE_ROWS at a time by block(i, n), each block seeded by its number."""
    partial = path.with_suffix(".partial")
    with h5py.File(partial, "w") as f:
        data = f.create_dataset("descriptors", shape=(rows, dim), dtype="float32", chunks=(min(rows, 1024), dim))
        for i, start in enumerate(range(0, rows, GENERATE_ROWS)):
            n = min(GENERATE_ROWS, rows - start)
            x = block(i, n)
            data[start:start + n] = x / np.linalg.norm(x, axis=1, keepdims=True)
    partial.replace(path)


def make_inputs(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    centres = np.random.default_rng(0).normal(size=(1000, DIM)).astype(np.float32)
    if not (folder / "database.h5").is_file():  # clustered unit vectors, like place descriptors
        def places(i, n):
            rng = np.random.default_rng([1, i])
            return centres[rng.integers(0, len(centres), n)] + 1.5 * rng.normal(size=(n, DIM)).astype(np.float32)
        _write(folder / "database.h5", DB_ROWS, DIM, places)
    if not (folder / "queries.h5").is_file():  # other views of 1,000 database places
        rows = np.sort(np.random.default_rng(2).choice(DB_ROWS, QUERIES, replace=False))
        with h5py.File(folder / "database.h5", "r") as f:
            seen = f["descriptors"][rows]
        _write(folder / "queries.h5", QUERIES, DIM,
               lambda i, n: seen + 0.05 * np.random.default_rng(3).normal(size=seen.shape).astype(np.float32))
    if not (folder / "pca.h5").is_file():  # a spectrum decaying like 1/i in a random basis, offset mean
        basis = np.linalg.qr(np.random.default_rng(4).normal(size=(PCA_IN, PCA_IN)))[0].astype(np.float32)
        scale = (np.arange(1, PCA_IN + 1) ** -0.5).astype(np.float32)

        def spectrum(i, n):
            z = np.random.default_rng([5, i]).normal(size=(n, PCA_IN)).astype(np.float32)
            return (z * scale) @ basis.T + 0.3 * basis[:, 0]
        _write(folder / "pca.h5", PCA_ROWS, PCA_IN, spectrum)


# ---------------------------------------------------------------- workloads
def _exact_chunked(folder: Path):
    from vprbench.search.exact import exact_search

    database, queries = H5Rows(folder / "database.h5"), H5Rows(folder / "queries.h5")

    def run():
        result = exact_search(database, queries, K)  # default memory budget
        np.save(folder / "exact-indices.npy", result.indices)
        return {"info": result.info}
    return run


def _flat_full(folder: Path):
    import faiss

    database, queries = H5Rows(folder / "database.h5"), H5Rows(folder / "queries.h5")

    def run():
        index = faiss.IndexFlatIP(DIM)
        index.add(database.read_rows(0, DB_ROWS))  # the whole database in memory, copied into faiss
        _, indices = index.search(queries.read_rows(0, QUERIES), K)
        exact = np.load(folder / "exact-indices.npy")
        return {"top1_equal_to_chunked": float(np.mean(indices[:, 0] == exact[:, 0])),
                "topk_equal_to_chunked": float(np.mean(indices == exact))}
    return run


def _ivf_pq(folder: Path):
    from vprbench.evaluation.retrieve import retrieve

    database, queries = H5Rows(folder / "database.h5"), H5Rows(folder / "queries.h5")

    def run():
        result = retrieve(None, database, queries, K, index="ivf-pq")
        exact = np.load(folder / "exact-indices.npy")
        overlap = np.mean([len(np.intersect1d(a, e)) / K for a, e in zip(result.indices, exact)])
        return {"info": result.info, "all_queries": {"r1_agreement": float(np.mean(result.indices[:, 0] == exact[:, 0])),
                                                     "topk_overlap": float(overlap)}}
    return run


def _pca(folder: Path, rows: int, budget: int, name: str):
    from vprbench.aggregation import PCAWhitening

    source = H5Rows(folder / "pca.h5", stop=rows)

    def run():
        pca = PCAWhitening(PCA_OUT)
        solver = pca.solver(source, budget)
        pca.fit(source, budget)
        np.savez(folder / f"{name}.npz", **pca.state())
        return {"solver": solver, "rows": rows, "budget": budget}
    return run


def _pca_sklearn(folder: Path):
    from sklearn.decomposition import PCA

    source = H5Rows(folder / "pca.h5", stop=EXACT_ROWS)

    def run():
        fitted = PCA(PCA_OUT, svd_solver="full", whiten=True).fit(source.read_rows(0, EXACT_ROWS))
        np.savez(folder / "pca-sklearn-20k.npz", pca_mean=fitted.mean_,
                 pca_projection=fitted.components_ / np.sqrt(fitted.explained_variance_)[:, None])
        return {"rows": EXACT_ROWS}
    return run


#: the urban domain's databases (Oxford, St Lucia, Pitts-30k) at AnyLoc-VLAD-DINOv2's width (32 x 1,536)
STACK_ROWS, STACK_IN, STACK_LATENT = (213, 1549, 10000), 49152, 2048


def _stack(folder: Path):
    """The three databases as row sources (HDF5 files written on first use, outside the timed run):
    a spectrum decaying like 1/i over 2,048 random directions, each database with its own mean."""
    from vprbench.evaluation.joint import JointRows

    paths = [folder / f"pca-stack-{i}.h5" for i in range(len(STACK_ROWS))]
    if not all(p.is_file() for p in paths):
        rng = np.random.default_rng(6)
        basis = (rng.normal(size=(STACK_LATENT, STACK_IN)) / np.sqrt(STACK_IN)).astype(np.float32)
        scale = (np.arange(1, STACK_LATENT + 1) ** -0.5).astype(np.float32)
        for i, (path, rows) in enumerate(zip(paths, STACK_ROWS)):
            offset = 0.2 * basis[i]
            _write(path, rows, STACK_IN, lambda b, n, i=i, offset=offset: (
                np.random.default_rng([7, i, b]).normal(size=(n, STACK_LATENT)).astype(np.float32) * scale) @ basis + offset)
    return JointRows([H5Rows(p) for p in paths])


def _pca_stack(folder: Path, budget: int, name: str):
    from vprbench.aggregation import PCAWhitening

    source = _stack(folder)

    def run():
        pca = PCAWhitening(PCA_OUT)
        solver = pca.solver(source, budget)
        pca.fit(source, budget)
        np.savez(folder / f"{name}.npz", **pca.state())
        return {"solver": solver, "rows": source.row_count, "dim": source.dim, "budget": budget}
    return run


WORKLOADS = {
    "pca-urban-stack": lambda folder: _pca_stack(folder, 1_200_000_000, "pca-urban-stack"),
    "pca-urban-stack-randomized": lambda folder: _pca_stack(folder, 1_100_000_000, "pca-urban-stack-randomized"),
    "exact-chunked": _exact_chunked,
    "flat-full": _flat_full,
    "ivf-pq": _ivf_pq,
    "pca-100k": lambda folder: _pca(folder, PCA_ROWS, 10**9, "pca-100k"),
    "pca-100k-randomized": lambda folder: _pca(folder, PCA_ROWS, 200 * 10**6, "pca-100k-randomized"),
    "pca-20k": lambda folder: _pca(folder, EXACT_ROWS, 10**9, "pca-20k"),
    "pca-20k-randomized": lambda folder: _pca(folder, EXACT_ROWS, 200 * 10**6, "pca-20k-randomized"),
    "pca-sklearn-20k": _pca_sklearn,
}


def tolerance(folder: Path, name: str, reference: str) -> dict:
    """Differences between two fitted PCA states on the first 2,000 rows (as queries) against
    the next 5,000 (as database): max |score difference| and max |whitened value difference|."""
    from vprbench.aggregation import PCAWhitening

    rows = (_stack(folder) if name.startswith("pca-urban") else H5Rows(folder / "pca.h5")).read_rows(0, 7000)
    out = {}
    for label, file in (("ours", name), ("reference", reference)):
        pca = PCAWhitening(PCA_OUT)
        with np.load(folder / f"{file}.npz") as saved:
            pca.load_state(dict(saved))
        out[label] = pca.transform(rows)
    (a, b) = out["ours"], out["reference"]
    scores = np.abs(a[:2000] @ a[2000:].T - b[:2000] @ b[2000:].T).max()
    return {"max_score_difference": float(scores), "max_value_difference": float(np.abs(a - b).max())}


def probe(name: str, folder: Path) -> dict:
    details, seconds, base, peak = measured(WORKLOADS[name](folder))
    return {"workload": name, "seconds": round(seconds, 3), "baseline_mb": round(base / 1024, 1),
            "peak_mb": round(peak / 1024, 1), "peak_above_baseline_mb": round((peak - base) / 1024, 1), **details}


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit("usage: search_workloads.py make DATA_DIR | tolerance DATA_DIR A B | CASE DATA_DIR")
    if sys.argv[1] == "make":
        make_inputs(Path(sys.argv[2]))
    elif sys.argv[1] == "tolerance":
        print(json.dumps(tolerance(Path(sys.argv[2]), sys.argv[3], sys.argv[4])))
    else:
        print(json.dumps(probe(sys.argv[1], Path(sys.argv[2])), default=str))
