"""A results repository: verified bundles merged into one folder laid out by identity.

    <DIR>/LAYOUT                                        the results layout (as a results store)
    <DIR>/<protocol hash>/<row key>/<run id>.json       the record, byte for byte as exported
                                   <run id>.npz         its per-query arrays
                                   <run id>.contribution  who sent it, when, in which bundle (JSON)
    <DIR>/methods/<row key>.json                        the method card

The folder is fit to be a git repository that people send pull requests to: files are only
ever added, each under a name that is its identity. A run already there (same run id and the
same bytes, or another run id with the same spec and the same per-query arrays) is recognised
as a duplicate and skipped; a different record under a run id already there is a conflict,
and its bundle is refused. A bundle that fails verification is refused with its reasons and
nothing of it is written. Imports hold the repository's lock, so two at once both land whole;
each commits its files with one rename (commit.py), so a kill leaves none of them orphaned.

`verify_repository` re-scores every run already in the folder, as a bundle's: a pull request that
adds or edits a record by hand, without an import, is caught however its files got there.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from ..errors import VPRBenchError, require
from ..evaluation.results import LAYOUT, LAYOUT_FILE, check_layout, oldest_first, read_record, read_results
from ..fsutil import CacheError, LockTimeout, atomic_write, check_lock_timeout, lock
from ..paths import special_file
from ..text import one_line
from .export import CARDS, MAX_CONTRIBUTOR
from .claims import one_record_per_run
from .archive import MAX_BYTES, RECORD_NAME
from .commit import PENDING, commit, leftovers, link_in, recover
from .verify import BundleReport, check_record, verify_bundle

CONTRIBUTION = ".contribution"
LOCK = ".import.lock"


@dataclass
class ImportReport:
    bundle: Path
    added: list[str] = field(default_factory=list)
    duplicates: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self) -> list[str]:
        if self.problems:
            return [*self.problems, f"{self.bundle}: refused; nothing of it was written."]
        return [f"{self.bundle}: {len(self.added)} run(s) added"
                + (f", {len(self.duplicates)} already there ({', '.join(self.duplicates)})" if self.duplicates else "")]


def import_bundles(bundles, into: Path, truth=None, *, max_bytes: int = MAX_BYTES,
                   lock_timeout: float | None = None) -> list[ImportReport]:
    """Verify each bundle and merge the sound ones into the repository `into`; one report per bundle."""
    into = Path(into)
    check_lock_timeout(lock_timeout, f"the results repository {into}")  # before any work
    if into.exists() and not into.is_dir():
        raise VPRBenchError(f"--into {into} is a file, not a folder.")
    check_layout(into)
    reports = []
    for bundle in bundles:
        verified = verify_bundle(Path(bundle), truth, max_bytes=max_bytes)
        report = ImportReport(Path(bundle))
        if not verified.ok:
            report.problems = [line for line in verified.lines() if ": ok, re-scored" not in line]
        else:
            with lock(into / LOCK, lock_timeout, what=f"the results repository {into}"):
                _merge(verified, into, report)
        reports.append(report)
    return reports


def _merge(verified, into: Path, report: ImportReport) -> None:
    """Under the lock: every record checked against the repository first, then written."""
    check_layout(into)
    recover(into)  # what an import killed here left (the lock proves no live import's files are touched)
    members, manifest = verified.members, verified.manifest
    bundle_sha = hashlib.sha256(b"".join(members[n] for n in sorted(members))).hexdigest()
    writes: dict[str, bytes] = {}
    for verdict in verified.verdicts:
        folder = verdict.member.rsplit("/", 1)[0]
        record = json.loads(members[verdict.member])
        target = into / verdict.member
        npz = f"{folder}/{record['per_query']['file']}"
        card = f"{CARDS}/{record['row_key']}.json"
        names = (PENDING, verdict.member, npz, card, f"{folder}/{verdict.run_id}{CONTRIBUTION}")
        linked = next((found for name in names if (found := link_in(into, name))), None)
        if linked:  # a write through it would land outside the repository, a read take in another file
            report.problems.append(f"{verified.path}: {verdict.member} (run {verdict.run_id}): {into / linked} is a "
                                   "link, not a file or folder of the repository; remove it, then import again.")
            continue
        special = next((name for name in names[1:] if special_file(into / name)), None)
        if special:  # its read (is it the same run?) would hang on a pipe, or never end on a device
            report.problems.append(f"{verified.path}: {verdict.member} (run {verdict.run_id}): {into / special} is a "
                                   "named pipe, device or socket, not a file; remove it, then import again.")
            continue
        if target.exists():
            if target.read_bytes() == members[verdict.member]:
                report.duplicates.append(verdict.run_id)
                continue
            report.problems.append(f"{verified.path}: {verdict.member} (run {verdict.run_id}): another record with this "
                                   f"run id is already in {into}; a run id names one run.")
            continue
        # the same run id in another row or protocol folder is the same clash (pages and
        # `results export --run` find a run by its id alone)
        elsewhere = sorted(into.glob(f"*/*/{verdict.run_id}.json"))
        if elsewhere:
            report.problems.append(f"{verified.path}: {verdict.member} (run {verdict.run_id}): another record with this "
                                   f"run id is already in {into} ({elsewhere[0].relative_to(into).as_posix()}); "
                                   "a run id names one run.")
            continue
        same = _same_result(into / folder, record)
        if same:
            report.duplicates.append(f"{verdict.run_id} = {same}")
            continue
        # a bundle's own text: one that is no UTF-8 (a '\udcff' in its JSON) failed the site's writing
        contributor = one_line(str(manifest.get("contributor") or "anonymous"))[:MAX_CONTRIBUTOR]
        contribution = {"contributor": contributor,
                        "bundle_created": str(manifest.get("created", ""))[:40], "bundle_sha256": bundle_sha,
                        "imported": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        if (into / npz).exists() and (into / npz).read_bytes() != members[npz]:
            report.problems.append(f"{verified.path}: {verdict.member} (run {verdict.run_id}): {into / npz} is there "
                                   "without its record and holds other arrays (left by a killed import of an older "
                                   "vprbench, or added by hand): remove it, then import again.")
            continue
        if not (into / card).exists():
            writes[card] = members[card]
        writes[npz] = members[npz]
        writes[verdict.member[:-len(".json")] + CONTRIBUTION] = json.dumps(contribution, indent=1,
                                                                         sort_keys=True).encode()
        writes[verdict.member] = members[verdict.member]
        report.added.append(verdict.run_id)
    if report.problems:
        report.added = []
        return
    try:
        if not (into / LAYOUT_FILE).is_file():
            atomic_write(into / LAYOUT_FILE, json.dumps(LAYOUT))
        commit(into, writes)  # all of the bundle's new files, or (killed before its one rename) none
    except CacheError as error:
        raise VPRBenchError(f"{error} The import of {verified.path} stopped; import it again.") from None


def _same_result(folder: Path, record: dict) -> str | None:
    """The run id of a record in `folder` with the same spec and the same per-query arrays."""
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        if path.is_symlink() or not path.is_file():  # a pipe would hang the read
            continue
        try:
            other = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if (isinstance(other, dict) and other.get("spec_key") == record.get("spec_key")
                and (other.get("per_query") or {}).get("sha256") == record["per_query"].get("sha256")):
            return str(other.get("run_id"))
    return None


def verify_repository(root: Path, truth=None, *, max_bytes: int = MAX_BYTES) -> BundleReport:
    """Every run of the repository `root` checked and re-scored as `verify_bundle` does a bundle's;
    files are read one run at a time, each within `max_bytes`."""
    from ..evaluation.rescore import DataGroundTruth

    root, truth = Path(root), truth or DataGroundTruth()
    report = BundleReport(root)
    try:
        check_layout(root)
    except VPRBenchError as error:
        report.problems.append(str(error))
        return report
    if leftovers(root):  # an import killed here: finished or undone, unless one is running now
        try:
            with lock(root / LOCK, 0, what=f"the results repository {root}", announce=False):
                recover(root)
        except LockTimeout:
            pass
        except VPRBenchError as error:
            report.problems.append(f"{error} An import into {root} was interrupted: import into it again (with "
                                   "write access) to finish it.")
    for link in sorted(p for p in (*root.glob("*"), *root.glob("*/*")) if p.is_symlink()):  # folders, mostly
        report.problems.append(f"{root}: {link.relative_to(root).as_posix()} is a link, not a regular file or folder; "
                               "refused (an import would write through it, outside the repository).")
    cards = {p.stem for p in (root / CARDS).glob("*.json")}
    records = _records(root)
    _orphans(root, cards, records, report.problems)
    for path in records:
        name = path.relative_to(root).as_posix()
        match = RECORD_NAME.match(name)
        if not match:
            report.problems.append(f"{root}: {name} is not where a results repository keeps a record "
                                   "(<protocol hash>/<row key>/<run id>.json); move or remove it.")
            continue
        members = {}
        for member in (name, f"{name[:-len('.json')]}.npz", f"{CARDS}/{match.group(2)}.json"):
            file = root / member
            if file.is_symlink() or (file.exists() and file.resolve() != root.resolve() / member):
                report.problems.append(f"{root}: {member} is a link, not a regular file; refused.")
            elif special_file(file) or file.is_dir():  # else passed over unread, unchecked
                report.problems.append(f"{root}: {member} is not a regular file (a folder, named pipe, device or "
                                       "socket); remove it.")
            elif file.is_file() and file.stat().st_size > max_bytes:
                report.problems.append(f"{root}: {member} is over the bound of {max_bytes / 2**20:g} MiB "
                                       "(raise --max-size).")
            elif file.is_file():
                try:
                    members[member] = file.read_bytes()
                except OSError as error:
                    report.problems.append(f"{root}: cannot read {member} ({error.strerror or error}).")
        if name in members:
            report.verdicts.append(check_record(name, match.groups()[:3], members, cards, truth, max_bytes))
    one_record_per_run(report.verdicts)
    return report


def _records(root: Path) -> list[Path]:
    """The records in place: `<protocol>/<row>/<run>.json`, method cards apart."""
    return sorted(p for p in root.glob("*/*/*.json") if p.parts[-3] != CARDS)


def _orphans(root: Path, cards: set, records: list[Path], problems: list) -> None:
    """Arrays, notes and cards no record uses (a kill in an import of an older vprbench left them). Not those
    whose record is still in an import's commit folder: that import (running now, or killed and finished by
    the next) moves the record last."""
    rows = {p.parent.name for p in records}
    stray = [p for suffix in (".npz", CONTRIBUTION) for p in root.glob(f"*/*/*{suffix}")
             if not p.with_suffix(".json").exists()]
    stray += [root / CARDS / f"{card}.json" for card in cards - rows]
    if stray:  # the commit folders looked in first, then the places again: a record moved in between is seen
        pending = root / PENDING
        moving = set() if pending.is_symlink() else {
            p.relative_to(folder).as_posix() for folder in pending.glob("commit-*") if not folder.is_symlink()
            for p in folder.glob("*/*/*.json")}
        known = moving | {p.relative_to(root).as_posix() for p in _records(root)}
        rows = {name.split("/")[1] for name in known}
        stray = [p for p in stray if (p.stem not in rows if p.parent == root / CARDS
                                      else p.with_suffix(".json").relative_to(root).as_posix() not in known)]
    for path in sorted(stray):
        problems.append(f"{root}: {path.relative_to(root).as_posix()} belongs to no record (left by an import of an "
                        "older vprbench that was killed, or added by hand); remove it.")


def read_repository(root: Path, skipped: list | None = None) -> list[dict]:
    """Every record of the repository, oldest first, each with `_contribution`: contributor,
    date, hardware and vprbench version (for the site). Unreadable files are named in a warning
    and skipped (their paths appended to `skipped`)."""
    import warnings

    root = Path(root)
    if not root.is_dir():
        raise VPRBenchError(f"The results repository {root} "
                            f"{'is a file, not a folder' if root.exists() else 'does not exist'}: give the folder "
                            "'vprbench results import --into' wrote.")
    check_layout(root)
    records = []
    paths = [path for path in sorted(root.glob("*/*/*.json")) if path.parts[-3] != CARDS]
    if not paths:  # a wrong folder would otherwise add nothing, silently
        raise VPRBenchError(f"The results repository {root} holds no records: give the folder 'vprbench results "
                            "import --into' wrote.")
    for path in paths:
        try:
            record = read_record(path)
        except VPRBenchError as error:
            warnings.warn(f"{error} Skipped.", stacklevel=2)
            if skipped is not None:
                skipped.append(path)
            continue
        sent = _contribution(path.with_suffix(CONTRIBUTION))
        record["_contribution"] = {"contributor": sent.get("contributor", "unknown"),
                                   "date": record.get("created"), "imported": sent.get("imported"),
                                   "hardware": record.get("hardware") or {},
                                   "version": (record.get("versions") or {}).get("vprbench")}
        records.append(record)
    return oldest_first(records)


def read_runs(cache_dir=None, results=None, skipped: list | None = None) -> list[dict]:
    """The runs a leaderboard is built from (`leaderboard show`, `compare` and `publish` alike): this
    cache's results store, and with `results` the repository's runs too, oldest first. A run in both
    is this machine's (read once, unmarked). Unreadable files are named in a warning and appended to
    `skipped`."""
    records = read_results(cache_dir, skipped=skipped)
    if results is None:
        return records
    require(results, (str, os.PathLike), "results take the folder 'vprbench results import --into' wrote")
    here = {r["run_id"] for r in records}
    return oldest_first(records + [r for r in read_repository(results, skipped) if r["run_id"] not in here])


def no_runs(cache_dir=None) -> str:
    """Why a leaderboard has no run to show, naming the cache folder read (a mistyped one was 'No results yet',
    as if the results were lost)."""
    from ..paths import cache_root

    root = cache_root(cache_dir)
    if cache_dir is not None and not root.is_dir():  # the default is made by the first run
        return (f"No results: the cache folder {root} does not exist; check --cache-dir or $VPRBENCH_CACHE (the "
                "folder 'vprbench evaluate' wrote to).")
    return f"No results yet in the cache folder {root}: run 'vprbench evaluate --method M --dataset D' first."


def _contribution(path: Path) -> dict:
    """A run's contribution note as the site shows it: each value one line, cut as an import cuts the
    contributor (a pull request can carry a note written by hand); a pipe in its place is not read."""
    try:
        found = {} if special_file(path) else json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return {k: one_line(v)[:MAX_CONTRIBUTOR] for k, v in found.items()} if isinstance(found, dict) else {}
