"""A paper's table as a plan (manifests/reproduce/<paper>.toml): its cells, what each needs, and
the table again with measured values, deltas and 95% confidence intervals beside the reported ones.

Reported values come from `vprbench.reference.paper_results()`; nothing is copied.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace

from ..errors import ProblemList, VPRBenchError, closest_names
from ..paths import shipped_file
from ..reference import paper_results
from .needs import pca_stack, placed_weights, stack_images, vocabulary_for
from .plan import Cell, build_plan
from .runner import StoredRecords


@dataclass
class TableCell:
    row: str
    column: str
    cells: list[Cell] = field(default_factory=list)  # several for a per-domain mean
    reason: str = ""  # why it cannot run as the paper ran it (no vprbench method, ...)


def reproduce_tables(paper: str) -> dict:
    plans = shipped_file("reproduce", paper, ".toml", "reproduction plans for paper")  # a name, never a path
    return tomllib.loads(plans.read_text(encoding="utf-8"))["tables"]


def table_spec(paper: str, table: str) -> dict:
    tables = reproduce_tables(paper)
    if str(table) not in tables:
        # the paper numbers its tables in Roman numerals (Table II): point from those to ours
        labels = {str(spec.get("paper", "")).lower(): name for name, spec in tables.items()}
        hint = labels.get(str(table).strip().lower()) or labels.get(f"ablation-{str(table).strip().lower()}")
        hint = f" Did you mean: {hint}?" if hint else closest_names(str(table), list(tables))
        raise VPRBenchError(f"The {paper} paper has no table {table!r} here; tables: {', '.join(tables)}.{hint}")
    spec = tables[str(table)]
    problems = plan_problems(spec, str(table))
    if problems:  # a reported value shown beside another row's, dataset's or metric's run, or none shown at all
        raise ProblemList(f"The reproduction plan of table {table} (manifests/reproduce/{paper}.toml) is inconsistent; "
                          "fix it:\n  " + "\n  ".join(problems))
    return spec


def plan_problems(spec: dict, name: str = "") -> list[str]:
    """What in a table's plan would run one thing under another's name: rows, columns and metrics the
    paper's table (the CSV) does not have or has beside them, a dataset column running another
    dataset, a domain column other datasets than the domain's. A plan that is no table of the paper
    (`paper` = its own `name`, as backbones) has nothing reported to pair. [] when consistent."""
    from ..datasets import dataset_manifests
    from ..methods.anyloc_vocabulary import vocabulary_policies

    def listed(value) -> bool:
        return isinstance(value, list) and bool(value) and all(isinstance(v, str) for v in value)

    problems = []
    metrics, columns = spec.get("metrics"), spec.get("columns", {})
    if not listed(metrics) or not all(m[:1] == "r" and m[1:].isdigit() for m in metrics):
        problems.append(f"metrics must be a list such as [\"r1\", \"r5\"]; got {metrics!r}")
    if not isinstance(columns, dict) or not all(listed(d) for d in columns.values()):
        return problems + [f"columns must map each column to a list of datasets; got {columns!r}"]
    rows = spec.get("rows", []) if spec.get("rows_from") != "setting" else []
    if spec.get("rows_from") == "setting" and not isinstance(spec.get("method"), str):
        problems.append("rows_from = \"setting\" needs the method the rows run")
    if spec.get("rows_from") != "setting" and (not isinstance(rows, list) or not rows) or \
            not all(isinstance(r, dict) and isinstance(r.get("row"), str) for r in rows):
        return problems + ["rows must be a list of tables, each with its row label (row = \"...\")"]
    labels = [r["row"] for r in rows]
    problems += [f"row {label!r} is there more than once" for label in dict.fromkeys(labels) if labels.count(label) > 1]
    used = dict(columns)
    for row in rows:
        for column, where in (row.get("cells") or {}).items():
            if not isinstance(where, dict) or not isinstance(where.get("dataset"), str):
                problems.append(f"row {row['row']!r}: cell {column!r} needs its dataset (dataset = \"...\")")
            elif "->" in row["row"] and where["dataset"] != row["row"].split("->")[-1]:  # vocabulary -> evaluated
                problems.append(f"row {row['row']!r}: cell {column!r} runs {where['dataset']}")
            else:
                used.setdefault(column, [where["dataset"]])
        if not row.get("cells") and not columns:
            problems.append(f"row {row['row']!r} has no columns (the table's columns, or cells of its own)")
        per_dataset = row.get("dataset_resize", False)
        if not isinstance(per_dataset, bool) or (per_dataset and "resize" in row.get("options", {})):
            problems.append(f"row {row['row']!r}: dataset_resize must be true or false, and not given with a resize "
                            "option")
    domains = {domain: {d for d, _ in members} for domain, members in vocabulary_policies()["domains"].items()}
    for column, datasets in columns.items():
        if len(set(datasets)) != len(datasets):  # a domain's mean would count that dataset twice
            problems.append(f"column {column!r} lists {', '.join(d for d in dict.fromkeys(datasets) if datasets.count(d) > 1)}"
                            " more than once")
        elif column in dataset_manifests() and datasets != [column]:
            problems.append(f"column {column!r} runs {', '.join(datasets)}: a dataset's column runs that dataset only")
        elif column in domains and set(datasets) != domains[column]:
            problems.append(f"column {column!r} runs {', '.join(datasets)}; the {column} domain is "
                            f"{', '.join(sorted(domains[column]))}")
    reported = paper_results()
    reported = reported[reported["table"] == spec.get("paper")]
    if not len(reported) and spec.get("paper") != name:
        tables = list(dict.fromkeys(paper_results()["table"]))
        problems.append(f"paper = {spec.get('paper')!r} is no table of the paper's reported numbers."
                        f"{closest_names(str(spec.get('paper')), tables)} (Tables: {', '.join(tables)}.)")
    if not len(reported) or problems:
        return problems
    extras = spec.get("reported_columns", [])
    for what, planned, paper in (
            ("row", set(labels) if rows else set(reported["row"]), set(reported["row"])),
            ("column", set(used) | set(extras), set(reported["column"])),
            ("metric", set(metrics) | set(extras), set(reported["metric"]))):
        problems += [f"{what} {item!r} is not in the paper's table {spec['paper']}.{closest_names(item, paper)}"
                     for item in sorted(planned - paper)]
        problems += [f"the paper's table {spec['paper']} has {what} {item!r}, which the plan leaves out"
                     for item in sorted(paper - planned)]
    return problems


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
                out.append(TableCell(row["row"], column, reason=row.get("reason", "no vprbench method matches this row")))
                continue
            options = {**row.get("options", {}), **where.get("options", {}), **placed_weights(row, cache_dir)}
            datasets = where.get("datasets") or [where["dataset"]]
            cells = []
            for group, resize in _resize_groups(row, datasets):
                given = {**options, **({"resize": list(resize)} if resize else {})}
                plan = build_plan({"methods": [{"name": row["method"], "options": given}], "datasets": group,
                                   "k": list(ks)}, f"{paper} table {table}", overrides={"options": dict(settings or {})},
                                  data_dir=data_dir, cache_dir=cache_dir)
                cells += [replace(c, label=row["row"]) for c in plan.cells]
            reason = next((r for r in map(cannot_run, cells) if r), "")
            out.append(TableCell(row["row"], column, [] if reason else cells, reason))
    return spec, out


def _resize_groups(row: dict, datasets: list[str]) -> list[tuple[list[str], tuple[int, int] | None]]:
    """(datasets, resize) runs of a cell: all at once, or, for a row with `dataset_resize = true` (a
    method the authors ran through their dataset loaders, which resize every image), each dataset at
    AnyLoc's size for it (vprbench.features.resize; None = as stored)."""
    if not row.get("dataset_resize"):
        return [(datasets, None)]
    from ..features.resize import dataset_resize

    return [([name], dataset_resize(name)) for name in datasets]


def cannot_run(cell: Cell) -> str:
    """Why the cell cannot run as the paper ran it, known before any image is read ('' if it can):
    PCA to more dimensions than the database images it is fitted on (the evaluated dataset's, or
    with pca_on=domain its domain's stacked, as the authors' code fitted it)."""
    dim, names = cell.spec.options.get("pca_dim"), pca_stack(cell)
    count = stack_images(cell, names)
    if not names or not count or dim < count:  # centred, N images span at most N - 1 directions
        return ""
    where = f"the databases of {', '.join(names)} hold" if len(names) > 1 else f"{names[0]} has"
    return (f"PCA to {dim} dimensions needs more than {dim} database images; {where} {count} (the authors' code fits "
            "this PCA jointly over its domain's datasets: pca_on = \"domain\")")


class PaperRecords(StoredRecords):
    """Stored records as the paper's cells take them: a cell whose vocabulary is not here has none (a
    run without it fell back to the map's vocabulary, under the same spec, and is not the paper's run)."""

    def record(self, spec, options: dict | None = None) -> dict | None:
        if vocabulary_for(Cell(spec), self.settings.cache_dir) is not None:
            return None
        return super().record(spec, options)


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
    frame = paper_results()  # all tables: a plan that is no table of the paper (backbones) finds nothing
    hit = frame[(frame["table"] == spec["paper"]) & (frame["row"] == row) & (frame["column"] == column)
                & (frame["metric"] == metric)]
    return float(hit["value"].iloc[0]) if len(hit) else None
