"""Records -> a board of cells: which run fills which (row, dataset) cell, and which runs are left out.

The rules (stated on every published page, CELL_RULE):
- a row is a run spec without its dataset and K (`RunSpec.row_key`): a method with its options,
  its weights (files by content), search and store; rows whose weights are not the authors'
  release (or nothing learnt), whose search is approximate or whose store is reduced get marks
  of their own, so they never overwrite an official row;
- a benchmark column is one of the benchmark's protocols (datasets/protocol.py; the default one
  carries the dataset's name, a variant is "name [protocol]"): it takes only runs whose protocol
  hash is that protocol's, whose image counts are the protocol's, and on one copy of its data (the
  dataset fingerprint most runs share, the newest on a tie); own datasets get a column per
  protocol (their positions, radius and content), even one named like a benchmark;
- a cell is exactly one run: the newest eligible run that reports R@1 and R@5 (read from its
  per-query ranks when its search went deep enough), else the newest eligible run; or a deeper run
  of the row whose top-K lists are that run's as far as it searched (pick.py).
"""
from __future__ import annotations

import json
import reprlib
from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..errors import VPRBenchError
from ..evaluation.identity import benchmark_protocols
from ..evaluation.metrics import recall_at_k
from ..evaluation.proof import proven
from ..evaluation.results import per_query
from .escape import public
from .pick import CELL_KS, pick as pick_run  # noqa: F401 (CELL_KS: tables and downloads import it from here)
from .truth import judge
from .shown import RANDOM, TRANSDUCTIVE, hardware_of, random_weights, stage_marks, vocabulary_mark, weights_of

STRUCTURED = ("indoor", "urban", "outdoor")
UNSTRUCTURED = ("aerial", "subt", "degraded", "underwater")

CELL_RULE = (
    "Each cell is exactly one run: the newest run of that row (a method with its options, weights, search and "
    "store) on that dataset that reports R@1 and R@5, else its newest run; an older run of the row that reports "
    "more of R@1, R@5, R@10 and R@20 fills the cell instead when its top-K lists are that run's as far as that run "
    "searched (the same computation, re-run asking fewer K). A benchmark's column is one of its protocols (which "
    "images, which ground truth: its id and hash are on the dataset's page) and takes only runs on that protocol, "
    "with its image counts, and on one copy of its data (the dataset fingerprint most runs share; the newest on a "
    "tie). Runs on your own data get a column per protocol (positions, radius and images), "
    "even when named like a benchmark. Runs with weights other than the authors' release, with approximate "
    "search (IVF-PQ, HNSW), with a float16 store, with a vocabulary named as the authors' release that is not it (by "
    "sha256) or with anything fitted on the evaluated database (transductive) get "
    "their own rows, marked †, and never replace an official row; runs on random weights fill no cell at all. Every "
    "metric is recomputed from the run's per-query arrays (a record whose stored numbers disagree is named). Images/s "
    "comes from the newest run of the cell that computed its descriptors (one served from stores measured no speed; "
    "without one, from the newest such run of the row on the same images under another protocol), "
    "with the machine it ran on."
)


@dataclass(frozen=True)
class Row:
    key: str       # the spec's row key
    label: str
    weights: str   # 'official' or the weights source key
    mark: str      # what sets the row apart ('' for an official row)
    #: single-image, re-ranked or sequence: each track is a table of its own, never mixed
    track: str = "single-image"
    #: the marks of its search and store ('hnsw search; float16 store'): part of `mark`, not of its weights
    setting: str = ""

    @property
    def official(self) -> bool:
        return not self.mark

    @property
    def like_the_paper(self) -> bool:
        """Official, or set apart only by a part fitted on the evaluated database: as the paper's own
        methods are (AnyLoc's map and domain vocabularies, its PCA), so its numbers are compared here."""
        return self.mark in ("", TRANSDUCTIVE)

    @property
    def name(self) -> str:
        return self.label if self.official else f"{self.label} † {self.mark}"


@dataclass(frozen=True)
class Column:
    key: str       # unique: the dataset name, "<name> [<protocol>]" or "<name> (own <protocol hash>)"
    dataset: str
    kind: str      # "benchmark" or "own"
    domain: str
    fingerprint: str
    protocol: str = ""
    #: the benchmark's default protocol (the one the paper's tables use)
    default: bool = True
    #: what tells an own column apart: e.g. "own, ±1 frame"
    detail: str = ""
    protocol_hash: str = ""

    @property
    def title(self) -> str:
        if self.kind != "benchmark":
            return f"{self.dataset} ({self.detail or 'own data'})"
        return self.dataset if self.default else f"{self.dataset} [{self.protocol}]"

    @property
    def slug(self) -> str:
        """The column's page, figures and downloads are named by it (file names, link targets): a
        safe name, an own dataset's by its last folder name (escape.public)."""
        from ..paths import safe_name

        if self.kind != "benchmark":
            return f"own-{safe_name(public(self.dataset), 40)}-{self.protocol_hash[:8]}"
        return safe_name(self.dataset if self.default else f"{self.dataset}-{self.protocol}")


@dataclass
class Cell:
    row: Row
    column: Column
    record: dict
    #: other eligible runs of the same row and column (older, without R@5, or re-runs asking fewer K)
    passed_over: int = 0
    #: the newest run of the row and column that computed its descriptors (its images/s and
    #: hardware are the cell's): a run served from stores measured no speed
    timed: dict | None = None
    #: where the cell's number comes from (MEASURED, CONTRIBUTED, AGREES, IMPORTED or a disagreement)
    source: str = "measured here"

    @property
    def images_per_second(self) -> float | None:
        return (self.timed or {}).get("images_per_second")

    @property
    def hardware(self) -> str:
        """The machine the cell's speed was measured on, e.g. 'Intel Xeon (2 cores), no GPU'."""
        return hardware_of(self.timed) if self.timed else ""

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
            return recall_at_k(self.arrays["first_positive_rank"], [k])[k]
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
        return [r for r in self.rows if label in (r.label, r.name, r.key)]

    @property
    def tracks(self) -> list[str]:
        from ..stages.base import TRACKS

        return [t for t in TRACKS if any(r.track == t for r in self.rows)]

    def of_track(self, track: str) -> "Board":
        """The board of one track only (its rows, their cells, the columns they fill): a run never
        appears in another track's table."""
        rows = [r for r in self.rows if r.track == track]
        cells = {key: cell for key, cell in self.cells.items() if key[0].track == track}
        filled = {key for _, key in cells}
        # the single-image board (the overview, the terminal's default) names every run left out; another, its own
        excluded = self.excluded if track == "single-image" else \
            [(record, why) for record, why in self.excluded if record.get("track") == track]
        return Board(rows, [c for c in self.columns if c.key in filled], cells, excluded)

    def of_column(self, column: Column) -> "Board":
        """The board of one column, as its dataset page shows it: its cells, their rows, and the runs
        left out on its dataset (own data and a benchmark of the same name are told apart)."""
        cells = {key: cell for key, cell in self.cells.items() if key[1] == column.key}
        rows = [r for r in self.rows if (r, column.key) in cells]
        excluded = [(record, why) for record, why in self.excluded if record.get("dataset") == column.dataset
                    and (record.get("dataset_kind") == "own") == (column.kind == "own")]
        return Board(rows, [column], cells, excluded)

    @property
    def marked(self) -> dict[str, int]:
        """How many cells are not on official weights, or not on a benchmark, and how many runs are left
        out: the board's (a page's note counts those of the board it shows, tables.marks_note)."""
        cells = list(self.cells.values())
        return {"marked_rows": sum(not c.row.official for c in cells),
                "own_data": sum(c.column.kind == "own" for c in cells), "excluded": len(self.excluded)}


def _column_of(record: dict) -> tuple[str, str, bool] | str:
    """(kind, protocol name, is the default protocol), or the reason the run fills no cell."""
    found = record.get("protocol") or {}
    if record.get("dataset_kind") == "own":
        return "own", str(found.get("name", "own")), True
    if record.get("dataset_kind") != "benchmark":
        return f"dataset {record['dataset']!r} was built by hand (protocol {found.get('id', '?')}): it fills no cell"
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


def own_detail(record: dict) -> str:
    """'own, ±1 frame' / 'own, 25 m': what an own column's protocol is, in its heading."""
    gt = record.get("ground_truth") or {}
    radius, unit = gt.get("radius"), gt.get("radius_unit") or gt.get("unit") or ""
    if radius is None:
        return "own data"
    value = f"{radius:g}" if isinstance(radius, (int, float)) else str(radius)
    if unit == "frames":
        return f"own, ±{value} frame{'' if value == '1' else 's'}"
    return f"own, {value} {'m' if unit == 'metres' else unit}".rstrip()


def row_of(record: dict) -> Row:
    from ..spec import RunSpec

    spec = RunSpec.model_validate(record["spec"])
    weights, mark = weights_of(record)
    transductive = (record.get("provenance") or {}).get("fitted_on_evaluated_database") is True
    marks = [m for m in (mark, vocabulary_mark(record), *stage_marks(record), *spec.marks(),
                         TRANSDUCTIVE if transductive else "") if m]
    track = record.get("track") or "single-image"  # records before stages had none
    return Row(spec.row_key, public(spec.label()), weights, "; ".join(marks), track, "; ".join(spec.marks()))


def build_board(records: list[dict], truth=None, refused: list | None = None) -> Board:
    """Apply the rules above to every record (oldest first, as read_results gives them). With `truth`
    (truth.LocalTruth), each run is re-scored from its top-K indices against its ground truth first: one
    that does not re-score to its numbers fills no cell, its file appended to `refused`."""
    if not isinstance(records, (list, tuple)) or not all(isinstance(r, dict) for r in records):
        raise VPRBenchError("The leaderboard is built from a list of result records: pass "
                            f"vprbench.evaluation.read_results(cache_dir); got {type(records).__name__} "
                            f"{reprlib.repr(records)}.")
    excluded: list[tuple[dict, str]] = []
    placed: list[tuple[dict, Row, Column]] = []
    for record in records:
        checked = proven(record)  # every metric from the run's per-query arrays
        if isinstance(checked, str):
            excluded.append((record, checked))
            continue
        record = checked
        if random_weights(record):
            excluded.append((record, RANDOM))
            continue
        found = _column_of(record)
        if isinstance(found, str):
            excluded.append((record, found))
            continue
        kind, protocol, default = found
        judged = judge(record, truth, refused)  # re-scored against its ground truth, or said not to be
        if isinstance(judged, str):
            excluded.append((record, judged))
            continue
        record = judged
        name, fingerprint = record["dataset"], str(record.get("dataset_fingerprint", ""))
        protocol_hash = str((record.get("protocol") or {}).get("hash", ""))
        if kind == "benchmark":
            key, detail = (name if default else f"{name} [{protocol}]"), ""
        else:
            key, detail = f"{name} (own {protocol_hash[:8]})", own_detail(record)
        column = Column(key, name, kind, str(record.get("domain") or ""), fingerprint, protocol, default, detail,
                        protocol_hash)
        placed.append((record, row_of(record), column))

    # one copy of each benchmark column's data: the fingerprint most runs share (the newest on a tie)
    chosen: dict[str, str] = {}
    for key in {c.key for _, _, c in placed if c.kind == "benchmark"}:
        prints = [c.fingerprint for _, _, c in placed if c.key == key]
        counts = Counter(prints)
        newest = {fp: i for i, fp in enumerate(prints)}
        chosen[key] = max(counts, key=lambda fp: (counts[fp], newest[fp]))

    columns: dict[str, Column] = {}
    candidates: dict[tuple[Row, str], list[dict]] = {}
    declared = {row.key for _, row, _ in placed if row.weights != "undeclared"}
    for record, row, column in placed:
        if row.weights == "undeclared" and row.key in declared:
            excluded.append((record, "its method did not declare its weights then; a later run of the same method "
                                     "declares them (provenance()) and replaces this row"))
            continue
        if column.kind == "benchmark" and column.fingerprint != chosen[column.key]:
            excluded.append((record, f"dataset fingerprint {column.fingerprint} differs from the {chosen[column.key]} "
                                     f"the other {column.key} runs share (another copy of its images or ground truth)"))
            continue
        columns.setdefault(column.key, column)
        candidates.setdefault((row, column.key), []).append(record)

    rows = _distinct(sorted({row for row, _ in candidates}, key=lambda r: (not r.official, r.label, r.mark, r.key)))
    columns = _distinct_titles(columns)
    # a speed belongs to a row and the images it described, whichever protocol judged the run
    timed_on: dict[tuple[str, str], list[dict]] = {}
    for (row, _), runs in candidates.items():
        for r in runs:
            if _timed(r):
                timed_on.setdefault((row.key, _images(r)), []).append(r)
    cells = {}
    for (row, key), runs in candidates.items():
        pick = pick_run(runs)
        final = rows[row]
        timed = [r for r in runs if _timed(r)] or sorted(timed_on.get((row.key, _images(pick)), []),
                                                         key=lambda r: str(r.get("created")))
        cells[(final, key)] = Cell(final, columns[key], pick, passed_over=len(runs) - 1,
                                   timed=timed[-1] if timed else None, source=_source(pick, runs))
    ordered = sorted(columns.values(), key=lambda c: (c.kind != "benchmark", _domain_order(c.domain), c.dataset, c.key))
    return Board(list(rows.values()), ordered, cells, [(record, public(why)) for record, why in excluded])


def _timed(record: dict) -> bool:
    """The run computed its descriptors and measured their speed (one served from stores did not)."""
    return not record.get("served_from_store") and bool(record.get("images_per_second"))


def _images(record: dict) -> str:
    """The identity of the images a run described (its dataset fingerprint without the ground truth)."""
    images = (record.get("dataset_fingerprints") or {}).get("images")
    return json.dumps(images, sort_keys=True) if images else f"dataset {record.get('dataset_fingerprint')}"


#: the marks of a cell's source: every cell has one of them (a paper's values are in the group tables, in italics)
MEASURED, CONTRIBUTED, IMPORTED = "measured here", "contributed, re-scored", "imported from VPR-Bench, re-scored"
AGREES = "contributed, re-run here and agreeing within its interval"


def _source(pick: dict, runs: list[dict]) -> str:
    """How the cell's number is known: measured on this machine, contributed to a results repository
    (re-scored from its arrays), both (agreeing within the contributed run's 95 % interval, or not)."""
    from .stats import bootstrap_ci
    from ..evaluation.blocks import for_record
    from ..evaluation.metrics import successes

    if pick.get("imported"):
        return IMPORTED
    contributed = [r for r in runs if r.get("_contribution")]
    local = [r for r in runs if not r.get("_contribution")]
    if not contributed:
        return MEASURED
    if not local:
        return CONTRIBUTED
    theirs, ours = contributed[-1], local[-1]
    arrays = per_query(theirs)
    if arrays is None or "1" not in ours["recall"]:  # R@1 of theirs comes from its arrays, kept with any K
        return f"contributed, re-run here (R@1 {ours['recall'].get('1', '–')}; the contributed run has no interval)"
    # the interval every page gives for that run: its dataset's units (blocks, places), not single queries
    low, high = bootstrap_ci(successes(arrays["first_positive_rank"], 1), for_record(theirs, arrays))
    mine = float(ours["recall"]["1"])
    if low <= mine <= high:
        return AGREES
    return f"contributed, re-run here and disagreeing: R@1 {mine:.1f} here, outside its interval [{low:.1f}, {high:.1f}]"


def _distinct(rows: list[Row]) -> dict[Row, Row]:
    """Each row as shown: rows whose names would read alike (another version of a preset) are told
    apart by their key."""
    names = Counter(r.name for r in rows)
    return {r: r if names[r.name] == 1 else Row(r.key, f"{r.label} #{r.key[:6]}", r.weights, r.mark, r.track, r.setting) for r in rows}


def _distinct_titles(columns: dict[str, Column]) -> dict[str, Column]:
    """Own columns whose headings would read alike are told apart by their protocol hash."""
    import dataclasses

    titles = Counter(c.title for c in columns.values())
    return {key: c if titles[c.title] == 1 or c.kind == "benchmark" else
            dataclasses.replace(c, detail=f"{c.detail or 'own'}, {c.protocol_hash[:8]}") for key, c in columns.items()}


def _domain_order(domain: str) -> int:
    order = STRUCTURED + UNSTRUCTURED
    return order.index(domain) if domain in order else len(order)
