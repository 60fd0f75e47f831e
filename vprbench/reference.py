"""Reported numbers of published papers, shipped as data (manifests/reference/*.csv).

Never measured here: pages and tables that show them label them as reported.
"""
from __future__ import annotations

import io
from functools import cache
from importlib.resources import files

import pandas as pd

from .errors import VPRBenchError
from .paths import shipped_file

COLUMNS = ["table", "row", "method", "column", "metric", "value", "setting", "source"]


@cache
def _read(name: str) -> pd.DataFrame:
    text = (files("vprbench.manifests") / "reference" / f"{name}.csv").read_text(encoding="utf-8")
    frame = pd.read_csv(io.StringIO(text), comment="#", dtype=str, keep_default_na=False)
    frame["value"] = frame["value"].astype(float)
    return frame[COLUMNS]


def paper_results(paper: str = "anyloc", table: str | None = None) -> pd.DataFrame:
    """One row per reported value: table (II..VII, ablation-facet, ablation-layer), row label,
    vprbench method name where one matches (else ""), column (dataset, domain or "dim"),
    metric (r1, r5, dim), value, setting and source (table and row, or the authors' file)."""
    shipped_file("reference", paper, "-paper.csv", "reported numbers for paper")  # a name, never a path
    frame = _read(f"{paper}-paper")
    tables = list(dict.fromkeys(frame["table"]))
    if table is not None and table not in tables:
        raise VPRBenchError(f"The {paper} paper has no table {table!r}; its tables: {', '.join(tables)}.")
    return (frame[frame["table"] == table] if table else frame).reset_index(drop=True)
