"""Records -> a board of cells: which run fills which (row, dataset) cell, and which runs are left out.

The rules (stated on every published page, CELL_RULE):
- a row is a method label (the method and the options set on top of its preset) with its
  weights: official weights (or a method without learnt weights) and every other weights source
  get rows of their own, so a user's or random weights never overwrite an official row;
- a benchmark column is one of the benchmark's protocols (datasets/protocol.py; the default one
  carries the dataset's name, a variant is "name [protocol]"): it takes only runs whose protocol
  hash is that protocol's, whose image counts are the protocol's, and on one copy of its data (the
  dataset fingerprint most runs share, the newest on a tie); own datasets get columns of their own,
  even one named like a benchmark;
- a cell is exactly one run: the newest eligible run that reports R@1 and R@5 (read from its
  per-query ranks when its search went deep enough), else the newest eligible run.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..evaluation.record import benchmark_protocols, per_query

#: options that change how a run is computed, not what it computes
UNLABELLED_OPTIONS = {"device", "batch_size", "weights"}
#: weights sources that make a row official: the authors' release, or nothing learnt at all
OFFICIAL_WEIGHTS = {"official", "none"}
#: the K a cell reports
CELL_KS = (1, 5)
STRUCTURED = ("indoor", "urban", "outdoor")
UNSTRUCTURED = ("aerial", "subt", "degraded", "underwater")

CELL_RULE = (
    "Each cell is exactly one run: the newest run of that method (with those options and weights) on that "
    "dataset that reports R@1 and R@5, else its newest run. A benchmark's column is one of its protocols "
    "(which images, which ground truth: its id and hash are on the dataset's page) and takes only runs on "
    "that protocol, with its image counts, and on one copy of its data (the dataset fingerprint most runs "
    "share; the newest on a tie). Runs on your own data get their own "
    "columns, even when named like a benchmark; runs with weights other than the authors' release get their "
    "own rows, marked, and never replace an official row."
)


def method_label(record: dict) -> str:
    """The method name, with the options the user set on top of its preset: ablations get rows of their own."""
    options = {k: v for k, v in (record.get("method_options") or {}).items() if k not in UNLABELLED_OPTIONS}
    if not options:
        return record["method"]
    shown = " ".join(f"{k}={'x'.join(map(str, v)) if isinstance(v, list) else v}" for k, v in sorted(options.items()))
    return f"{record['method']} [{shown}]"


def weights_of(record: dict) -> tuple[str, str]:
    """(key, mark): key 'official' for official rows, else one key per weights source;
    mark is the label shown beside a non-official row ('' for official)."""
    weights = (record.get("provenance") or {}).get("weights") or {}
    source = weights.get("source", "undeclared")
    if source in OFFICIAL_WEIGHTS:
        return "official", ""
    if source == "user":
        digest = str(weights.get("sha256", ""))[:12]
        return f"user:{digest}", f"user weights sha256:{digest}"
    if source == "random":
        return "random", "random weights"
    return source, f"weights {source}"


@dataclass(frozen=True)
class Row:
    label: str
    weights: str
    mark: str

    @property
    def official(self) -> bool:
        return self.weights == "official"

    @property
    def name(self) -> str:
        return self.label if self.official else f"{self.label} † {self.mark}"


@dataclass(frozen=True)
class Column:
    key: str       # unique: the dataset name, "<name> [<protocol>]" or "<name> (own <fingerprint>)"
    dataset: str
    kind: str      # "benchmark" or "own"
    domain: str
    fingerprint: str
    protocol: str = ""
    #: the benchmark's default protocol (the one the paper's tables use)
    default: bool = True

    @property
    def title(self) -> str:
        if self.kind != "benchmark":
            return f"{self.dataset} (own data)"
        return self.dataset if self.default else f"{self.dataset} [{self.protocol}]"

    @property
    def slug(self) -> str:
        if self.kind != "benchmark":
            return f"own-{self.dataset}-{self.fingerprint[:8]}"
        return self.dataset if self.default else f"{self.dataset}-{self.protocol}"


@dataclass
class Cell:
    row: Row
    column: Column
    record: dict
    #: other eligible runs of the same row and column (older, or without R@5)
    passed_over: int = 0

    @cached_property
    def arrays(self) -> dict[str, np.ndarray] | None:
        return per_query(self.record)

    def recall(self, k: int) -> float | None:
        """R@k of this run: as recorded, or from its per-query ranks when its search reached k."""
        found = (self.record.get("recall") or {}).get(str(k))
        if found is not None:
            return float(found)
        section = self.record.get("per_query") or {}
        if section.get("k", 0) >= k and self.arrays is not None:
            first = self.arrays["first_positive_rank"]
            return float(100.0 * np.mean((first >= 1) & (first <= k)))
        return None


@dataclass
class Board:
    rows: list[Row]
    columns: list[Column]
    cells: dict[tuple[Row, str], Cell]
    excluded: list[tuple[dict, str]] = field(default_factory=list)

    def cell(self, row: Row, column: Column) -> Cell | None:
        return self.cells.get((row, column.key))

    def column_cells(self, column: Column) -> list[Cell]:
        return [c for r in self.rows if (c := self.cell(r, column))]

    def find_row(self, label: str) -> list[Row]:
        return [r for r in self.rows if label in (r.label, r.name)]

    @property
    def marked(self) -> dict[str, int]:
        """How many cells are not on official weights, or not on a benchmark: shown on every page."""
        cells = list(self.cells.values())
        return {"non_official_weights": sum(not c.row.official for c in cells),
                "own_data": sum(c.column.kind == "own" for c in cells), "excluded": len(self.excluded)}


def _max_k(record: dict) -> int:
    ks = [int(k) for k in (record.get("recall") or {}) if str(k).isdigit()]
    return max([(record.get("per_query") or {}).get("k", 0), *ks], default=0)


def _column_of(record: dict) -> tuple[str, str, bool] | str:
    """(kind, protocol name, is the default protocol), or the reason the run fills no cell."""
    if int(record.get("schema_version", 1)) < 2:
        return ("recorded by vprbench 0.1, without protocol, dataset kind or weights provenance; "
                "rerun it to include it (its descriptors are served from the store)")
    found = record.get("protocol") or {}
    if record.get("dataset_kind", "own") != "benchmark":
        return "own", str(found.get("name", "own")), True
    known = benchmark_protocols(record["dataset"])
    if not known:
        return f"no benchmark is named {record['dataset']!r} in this vprbench"
    if found.get("hash") not in known:
        names = ", ".join(f"{p['name']} ({h})" for h, p in known.items())
        return (f"protocol {found.get('id', '?')} ({found.get('hash', 'no hash')}) is none of {record['dataset']}'s: "
                f"{names}" + ("; recorded before protocols existed, rerun it" if found.get("provisional") else ""))
    protocol = known[found["hash"]]
    counts = record.get("counts") or {}
    for split, key in (("database", "database"), ("queries", "queries")):
        expected = (protocol.get(split) or {}).get("count")
        if expected is not None and counts.get(key) != expected:
            return (f"{counts.get(key)} {split} images, but protocol {protocol['id']} has {expected}: "
                    "not a complete copy of the benchmark")
    return "benchmark", protocol["name"], found["hash"] == next(iter(known))


def build_board(records: list[dict]) -> Board:
    """Apply the rules above to every record (oldest first, as read_results gives them)."""
    excluded: list[tuple[dict, str]] = []
    placed: list[tuple[dict, Row, Column]] = []
    for record in records:
        found = _column_of(record)
        if isinstance(found, str):
            excluded.append((record, found))
            continue
        kind, protocol, default = found
        name, fingerprint = record["dataset"], str(record.get("dataset_fingerprint", ""))
        if kind == "benchmark":
            key = name if default else f"{name} [{protocol}]"
        else:
            key = f"{name} (own {fingerprint[:8]})"
        column = Column(key, name, kind, str(record.get("domain") or ""), fingerprint, protocol, default)
        key_, mark = weights_of(record)
        placed.append((record, Row(method_label(record), key_, mark), column))

    # one copy of each benchmark column's data: the fingerprint most runs share (the newest on a tie)
    chosen: dict[str, str] = {}
    for key in {c.key for _, _, c in placed if c.kind == "benchmark"}:
        prints = [c.fingerprint for _, _, c in placed if c.key == key]
        counts = Counter(prints)
        newest = {fp: i for i, fp in enumerate(prints)}
        chosen[key] = max(counts, key=lambda fp: (counts[fp], newest[fp]))

    columns: dict[str, Column] = {}
    candidates: dict[tuple[Row, str], list[dict]] = {}
    for record, row, column in placed:
        if column.kind == "benchmark" and column.fingerprint != chosen[column.key]:
            excluded.append((record, f"dataset fingerprint {column.fingerprint} differs from the {chosen[column.key]} "
                                     f"the other {column.key} runs share (another copy of its images or ground truth)"))
            continue
        columns.setdefault(column.key, column)
        candidates.setdefault((row, column.key), []).append(record)

    cells = {}
    for (row, key), runs in candidates.items():
        complete = [r for r in runs if _max_k(r) >= max(CELL_KS)]
        pick = (complete or runs)[-1]
        cells[(row, key)] = Cell(row, columns[key], pick, passed_over=len(runs) - 1)
    rows = sorted({row for row, _ in cells}, key=lambda r: (not r.official, r.label, r.weights))
    ordered = sorted(columns.values(), key=lambda c: (c.kind != "benchmark", _domain_order(c.domain), c.dataset, c.key))
    return Board(rows, ordered, cells, excluded)


def _domain_order(domain: str) -> int:
    order = STRUCTURED + UNSTRUCTURED
    return order.index(domain) if domain in order else len(order)
