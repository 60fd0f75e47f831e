"""A paper's table as a plan (manifests/reproduce/<paper>.toml): its cells, what each needs, and
the table again with measured values, deltas and 95% confidence intervals beside the reported ones.

Reported values come from `vprbench.reference.paper_results()`; nothing is copied.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib.resources import files

from ..errors import VPRBenchError
from ..reference import paper_results
from .plan import Cell, build_plan


@dataclass
class TableCell:
    row: str
    column: str
    cells: list[Cell] = field(default_factory=list)  # several for a per-domain mean
    reason: str = ""  # why it cannot run at all (no vprbench method)


def reproduce_tables(paper: str) -> dict:
    try:
        text = (files("vprbench.manifests") / "reproduce" / f"{paper}.toml").read_text()
    except FileNotFoundError:
        raise VPRBenchError(f"No reproduction plans for paper {paper!r}; available: anyloc.") from None
    return tomllib.loads(text)["tables"]


def table_spec(paper: str, table: str) -> dict:
    tables = reproduce_tables(paper)
    if str(table) not in tables:
        raise VPRBenchError(f"The {paper} paper has no table {table!r} here; tables: {', '.join(tables)}.")
    return tables[str(table)]


def _rows(spec: dict) -> list[dict]:
    if spec.get("rows_from") == "setting":
        reported = paper_results(table=spec["paper"])
        rows = []
        for label, setting in reported.drop_duplicates("row")[["row", "setting"]].itertuples(index=False):
            options = dict(spec.get("options", {}))
            for item in setting.split():
                key, _, value = item.partition("=")
                options[key] = int(value) if value.isdigit() else value
            rows.append({"row": label, "method": spec["method"], "options": options})
        return rows
    return spec["rows"]


def table_cells(paper: str, table: str, ks=(1, 5), *, settings: dict | None = None, data_dir=None,
                cache_dir=None) -> tuple[dict, list[TableCell]]:
    """The table's cells as run specs (the paper's settings; `settings` are run settings such as
    device or batch_size, which change no result)."""
    spec = table_spec(paper, table)
    out = []
    for row in _rows(spec):
        columns = row.get("cells") or {c: {"datasets": d} for c, d in spec["columns"].items()}
        for column, where in columns.items():
            if not row.get("method"):
                out.append(TableCell(row["row"], column, reason="no vprbench method matches this row"))
                continue
            options = {**row.get("options", {}), **where.get("options", {})}
            datasets = where.get("datasets") or [where["dataset"]]
            plan = build_plan({"methods": [{"name": row["method"], "options": options}], "datasets": datasets, "k": list(ks)},
                              f"{paper} table {table}", overrides={"options": dict(settings or {})}, data_dir=data_dir,
                              cache_dir=cache_dir)
            cells = [Cell(c.spec, c.settings, label=row["row"]) for c in plan.cells]
            out.append(TableCell(row["row"], column, cells))
    return spec, out


def weights_for(row_weights: dict | None, cell: Cell, cache_dir=None) -> str | None:
    """What is missing of the cell's weights (None: present, or not knowable before running)."""
    from ..features.catalogue import backbone_spec
    from ..methods.anyloc import AnyLoc
    from ..methods.registry import method_entry
    from ..paths import cache_root
    from ..weights import cached_weights, local_weights, weights_folder

    entry = method_entry(cell.spec.method)
    merged = {**entry.defaults, **cell.spec.given}
    if entry.factory is AnyLoc:
        spec = backbone_spec(merged.get("backbone", "dinov2_vitg14"))
        if merged.get("weights"):
            try:
                local_weights(spec.source, merged["weights"], f"backbone {spec.name}")
                return None
            except VPRBenchError as error:
                return str(error)
        if cached_weights(spec.source, cache_dir) is not None:
            return None
        return f"weights {spec.file_name} (download {spec.source.where} into {weights_folder(cache_dir)})"
    if merged.get("weights") or not row_weights:
        return None
    folder = cache_root(cache_dir) / row_weights["folder"] if "folder" in row_weights else weights_folder(cache_dir)
    found = list(folder.rglob(row_weights["file"])) if folder.is_dir() else []
    return None if found else f"weights {row_weights['file']} (from {row_weights['url']}, into {folder}, or pass weights=PATH)"


def vocabulary_for(cell: Cell) -> str | None:
    """A domain or union vocabulary that is neither cached nor released must be fitted first."""
    from ..methods.anyloc_vocabulary import domain_names, find_vocabulary, released_path
    from ..methods.registry import method_entry

    merged = {**method_entry(cell.spec.method).defaults, **cell.spec.given}
    name = merged.get("vocabulary")
    if name not in domain_names() or released_path(name) is not None or not str(merged.get("aggregation", "")).startswith("vlad"):
        return None
    layer = merged.get("layer") or int(str(merged.get("layer_for", ":31")).partition(":")[2])
    if find_vocabulary(name, merged.get("backbone", "dinov2_vitg14"), layer, merged.get("facet", "value"), merged.get("clusters", 32)):
        return None
    return f"vocabulary {name!r} (run 'vprbench vocabulary fit --domain {name} --method {cell.spec.method}')"


def missing_for(cell: Cell, row_weights, data_dir=None, cache_dir=None) -> str:
    """Everything the cell lacks on this machine, '' when it can run."""
    from ..datasets import dataset_location, dataset_manifest
    from ..datasets.download import how_to_get

    problems = []
    if cell.spec.dataset.kind == "benchmark":
        manifest = dataset_manifest(cell.spec.dataset.name)
        root = dataset_location(manifest, data_dir)
        if not root.is_dir():
            problems.append(f"dataset {cell.spec.dataset.name} ({how_to_get(manifest, root)})")
    for check in (weights_for(row_weights, cell, cache_dir), vocabulary_for(cell)):
        if check:
            problems.append(check)
    return "; ".join(problems)


def measured(records: list[dict | None], metric: str, seed: int = 0) -> tuple[float, float, float] | None:
    """(value, low, high): one dataset's recall, or the mean over a domain's datasets, with the
    seeded bootstrap interval the leaderboard uses; None unless every dataset was measured."""
    from ..evaluation.blocks import for_record
    from ..evaluation.metrics import successes
    from ..evaluation.proof import proven
    from ..evaluation.results import per_query
    from ..leaderboard.stats import bootstrap_mean_ci

    records = [proven(r) if r is not None else None for r in records]  # metrics from the runs' arrays
    if not records or any(r is None or isinstance(r, str) for r in records):
        return None
    k = int(metric.removeprefix("r"))
    values = [r["recall"][str(k)] for r in records]
    arrays = [per_query(r) for r in records]
    mean = sum(values) / len(values)
    if any(a is None for a in arrays):
        return mean, float("nan"), float("nan")
    low, high = bootstrap_mean_ci([successes(a["first_positive_rank"], k) for a in arrays],
                                  [for_record(r, a) for r, a in zip(records, arrays)], seed=seed)
    return mean, low, high


def reported_value(spec: dict, row: str, column: str, metric: str) -> float | None:
    frame = paper_results(table=spec["paper"])
    hit = frame[(frame["row"] == row) & (frame["column"] == column) & (frame["metric"] == metric)]
    return float(hit["value"].iloc[0]) if len(hit) else None
