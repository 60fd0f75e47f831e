"""A results repository after a real kill -9 of `vprbench results import` at a chosen step of its
commit (each staged file, the one rename that commits, each move after it), alone and with a second
import waiting on the lock: the next import or verify leaves it whole, with nothing lost and nothing
orphaned, and never touches the files of an import that is running."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from vprbench.bundles import export_bundle, read_repository, verify_repository
from vprbench.evaluation.rescore import DataGroundTruth

#: `vprbench ARGS...` that, just after step STEP of the commit, kills itself (die) or says so and
#: waits to be killed from outside (pause)
KILLED_IMPORT = """
import os, pathlib, signal, sys, time
import vprbench.bundles.commit as commit
from vprbench.cli.main import main

step, mode, steps = int(os.environ["STEP"]), os.environ["MODE"], []

def counted(real):
    def run(*args):
        real(*args)
        steps.append(args)
        if len(steps) == step:
            if mode == "pause":
                pathlib.Path(os.environ["PAUSED"]).write_text("paused")
                time.sleep(600)
            os.kill(os.getpid(), signal.SIGKILL)
    return run

commit._write, commit._rename = counted(commit._write), counted(commit._rename)
sys.exit(main(sys.argv[1:]))
"""

HOLDS_LOCK = """
import sys, time
from vprbench.fsutil import lock
with lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def importer(bundle, repo, shared_data, cache, **env):
    command = [sys.executable, "-c", KILLED_IMPORT, "results", "import", bundle, "--into", repo,
               "--data-dir", shared_data, "--cache-dir", cache]
    return subprocess.Popen(list(map(str, command)), env={**os.environ, "STEP": "0", "MODE": "die", **env},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def files(repo) -> list[str]:
    return sorted(p.relative_to(repo).as_posix() for p in repo.rglob("*") if p.is_file())


def expected(records) -> list[str]:
    out = ["LAYOUT", ".import.lock"]
    for r in records:
        run = f"{r['protocol']['hash']}/{r['row_key']}/{r['run_id']}"
        out += [f"{run}.json", f"{run}.npz", f"{run}.contribution", f"methods/{r['row_key']}.json"]
    return sorted(out)


# steps for two runs in two rows: 8 files staged (1..8), the commit (9), 8 moves (10..17), records last
@pytest.mark.parametrize("step", [3, 9, 16], ids=["while-staging", "just-committed", "one-record-moved"])
def test_an_import_killed_then_imported_again_is_whole(records, shared_data, tmp_path, cli, step):
    """Was: each file was written to its place in turn, so a kill -9 left arrays, notes and a card
    that no record used; no later import or verify removed them (verify did not even name them)."""
    bundle = export_bundle(records, tmp_path / "runs.tar.gz", contributor="alice")
    repo = tmp_path / "repo"
    killed = importer(bundle, repo, shared_data, tmp_path / "cache", STEP=str(step))
    _, err = killed.communicate(timeout=120)
    assert killed.returncode == -signal.SIGKILL, err
    runs = list(repo.glob("*/*/*.json"))
    assert len(runs) == (1 if step == 16 else 0)  # before the commit no record; after it, records come last
    for path in runs:
        assert path.with_suffix(".npz").is_file() and (repo / "methods" / f"{path.parent.name}.json").is_file()
    code, out, err = cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)
    assert code == 0, out + err
    assert out.strip() == (f"{bundle}: 2 run(s) added" if step < 9 else
                           f"{bundle}: 0 run(s) added, 2 already there ({records[0]['run_id']}, {records[1]['run_id']})")
    code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 0 and out.count(": ok, re-scored from its arrays") == 2, out + err
    assert files(repo) == expected(records)


def test_a_killed_import_is_finished_by_the_one_waiting_for_the_lock(records, shared_data, tmp_path, cli):
    """Two importers at once: the first is killed -9 holding the lock, just after its commit; the
    second, waiting on the lock meanwhile, finishes the first's runs and adds its own. A verify
    while the first still runs leaves its files alone (the lock says it is live)."""
    alice = export_bundle([records[0]], tmp_path / "alice.tar.gz", contributor="alice")
    bob = export_bundle([records[1]], tmp_path / "bob.tar.gz", contributor="bob")
    repo, paused = tmp_path / "repo", tmp_path / "paused"
    first = importer(alice, repo, shared_data, tmp_path / "cache", STEP="5", MODE="pause", PAUSED=str(paused))
    deadline = time.monotonic() + 120
    while not paused.exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert paused.exists(), first.communicate()
    [pending] = (repo / ".import.pending").iterdir()  # alice's four files, committed, not yet moved
    assert pending.name.startswith("commit-") and len(files(pending)) == 4
    second = importer(bob, repo, shared_data, tmp_path / "cache")
    report = verify_repository(repo, DataGroundTruth(shared_data))  # the lock is held: a live import's files
    assert len(files(pending)) == 4 and report.verdicts == [], report.lines()
    while "waiting for the results repository" not in (line := second.stderr.readline()) and line:
        pass
    assert "locked by pid" in line
    os.kill(first.pid, signal.SIGKILL)
    first.communicate(timeout=60)
    out, err = second.communicate(timeout=120)
    assert second.returncode == 0 and out.strip() == f"{bob}: 1 run(s) added", out + err
    assert files(repo) == expected(records)
    assert sorted(r["run_id"] for r in read_repository(repo)) == sorted(r["run_id"] for r in records)
    assert sorted(r["_contribution"]["contributor"] for r in read_repository(repo)) == ["alice", "bob"]
    code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 0 and out.count(": ok, re-scored from its arrays") == 2, out + err


def test_a_killed_import_left_behind_is_undone_by_verify_not_while_it_runs(records, shared_data, tmp_path):
    """An uncommitted staging folder is removed by verify only when no import holds the lock."""
    repo = tmp_path / "repo"
    bundle = export_bundle([records[0]], tmp_path / "alice.tar.gz")
    from vprbench.bundles import import_bundles

    truth = DataGroundTruth(shared_data)
    assert import_bundles([bundle], repo, truth)[0].ok
    staging = repo / ".import.pending" / "staging-1-ab" / "methods"
    staging.mkdir(parents=True)
    (staging / "0123456789abcdef.json").write_text("{}")
    holder = subprocess.Popen([sys.executable, "-c", HOLDS_LOCK, str(repo / ".import.lock")], stdout=subprocess.PIPE,
                              text=True)  # an import running now (another process holds the lock)
    try:
        assert holder.stdout.readline() == "held\n"
        assert verify_repository(repo, truth).ok and staging.is_dir()
    finally:
        holder.kill()
        holder.wait()
    assert verify_repository(repo, truth).ok and not (repo / ".import.pending").exists()
    assert files(repo) == expected([records[0]])


def test_orphans_an_older_import_left_are_named_by_verify(records, shared_data, tmp_path, cli):
    """Arrays, a note and a card no record uses (what a killed import of the old code left): one
    line each from verify, exit 1; importing the bundle again then makes the repository whole, and
    the old code's temporary files go (only those named after a repository file). Was: verify
    said nothing of them (exit 0), and the temporary files stayed for good."""
    bundle = export_bundle(records, tmp_path / "runs.tar.gz")
    repo = tmp_path / "repo"
    code, out, err = cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)
    assert code == 0, out + err
    r = records[1]
    run = repo / r["protocol"]["hash"] / r["row_key"] / r["run_id"]
    run.with_suffix(".json").unlink()  # as the old code left it, killed before the record
    mine = [repo / ".LAYOUT.k2j4h5g6.tmp", run.parent / f".{run.name}.npz.aeu47kkk.tmp"]  # killed mid-write
    others = repo / ".notes.md.x1y2z3w4.tmp"  # not a repository file's: someone else's
    for path in (*mine, others):
        path.write_bytes(b"half")
        os.utime(path, (time.time() - 7200,) * 2)  # left two hours ago
    fresh = run.parent / f".{run.name}.json.q9w8e7r6.tmp"  # a live writer's (outside the lock): kept
    fresh.write_bytes(b"being written")
    code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
    stray = [f"{run.with_suffix(s).relative_to(repo).as_posix()}" for s in (".contribution", ".npz")]
    stray.append(f"methods/{r['row_key']}.json")
    assert code == 1 and [line for line in out.splitlines() if "belongs to no record" in line] == [
        f"{repo}: {name} belongs to no record (left by an import of an older vprbench that was killed, or added "
        "by hand); remove it." for name in sorted(stray)], out
    code, out, err = cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)
    assert code == 0 and "1 run(s) added" in out, out + err
    code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 0, out
    assert files(repo) == sorted([*expected(records), others.name, fresh.relative_to(repo).as_posix()]) and others.read_bytes() == b"half"


def paused_import(bundle, repo, shared_data, tmp_path, step):
    """An import run up to step STEP of its commit, then holding there (the lock held)."""
    paused = tmp_path / "paused"
    running = importer(bundle, repo, shared_data, tmp_path / "cache", STEP=str(step), MODE="pause", PAUSED=str(paused))
    deadline = time.monotonic() + 120
    while not paused.exists() and running.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert paused.exists(), running.communicate()
    return running


def test_verify_while_an_import_moves_its_files_names_none_of_them(records, shared_data, tmp_path, cli):
    """Was: a verify while an import was moving its files (arrays and cards first, records last) said
    of the arrays, notes and card whose record was not yet moved 'belongs to no record ...; remove it'
    (exit 1): a false alarm, and advice that, taken, leaves a record without its arrays."""
    bundle = export_bundle(records, tmp_path / "runs.tar.gz")
    repo = tmp_path / "repo"
    running = paused_import(bundle, repo, shared_data, tmp_path, 16)  # one record moved, the other's files too
    try:
        [pending] = (repo / ".import.pending").iterdir()
        assert files(pending) == [f"{records[1]['protocol']['hash']}/{records[1]['row_key']}/{records[1]['run_id']}.json"]
        code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
        assert code == 0 and "belongs to no record" not in out, out + err
        assert out.count(": ok, re-scored from its arrays") == 1 and records[0]["run_id"] in out, out
        assert len(files(pending)) == 1  # the live import's file left alone
    finally:
        os.kill(running.pid, signal.SIGKILL)
        running.communicate(timeout=60)
    code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)  # the killed import finished
    assert code == 0 and out.count(": ok, re-scored from its arrays") == 2, out + err
    assert files(repo) == expected(records)


def test_an_import_started_while_verify_runs_is_no_orphan(records, shared_data, tmp_path, monkeypatch):
    """An import that starts after verify has listed the records, and is moving its files when verify
    looks for orphans: its arrays and note are not named (was: two 'belongs to no record' lines)."""
    from vprbench.bundles import import_bundles, repository

    truth, repo = DataGroundTruth(shared_data), tmp_path / "repo"
    assert import_bundles([export_bundle([records[0]], tmp_path / "alice.tar.gz")], repo, truth)[0].ok
    bob = export_bundle([records[1]], tmp_path / "bob.tar.gz")
    started, real = [], repository._orphans

    def import_meanwhile(*args):
        # one run: 4 files staged, the commit (5), then note, arrays and card moved (6..8), the record not
        started.append(paused_import(bob, repo, shared_data, tmp_path, 8))
        return real(*args)

    monkeypatch.setattr(repository, "_orphans", import_meanwhile)
    try:
        report = verify_repository(repo, truth)
    finally:
        for running in started:
            os.kill(running.pid, signal.SIGKILL)
            running.communicate(timeout=60)
    assert len(started) == 1 and report.problems == [] and report.ok, report.lines()
    assert [v.run_id for v in report.verdicts] == [records[0]["run_id"]]


def test_a_killed_import_verify_cannot_finish_is_named_once(records, shared_data, tmp_path, monkeypatch):
    """Killed mid-move and verified without write access: one line says to import again; its moved
    arrays are not named orphans to remove (was: 'remove it' for each, which loses them for good)."""
    from vprbench.bundles import repository
    from vprbench.fsutil import cache_error

    bundle = export_bundle(records, tmp_path / "runs.tar.gz")
    repo = tmp_path / "repo"
    killed = importer(bundle, repo, shared_data, tmp_path / "cache", STEP="14")
    killed.communicate(timeout=120)
    assert killed.returncode == -signal.SIGKILL

    def read_only(into):
        raise cache_error(PermissionError(13, "Permission denied"), into / ".import.pending")

    monkeypatch.setattr(repository, "recover", read_only)
    report = verify_repository(repo, DataGroundTruth(shared_data))
    assert len(report.problems) == 1 and report.problems[0].endswith(
        f"An import into {repo} was interrupted: import into it again (with write access) to finish it."), report.problems
