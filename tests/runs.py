"""Evaluating a method object on a dataset object through the one entry point (tests build both by hand)."""
from __future__ import annotations

from vprbench.evaluation import evaluate
from vprbench.spec import RunSettings, spec_for


def evaluate_method(method, dataset, *, ks=None, cache_dir=None, index="exact", index_options=None,
                    store_dtype="float32", progress=None, ranks=None, **settings):
    """`vprbench.evaluate(spec_for(method, dataset, ...), RunSettings(...), dataset=..., method=...)`."""
    spec = spec_for(method, dataset, ks=ks, search={"index": index, "options": index_options or {}},
                    store_dtype=store_dtype, cache_dir=cache_dir)
    return evaluate(spec, RunSettings(cache_dir=cache_dir, **settings), dataset=dataset, method=method,
                    progress=progress, ranks=ranks)


def register_weighted_grey(scratch_methods) -> None:
    """Registers, in the test's own registry (`scratch_methods`), "weighted-grey": 4 x 4 grey thumbnails weighted
    by the .npy file its one option, `table`, names (a plugin whose fingerprint() does not name its file: the spec's
    files do)."""
    import numpy as np

    from vprbench.images import load_image
    from vprbench.methods.base import Method

    class Weighted(Method):
        def __init__(self, table: str = "", device: str = "cpu"):
            self.table = np.load(table)

        def describe(self, images):
            rows = np.stack([np.asarray(load_image(p, "L").resize((4, 4)), np.float32).ravel() * self.table
                             for p in images])
            return rows / np.linalg.norm(rows, axis=1, keepdims=True)

    scratch_methods.module.register_method("weighted-grey", Weighted)
