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
    return tomllib.loads(plans.read_text())["tables"]


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
        if column in dataset_manifests() and datasets != [column]:
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


def pca_stack(cell: Cell) -> list[str]:
    """The benchmarks whose databases the cell's PCA-whitening is fitted on: the evaluated one, or with
    pca_on = "domain" its domain's; none without PCA or on a dataset that is no benchmark."""
    from ..methods.anyloc_options import pca_datasets

    dataset = cell.spec.dataset
    if not cell.spec.options.get("pca_dim") or dataset.kind != "benchmark":
        return []
    joint = pca_datasets(cell.spec.options.get("pca_on", "database"), dataset.name)
    return joint[1] if joint else [dataset.name]


def stack_images(cell: Cell, names: list[str]) -> int:
    """The database images of `names` (the cell's dataset at its protocol, the others at their default)."""
    dataset = cell.spec.dataset
    return sum(_database_count(name, dataset.protocol if name == dataset.name else None) for name in names)


def _database_count(name: str, protocol) -> int:
    from ..datasets import dataset_manifest, find_protocol

    manifest = dataset_manifest(name)
    found = find_protocol(manifest, protocol)
    return found.database_count or (manifest.query_count if found.swap else manifest.database_count) or 0


#: what a cell lacks: (the thing, how to get it), e.g. ("dataset hawkins", "Download ...")
Need = tuple[str, str]


def row_source(row_weights: dict):
    """A plan row's `weights` (file + url, hub or page, as its authors publish it) as the resolver's source."""
    from ..weights import WeightSource

    return WeightSource(row_weights["file"], url=row_weights.get("url"), hub=row_weights.get("hub"),
                        page=row_weights.get("page"))


def placed_weights(row: dict, cache_dir=None) -> dict:
    """{"weights": path} for a row whose checkpoint has no download (a Google Drive page) once the file
    is where the dry run says to put it: the run cannot fetch it, and reproduce takes no weights option."""
    from ..weights import weights_folder

    source = row_source(row["weights"]) if row.get("weights") else None
    if source is None or source.url or source.hub:
        return {}
    path = weights_folder(cache_dir) / source.file_name
    return {"weights": str(path)} if path.is_file() else {}


def how_to_fetch(source, cache_dir=None) -> str:
    """Where the run reads `source`'s file, and how to put it there first (a compute node may be offline)."""
    from ..weights import hub_folder, weights_folder

    if source.url or source.hub:
        return f"download {source.where} into {weights_folder(cache_dir) if source.url else hub_folder(cache_dir)}"
    return (f"download it from {source.where} (no direct download) and put it at "
            f"{weights_folder(cache_dir) / source.file_name}")


def weights_for(row_weights: dict | None, cell: Cell, cache_dir=None) -> Need | None:
    """What is missing of the cell's weights (None: present, or not knowable before running)."""
    from ..features.catalogue import backbone_spec
    from ..methods.anyloc import AnyLoc
    from ..methods.registry import method_entry
    from ..weights import cached_weights, local_weights

    entry = method_entry(cell.spec.method)
    merged = {**entry.defaults, **cell.spec.given}
    if entry.factory is AnyLoc:
        spec = backbone_spec(merged.get("backbone", "dinov2_vitg14"))
        if merged.get("weights"):
            try:
                local_weights(spec.source, merged["weights"], f"backbone {spec.name}")
                return None
            except VPRBenchError as error:
                return f"weights {merged['weights']}", str(error)
        if cached_weights(spec.source, cache_dir) is not None:
            return None
        if spec.gated:
            return (f"weights of {spec.name}", f"gated, {spec.licence}: request access at {spec.page}; "
                    f"then downloaded from {spec.source.where} on first use")
        return f"weights {spec.file_name}", how_to_fetch(spec.source, cache_dir)
    if merged.get("weights") or not row_weights:
        return None
    # where the run looks, as it looks (not "pass weights=PATH": reproduce refuses method options)
    source = row_source(row_weights)
    return None if cached_weights(source, cache_dir) else (f"weights {source.file_name}", how_to_fetch(source, cache_dir))


def vocabulary_for(cell: Cell, cache_dir=None, given: dict | None = None) -> Need | None:
    """A domain or union vocabulary (`domain`: the paper's choice for the cell's dataset) that is
    neither cached nor released for the cell's features must be fitted first. `given`: the run's
    own locations ({"data-dir": ..., "cache-dir": ...}), carried into the fit command, which
    would otherwise fit from and into the default ones."""
    import shlex
    import warnings

    from ..methods.anyloc import VLADS, AnyLoc
    from ..methods.anyloc_vocabulary import (domain_names, find_vocabulary, is_released_setting, paper_vocabulary,
                                             released_path)
    from ..methods.registry import method_entry

    entry = method_entry(cell.spec.method)
    if entry.factory is not AnyLoc:
        return None
    options = {**entry.effective_defaults(), **cell.spec.options}  # a default is not written in a spec
    name = options.get("vocabulary")
    if options.get("aggregation") not in VLADS:
        return None
    if name == "domain":
        name = paper_vocabulary(cell.spec.dataset.name)
    if not isinstance(name, str) or name not in domain_names() and released_path(name) is None:
        return None  # fitted on the map at run time, or a file
    with warnings.catch_warnings():  # a preset's layer on another backbone: the same relative depth
        warnings.simplefilter("ignore")
        method = AnyLoc(**{**options, "vocabulary": "map"})  # the cell's features; nothing loads
    setting = (method.vocabulary_backbone, method.layer, method.facet, method.clusters)
    released = released_path(name, cache_dir) if is_released_setting(*setting, method.stride) else None
    if find_vocabulary(name, *setting, cache_dir, method.stride) or (released is not None and released.is_file()):
        return None  # cached, or the authors' release already here
    located = [(flag, shlex.quote(str(path))) for flag, path in (given or {}).items() if path is not None]
    where = "".join(f" --{flag} {path}" for flag, path in located)
    if released is not None:  # fetched before the run, as weights are (a compute node may be offline)
        # `vocabulary download` reads no data: only the cache it fills is carried into the command
        into = "".join(f" --{flag} {path}" for flag, path in located if flag == "cache-dir")
        return (f"the authors' vocabulary {name!r}", f"run 'vprbench vocabulary download{into}', or put the "
                f"release's c_centers.pt at {released}")
    if name not in domain_names():
        return None
    return (f"vocabulary {name!r} for {method.backbone} layer {method.layer} {method.facet} c{method.clusters}",
            f"run 'vprbench vocabulary fit --domain {name} --method {cell.spec.method} --backbone {method.backbone} "
            f"--layer {method.layer}{where}'")


class PaperRecords(StoredRecords):
    """Stored records as the paper's cells take them: a cell whose vocabulary is not here has none (a
    run without it fell back to the map's vocabulary, under the same spec, and is not the paper's run)."""

    def record(self, spec, options: dict | None = None) -> dict | None:
        if vocabulary_for(Cell(spec), self.settings.cache_dir) is not None:
            return None
        return super().record(spec, options)


def memory_for(cell: Cell, memory_budget: int | None = None) -> Need | None:
    """AnyLoc's PCA-whitening fitted exactly, as the authors' sklearn PCA: a memory budget too small for
    the database rows it is fitted on (their count from the manifests, their width from the features)
    is said before hours of description, not at the fit."""
    from ..aggregation.pca import PCAWhitening
    from ..evaluation.postprocess import RowShape
    from ..methods.anyloc import VLADS, AnyLoc
    from ..methods.anyloc_options import probe
    from ..methods.registry import method_entry
    from ..row_sources import DEFAULT_MEMORY_BUDGET, format_budget, format_bytes

    entry, names = method_entry(cell.spec.method), pca_stack(cell)
    # the cell's features, nothing loaded (a default is not written in a spec); None: an option its run refuses
    method = probe(AnyLoc, {**entry.effective_defaults(), **cell.spec.options}) if entry.factory is AnyLoc else None
    if method is None or not names:
        return None
    rows, dim = stack_images(cell, names), method.spec.width * (method.clusters if method.aggregation in VLADS else 1)
    need = PCAWhitening(method.pca_dim).exact_memory(RowShape({"count": rows, "dim": dim, "dtype": cell.spec.store_dtype}))
    budget = memory_budget or DEFAULT_MEMORY_BUDGET
    if need <= budget:
        return None
    return (f"memory for PCA-whitening of {rows:,} x {dim:,} descriptors",
            f"run with --search-memory {format_budget(need)} or more, so it is fitted exactly as the authors' sklearn "
            f"PCA ({format_bytes(budget)} given)")


def missing_for(cell: Cell, row_weights, data_dir=None, cache_dir=None, given: dict | None = None,
                memory_budget: int | None = None) -> list[Need]:
    """Everything the cell lacks on this machine, none when it can run (`given`: as vocabulary_for;
    `memory_budget`: the run's)."""
    from ..datasets import dataset_location, dataset_manifest
    from ..datasets.download import how_to_get

    needs = []
    if cell.spec.dataset.kind == "benchmark":  # with the other databases its PCA is fitted on (pca_on = "domain")
        for name in pca_stack(cell) or [cell.spec.dataset.name]:
            manifest = dataset_manifest(name)
            if not dataset_location(manifest, data_dir).is_dir():
                needs.append((f"dataset {name}", how_to_get(manifest, data_dir)))
    return needs + [need for need in (weights_for(row_weights, cell, cache_dir), vocabulary_for(cell, cache_dir, given),
                                      memory_for(cell, memory_budget)) if need]


def needs_text(needs: list[Need]) -> str:
    """The needs in one line, each with how to get it."""
    return "; ".join(f"{thing} ({how})" for thing, how in needs)


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
