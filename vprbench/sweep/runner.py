"""Run the cells of a sweep: skip complete ones, claim the rest, continue past failures, report.

Several processes may run the same cells on one cache at once (two GPUs, a SLURM array,
machines sharing a file system): each cell is claimed (claims.py) and evaluated exactly
once; a process that finds every remaining cell claimed by a live process waits for them,
and takes over the cell of a process that died once its lease expires.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from rich.table import Table
from rich.text import Text

from ..errors import VPRBenchError
from ..evaluation.results import save_result
from ..evaluation.served import find_result
from ..spec import RunSettings
from ..text import recall_text
from .claims import Claims
from .plan import Cell

RAN, SKIPPED, ELSEWHERE, FAILED, MISSING = "ran", "skipped", "done elsewhere", "failed", "missing"


@dataclass
class Outcome:
    cell: Cell
    status: str
    detail: str = ""
    record: dict | None = None
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)


def evaluate_cell(cell: Cell, settings: RunSettings, *, progress=None, context=None) -> dict:
    """The one entry point, with the cell's own run settings."""
    from ..evaluation import evaluate

    record = evaluate(cell.spec, settings.with_options(cell.settings), progress=progress)
    record.setdefault("context", {})["sweep"] = {"cell": cell.key, **(context or {})}
    return record


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if not isinstance(error, VPRBenchError) else text


def _minute(created: str | None) -> str:
    """'2026-12-03 00:25' of a record's ISO time (UTC), short enough for a table cell."""
    return (created or "?")[:16].replace("T", " ")


def run_cells(cells: list[Cell], settings: RunSettings | None = None, *, lease_s: float = 120.0, poll_s: float = 2.0,
              progress=None, plan: str = "", runnable=None, stored: "StoredRecords | None" = None) -> list[Outcome]:
    """Evaluate every cell once across all processes sharing the cache. `runnable(cell)` may
    return a reason not to run a cell here (reproduce: the dataset or weights are missing).
    `stored`: the lookup of cells' records to share with a caller (its datasets fingerprinted once).
    `progress` is a rich-style progress display (cli.progress makes one for terminals and for logs)."""
    settings = settings or RunSettings()
    cache_dir = settings.cache_dir
    if progress is None:
        from ..progress import Silent

        progress = Silent()
    claims, done = Claims(cache_dir, lease_s=lease_s), stored or StoredRecords(settings)
    outcomes: dict[str, Outcome] = {}
    pending = list({c.key: c for c in cells}.values())  # a plan may list a cell twice
    first_look = True
    try:
        with progress:
            overall = progress.add_task(f"cells of {plan or 'the sweep'}", total=len(pending))
            while pending:
                waiting = []
                for cell in pending:
                    reason = runnable(cell) if runnable else None
                    if reason:
                        outcomes[cell.key] = Outcome(cell, MISSING, reason)
                        progress.advance(overall)
                        continue
                    done.fingerprint(cell.spec)  # hashing a new copy's images: before the claim's lock, not under it
                    if done.may_hold(cell.spec):  # the method its record is checked against: made before the lock too
                        done.described_as(cell.spec)
                    found = []  # the record the claim found complete, looked up (and proven) once
                    state, detail = claims.claim(
                        cell.key, lambda c=cell: found.append(done.record(c.spec, c.settings)) or found[-1] is not None)
                    if state == "complete":
                        record = found[-1] if found else done.record(cell.spec, cell.settings)
                        status, why = (SKIPPED, f"already complete ({_minute(record.get('created'))})") if first_look \
                            else (ELSEWHERE, "evaluated by another process")
                        outcomes[cell.key] = Outcome(cell, status, why, record)
                    elif state == "failed":
                        outcomes[cell.key] = Outcome(cell, FAILED, detail)
                    elif state == "busy":
                        waiting.append(cell)
                        continue
                    else:
                        outcomes[cell.key] = _run_claimed(cell, claims, detail, settings, progress, plan)
                    progress.advance(overall)
                pending, first_look = waiting, False
                if pending:
                    progress.update(overall, description=f"cells of {plan or 'the sweep'} ({len(pending)} held by other processes)")
                    time.sleep(poll_s)
    finally:
        claims.close()
    return [outcomes[c.key] for c in {c.key: c for c in cells}.values()]


class StoredRecords:
    """A cell's stored record, if it was computed on the data at hand: a benchmark's spec names its
    protocol, not the bytes of the copy (an image or the ground truth edited, a file renamed)."""

    def __init__(self, settings: RunSettings):
        self.settings, self.fingerprints, self.methods, self.stacks = settings, {}, {}, {}

    def record(self, spec, options: dict | None = None) -> dict | None:
        """The newest record made for the computation this cell would make now: on the data at hand,
        by the method's code as it is (its store fingerprint), fitting the post-processing this cell's
        run settings (`options`, its plan entry's: the memory budget picks PCA's solver) would fit. None
        when the method cannot be made here (its factory, use_dataset, postprocessor or fingerprint fails)."""
        if not self.may_hold(spec):  # no method made (nor centres fetched) for a cell without records
            return None
        from ..evaluation.joint import stack_as_recorded
        from ..evaluation.postprocess import fits_as_recorded
        from ..row_sources import DEFAULT_MEMORY_BUDGET

        described, postprocessor = self.described_as(spec)
        if described is None:  # the method's identity cannot be checked now: no stored number; its run says why
            return None
        budget = self.settings.with_options(options or {}).memory_budget or DEFAULT_MEMORY_BUDGET
        stack = self.stacks.get((spec.key, spec.dataset.name))  # the databases its post-processor is fitted on
        return find_result(spec, self.settings.cache_dir, dataset_fingerprint=self.fingerprint(spec),
                           method_fingerprint=described,
                           accept=lambda record: fits_as_recorded(postprocessor, record, budget)
                           and stack_as_recorded(record, stack))

    def may_hold(self, spec) -> bool:
        """Whether the spec's results folder holds any record (a listing, nothing read)."""
        from ..evaluation.results import migrate_legacy, run_folder

        migrate_legacy(self.settings.cache_dir)  # 0.2's flat records into their folders first
        folder = run_folder(spec.dataset.protocol_hash, spec.row_key, self.settings.cache_dir)
        return folder.is_dir() and any(folder.glob("*.json"))

    def described_as(self, spec) -> tuple[dict | None, object]:
        """The store key the spec's method has now (`store.method_fingerprint`: what its descriptors depend
        on beyond the options, a version its author raised, a library's; a record made with another was
        computed by other code) and its post-processor (the databases it is fitted on kept in `stacks`).
        (None, None) when the method cannot be made here: no record answers then (the run says why)."""
        import warnings

        from ..evaluation.joint import stack_identity
        from ..evaluation.pipeline import create_run_method
        from ..loader import postprocessor_of
        from ..methods.attributes import use_dataset
        from ..store import method_fingerprint

        key = (spec.key, spec.dataset.name)
        if key not in self.methods:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the run says the method's notes
                    method = create_run_method(spec.method, spec.given, self.settings)
                    use_dataset(method, spec.dataset.name)
                    postprocessor = postprocessor_of(method)
                    self.stacks[key] = stack_identity(method, spec, self.settings)
                    self.methods[key] = method_fingerprint(method, spec.store_dtype, spec.options,
                                                           self.settings.cache_dir), postprocessor
            except Exception:  # noqa: BLE001 - a lookup: whatever stops the method here stops its run, which names it
                self.methods[key] = None, None
        return self.methods[key]

    def fingerprint(self, spec) -> str | None:
        """The content fingerprint of the spec's data as found now (never downloaded for this); None
        when it cannot be read (the run itself says why)."""
        from ..datasets import load_dataset

        if spec.dataset.kind != "benchmark":  # own: its protocol hash covers its content; given: no copy to read
            return None
        key = spec.dataset.model_dump_json()
        if key not in self.fingerprints:
            data = spec.dataset
            try:
                dataset = load_dataset(data.name, self.settings.data_dir, fetch=False, protocol=data.protocol,
                                       cache_dir=self.settings.cache_dir)
                self.fingerprints[key] = dataset.fingerprint(self.settings.cache_dir)
            except VPRBenchError:
                self.fingerprints[key] = None
        return self.fingerprints[key]


def _run_claimed(cell, claims, taken_over, settings, progress, plan) -> Outcome:
    started = time.perf_counter()
    try:
        record = evaluate_cell(cell, settings, progress=progress,
                               context={"plan": plan, "worker": claims.worker, **({"resumed": taken_over} if taken_over else {})})
        if not claims.keep_if_mine(cell.key, lambda: save_result(record, settings.cache_dir)):
            claims.forget(cell.key)  # this process stalled past its lease and the cell was taken over
            return Outcome(cell, ELSEWHERE, "lease lost while running; the other process's result counts")
    except (Exception, KeyboardInterrupt) as error:  # a failing cell must not stop the sweep
        if isinstance(error, KeyboardInterrupt):
            claims.release(cell.key)
            raise
        reason = _one_line(error)
        claims.release(cell.key, failure=reason)
        return Outcome(cell, FAILED, reason, seconds=time.perf_counter() - started)
    claims.release(cell.key)
    detail = "resumed: " + taken_over if taken_over else ""
    return Outcome(cell, RAN, detail, record, time.perf_counter() - started)


def summary_table(outcomes: list[Outcome], title: str = "Sweep"):
    """One line per cell; long details (a missing dataset's instructions, an error) follow the table once."""
    from ..leaderboard.shown import PIPELINE_CHECK, random_weights
    from ..notes import Notes

    notes = Notes()
    counts = {s: sum(o.status == s for o in outcomes) for s in (RAN, SKIPPED, ELSEWHERE, MISSING, FAILED)}
    table = Table(title=f"{title}: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n))
    # the K the cells asked (R@1 and R@5 alone left '--k 10 20' with two empty columns)
    ks = [str(k) for k in sorted({int(k) for o in outcomes for k in o.cell.spec.ks})]
    for column in ("method | dataset:protocol", "status", *(f"R@{k}" for k in ks), "computed", "detail"):
        table.add_column(column, overflow="fold")
    colour = {RAN: "green", SKIPPED: "cyan", ELSEWHERE: "cyan", MISSING: "yellow", FAILED: "red"}
    for o in outcomes:
        recall = (o.record or {}).get("recall", {})
        computed = (o.record or {}).get("descriptors_computed") if o.status == RAN else None
        detail = o.detail
        if o.record and random_weights(o.record):  # no result: its numbers fill no R@K column, the note keeps them
            checked = ", ".join(f"R@{k} {recall_text(recall[k])}" for k in ks if k in recall)
            detail = "; ".join(filter(None, [f"{PIPELINE_CHECK}{f' ({checked})' if checked else ''}", detail]))
            recall = {}
        table.add_row(o.cell.title(), Text(o.status, style=colour[o.status]),
                      *(recall_text(recall[k]) if k in recall else "" for k in ks),
                      f"{computed['database'] + computed['queries']}" if computed else "", notes.short(detail))
    return notes.below(table)
