"""`vprbench results verify`: nothing in a bundle is trusted that can be recomputed.

The archive is read into memory, bounded and never extracted, and its manifest checked against
every member (archive.py). Each record is then validated (a record of a newer schema is refused), the names it gives must be
its spec's and vprbench's (claims.py), its protocol hash must be one vprbench ships for its
dataset, and its metrics are recomputed from its per-query arrays against that protocol's ground truth, read from the dataset on this machine: query and database
counts, indices in range, every query present, first-positive ranks, and Recall@K (records keep
6 decimals, earlier ones 4) and the top-1 PR metrics (6 decimals, computed from the similarities the record keeps;
tolerance 1e-3 for records of earlier versions, computed before rounding). Units of the bootstrap a record keeps (each query's place,
the traverse order, blocks lengthened by its stages' sequence window) must be the protocol's, or its
intervals would be drawn from the wrong ones.
"""
from __future__ import annotations

import hashlib
import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import VPRBenchError
from ..text import one_line, recall_text, shortened
from ..evaluation.record import per_query_arrays_in, validated
from ..evaluation.rescore import DataGroundTruth, rescore
from ..evaluation.results import check_kinds
from .archive import _CARD, MAX_BYTES, RECORD_NAME, BundleError, _json, check_manifest, read_members
from .claims import false_card, false_claims, malformed, one_record_per_run
from .export import CARDS, KIND_WORDS

#: the longest row label a verdict line shows
MAX_LABEL = 200


# ---------------------------------------------------------------- the records
@dataclass
class Verdict:
    """What was found about one record of a bundle."""

    member: str
    run_id: str
    label: str = ""
    problems: list[str] = field(default_factory=list)
    recall: dict[str, float] = field(default_factory=dict)
    #: a run on random weights: sound, but a pipeline check that fills no leaderboard cell
    check: bool = False

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class BundleReport:
    path: Path
    manifest: dict = field(default_factory=dict)
    members: dict[str, bytes] = field(default_factory=dict)
    verdicts: list[Verdict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and bool(self.verdicts) and all(v.ok for v in self.verdicts)

    def lines(self) -> list[str]:
        """One line per problem (naming the file and the record), or per record found sound."""
        from ..leaderboard.shown import PIPELINE_CHECK

        out = list(self.problems)
        for verdict in self.verdicts:
            head = f"{self.path}: {verdict.member} (run {verdict.run_id}{', ' + verdict.label if verdict.label else ''})"
            if verdict.ok:
                # rounded as the leaderboard shows it
                shown = " ".join(f"R@{k} {recall_text(v)}" for k, v in verdict.recall.items())
                check = f" ({PIPELINE_CHECK}; it fills no leaderboard cell)" if verdict.check else ""
                out.append(f"{head}: ok, re-scored from its arrays: {shown}{check}")
            out += [f"{head}: {problem}" for problem in verdict.problems]
        if not self.problems and not self.verdicts:
            out.append(f"{self.path}: it holds no records.")
        # names from a record (a label, a key) hold no line break: none can forge a verdict line
        return [one_line(line) for line in out]


def verify_bundle(path: Path, truth=None, *, max_bytes: int = MAX_BYTES) -> BundleReport:
    """Every record of the bundle at `path` checked and re-scored; `truth(dataset, protocol_hash)`
    gives the ground truth (default: `DataGroundTruth()`, the datasets on this machine)."""
    report = BundleReport(Path(path))
    truth = truth or DataGroundTruth()
    try:
        report.members = read_members(Path(path), max_bytes)
        report.manifest = check_manifest(report.members, str(path))
    except BundleError as error:
        report.problems.append(str(error))
        return report
    cards = {m.group(1) for m in map(_CARD.match, report.members) if m}
    for name in sorted(report.members):
        match = RECORD_NAME.match(name)
        if match and match.group(4) == "json":
            report.verdicts.append(check_record(name, match.groups()[:3], report.members, cards, truth, max_bytes))
    one_record_per_run(report.verdicts)
    return report


def check_record(name: str, place: tuple, members: dict[str, bytes], cards: set, truth,
                 max_bytes: int = MAX_BYTES) -> Verdict:
    protocol_hash, row_key, run_id = place
    verdict = Verdict(name, run_id)
    problems = verdict.problems
    try:
        record = validated(_json(members[name]), name)
    except ValueError as error:
        problems.append(f"not JSON ({error})")
        return verdict
    except VPRBenchError as error:
        problems.append(str(error).removeprefix(f"{name} ").removeprefix(f"{name}: "))
        return verdict
    # here, not at the top: the leaderboard package loads pandas (its tables), which export and verify need not
    from ..leaderboard.cells import row_of
    from ..leaderboard.shown import random_weights

    shapeless = malformed(record)  # the row's name and marks are read from these parts: none can be told
    if shapeless:
        problems += shapeless
        return verdict
    # the row as the leaderboard names it, marks included: a run on random weights (which fills no cell)
    # or fitted on the evaluated database does not read as an official one
    # cut: a method name or protocol id a stranger wrote can be megabytes, printed on each of the record's lines
    verdict.label = shortened(f"{row_of(record).name} on {record['protocol']['id']}", MAX_LABEL)
    verdict.check = random_weights(record)
    found = (record["protocol"]["hash"], record["row_key"], record["run_id"])
    if found != place or record["spec"]["dataset"]["protocol_hash"] != protocol_hash:
        problems.append(f"its protocol hash, row key and run id {'/'.join(found)} are not its place in the bundle")
        return verdict
    if row_key not in cards:
        problems.append(f"its method card {CARDS}/{row_key}.json is missing")
    elif f"{CARDS}/{row_key}.json" in members:
        problems += false_card(members[f"{CARDS}/{row_key}.json"], record)
    if record["dataset_kind"] != "benchmark":
        problems.append(f"it was run on {KIND_WORDS.get(record['dataset_kind'], 'a dataset of its own')}, whose ground "
                        "truth vprbench does not ship; only benchmark runs can be checked")
        return verdict
    problems += false_claims(record)
    arrays = _arrays(record, members, f"{protocol_hash}/{row_key}", problems, max_bytes)
    if arrays is None:
        return verdict
    try:
        gt = truth(record["dataset"], protocol_hash)
    except VPRBenchError as error:
        problems.append(f"cannot be checked: {error}")
        return verdict
    verdict.recall = rescore(record, arrays, gt, problems)
    return verdict


def _arrays(record: dict, members: dict[str, bytes], folder: str, problems: list, max_bytes: int) -> dict | None:
    section = record.get("per_query") or {}
    file = f"{folder}/{section.get('file')}"
    if section.get("file") != f"{record['run_id']}.npz" or file not in members:
        problems.append("its per-query arrays are missing (a bundle record must keep them)")
        return None
    data = members[file]
    if hashlib.sha256(data).hexdigest() != section.get("sha256"):
        problems.append(f"{file} does not match the sha256 its record gives")
        return None
    try:
        # an .npz is a zip of its own: a few kB may claim gigabytes (a bomb inside the bundle);
        # the sizes its members declare bound what they unpack to
        with zipfile.ZipFile(io.BytesIO(data)) as inner:
            unpacked = sum(info.file_size for info in inner.infolist())
        if unpacked > max_bytes:
            problems.append(f"{file} unpacks to {unpacked / 2**20:,.0f} MiB, more than the bound of "
                            f"{max_bytes / 2**20:g} MiB (an archive bomb, or a bundle too big: raise --max-size)")
            return None
        arrays = per_query_arrays_in(data, max_bytes)  # the bound above, not the reader's default
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as error:
        problems.append(f"{file} is not readable per-query arrays ({type(error).__name__}: {error})")
        return None
    try:
        check_kinds(arrays)  # the store's own test: what the metrics below compute with
    except ValueError as error:
        problems.append(f"{file}: {error}")
        return None
    return arrays
