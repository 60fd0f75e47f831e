"""Cells proven by their content: before a benchmark run fills a cell, its top-K indices are
re-scored against the ground truth of the dataset on this machine with the code `vprbench results
verify` uses (evaluation/rescore.rescore, one function), so arrays rewritten consistently with their
sha256 and summary numbers cannot publish a score. A folder of one's own is re-read at the path its
record gives; so is a benchmark's copy when no data root is named and the default one has none (proven
the run's by its ground truth's fingerprint, never by its name). Where the ground truth is not here (no
copy of the dataset, another copy's ground truth, an own folder moved or changed) the cell is shown but
said not to be re-scored.

Cost: the protocol's ground truth is read once per protocol; a re-score is one pass over the top-K
lists (Pitts-250k's 8,280 queries x K=100 against 254,064 database images: well under a second).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import warnings

from ..errors import VPRBenchError
from ..evaluation.rescore import DataGroundTruth, Truth, rescore
from ..evaluation.results import per_query
from ..text import first_clause

#: a record that re-scores to its numbers / does not / could not be re-scored here
PROVEN, REFUSED, UNPROVEN = "proven", "refused", "unproven"
#: (the record as read, its arrays' sha256, the ground truth's fingerprint) -> verdict: repeated boards pay once
_CACHE: dict[tuple, tuple[str, str]] = {}


class LocalTruth:
    """The ground truth on this machine: a benchmark's under `data_dir` (else the default data root, else
    the copy its run read), and a folder of one's own at the path its record gives; each read once,
    positives and their fingerprint only (a benchmark's images may be absent; an own folder's are hashed
    once, as its protocol needs)."""

    def __init__(self, data_dir=None, cache_dir=None):
        self.benchmark, self.cache_dir, self._own = DataGroundTruth(data_dir, cache_dir, images=False), cache_dir, {}
        self.data_dir = data_dir  # named (--data-dir, $VPRBENCH_DATA): only that data root is looked in

    def __call__(self, record: dict):
        protocol_hash = str((record.get("protocol") or {}).get("hash"))
        root = str(record.get("dataset_root") or "")
        if record.get("dataset_kind") == "benchmark":
            try:
                return self.benchmark(record["dataset"], protocol_hash)
            except (VPRBenchError, OSError, ValueError):
                # no data root named and no copy in the default one: the copy this machine's run read, where
                # its record says. Never trusted by its name: against_truth compares its ground truth's
                # fingerprint with the run's (another copy there leaves the cell unproven, and says so)
                if self.data_dir is not None or record.get("_contribution") or not root or not os.path.isdir(root):
                    raise
                found = self._once(root, protocol_hash, lambda: self.benchmark(record["dataset"], protocol_hash, root))
                if isinstance(found, Exception):
                    raise  # the data root's reason: the run's folder is no copy of it either
                return found
        if record.get("_contribution"):  # a path from another machine's record: never read here
            raise VPRBenchError("a contributed run on data of its own, whose folder is not on this machine")
        found = self._once(root, protocol_hash, lambda: self._read_own(root, protocol_hash))
        if isinstance(found, Exception):
            raise found
        return found

    def _once(self, root: str, protocol_hash: str, read):
        """The ground truth of the folder `root` (or why not): a failure is remembered too, so a folder is read once."""
        if (root, protocol_hash) not in self._own:
            try:
                self._own[root, protocol_hash] = read()
            except (VPRBenchError, OSError, ValueError) as error:
                self._own[root, protocol_hash] = error
        return self._own[root, protocol_hash]

    def _read_own(self, root: str, protocol_hash: str):
        from ..datasets import load_dataset
        from ..evaluation.blocks import for_dataset

        if not root:
            raise VPRBenchError("its record names no folder")
        data = load_dataset(root, cache_dir=self.cache_dir)
        if data.protocol.get("hash") != protocol_hash:  # its images, positions or radius changed since the run
            raise VPRBenchError(f"the folder {root} now gives protocol hash {data.protocol.get('hash')}, not "
                                f"{protocol_hash}: it changed since the run")
        return Truth(data.protocol["id"], len(data.database), data.positives, for_dataset(data),
                     {"ground_truth": data.ground_truth_fingerprint()})


def against_truth(record: dict, truth) -> tuple[str, str]:
    """(PROVEN, ""), (REFUSED, why) or (UNPROVEN, why) for a record `proven` kept (its arrays fit it);
    `truth(record)` gives its ground truth (LocalTruth)."""
    try:
        gt = truth(record)
    except (VPRBenchError, OSError, ValueError) as error:  # no copy here: said, not hidden
        # its first clause ("Dataset 'x' is not in the data root /d"): the note lists it once per column
        return UNPROVEN, f"its ground truth is not here ({first_clause(str(error))})"
    given = (record.get("dataset_fingerprints") or {}).get("ground_truth")
    if given != gt.fingerprints["ground_truth"]:
        # it names another copy's positives: re-scoring it against these would judge it by other data
        return UNPROVEN, f"it was scored against another copy of {record['dataset']}'s ground truth than the one here"
    section = record.get("per_query") or {}
    key = None
    if section.get("file") and section.get("sha256"):  # per_query checks that sha256 on every read
        kept = {k: v for k, v in record.items() if k not in ("_source", "_proof", "_contribution")}
        key = (hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest(), given)
        if key in _CACHE:
            return _CACHE[key]
    arrays = per_query(record)
    if arrays is None:  # (proven read them a moment ago)
        return REFUSED, "its per-query arrays are missing or damaged"
    problems: list[str] = []
    rescore(record, arrays, dataclasses.replace(gt, fingerprints=None), problems)
    # the first two disagreements name the fault; `results verify` lists them all
    more = f"; and {len(problems) - 2} more" if len(problems) > 2 else ""
    verdict = (REFUSED, "; ".join(problems[:2]) + more) if problems else (PROVEN, "")
    if key is not None:
        _CACHE[key] = verdict
    return verdict


#: why a board built without `truth` (a library caller's build_board(records)) has no cell re-scored
NO_TRUTH = "the board was built without a ground truth (build_board(records, LocalTruth(data_dir)) re-scores them)"


def judge(record: dict, truth, refused: list | None) -> dict | str:
    """The record with its verdict in `_proof` (PROVEN, or why it was not re-scored), or the reason it
    fills no cell (its file appended to `refused`). Without `truth` every cell says so: truth_note is
    then never silent about numbers no ground truth checked."""
    verdict, why = against_truth(record, truth) if truth is not None else (UNPROVEN, NO_TRUTH)
    if verdict == REFUSED:
        if refused is not None:
            refused.append(record.get("_source") or record.get("run_id"))
        return refuse(record, why)
    return {**record, "_proof": {**(record.get("_proof") or {}), "ground_truth": why or PROVEN}}


def refuse(record: dict, why: str) -> str:
    """The reason a record fills no cell, warned naming its file."""
    where = record.get("_source") or f"run {record.get('run_id')}"
    reason = (f"its per-query top-K indices do not re-score to its numbers against the ground truth of "
              f"{record.get('dataset')} on this machine ({why}); 'vprbench results verify' says the same")
    warnings.warn(f"{where}: {reason}; it fills no cell.", stacklevel=4)  # the caller of build_board
    return reason


def truth_note(board) -> str:
    """Which cells were not re-scored against the ground truth here, and why ("" for a board of no cell)."""
    return cells_note(board.cells.values())


def unproven_note(cells) -> str:
    """cells_note when some of `cells` were not re-scored, else "" (compare says nothing of proven cells)."""
    return "" if all((c.record.get("_proof") or {}).get("ground_truth") == PROVEN for c in cells) else cells_note(cells)


def cells_note(cells) -> str:
    """truth_note of these cells."""
    cells = [c for c in cells if "ground_truth" in (c.record.get("_proof") or {})]
    unproven = [c for c in cells if c.record["_proof"]["ground_truth"] != PROVEN]
    if not unproven:
        return "Every cell was re-scored from its top-K indices against the ground truth on this machine." if cells else ""
    why = {}
    for cell in unproven:
        why.setdefault(cell.record["_proof"]["ground_truth"], []).append(cell.column.title)
    reasons = "; ".join(f"{', '.join(sorted(set(titles)))}: {reason}" for reason, titles in why.items())
    # an own folder is re-read at the path its runs name, never looked for under --data-dir
    own = "; a folder of your own, back unchanged at the path its runs name, proves theirs" \
        if any(c.column.kind != "benchmark" for c in unproven) else ""
    return (f"{len(unproven)} of {len(cells)} cell(s) were NOT re-scored against a ground truth (their numbers are "
            f"their own arrays', checked for consistency only): {reasons}. A benchmark's copy under --data-dir proves "
            f"its cells{own}.")
