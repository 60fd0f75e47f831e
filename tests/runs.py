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
