"""The results store with real processes: many writers at once, kill -9 in the middle of a
write, a full disk and a read-only cache. Every stored record must stay whole and readable."""
import json
import os
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation import per_query, read_results, results_dir, save_result

WRITER = """
import json, os, sys, time
from pathlib import Path
import vprbench.evaluation.results as record

template = json.loads(Path(sys.argv[1]).read_text())
writer, count = sys.argv[2], int(sys.argv[3])
if os.environ.get("ANNOUNCE"):  # say which file is being written, and write slowly, so the parent can kill mid-write
    original = record.atomic_write
    def announced(path, data):
        if path.parent.parent.parent.name != "results":  # the layout note and method cards: not a record
            return original(path, data)
        print("writing", path.suffix, flush=True)
        real_fsync = os.fsync
        os.fsync = lambda fd: (time.sleep(0.4), real_fsync(fd))
        try:
            original(path, data)
        finally:
            os.fsync = real_fsync
    record.atomic_write = announced  # the name save_result calls
print("ready", flush=True)
started = time.time()
while not Path(sys.argv[4]).exists():  # all writers start together
    if time.time() - started > 300:
        sys.exit("never told to start")
    time.sleep(0.005)
for i in range(count):
    run = dict(template, run_id=f"{writer}-{i:03d}", context={"writer": writer, "index": i})
    run["recall"] = {"1": float(i), "5": float(i)}
    record.save_result(run)
"""


_started: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def no_writer_outlives_its_test():
    """A failing test must not leave writers polling for their start file forever."""
    yield
    while _started:
        proc = _started.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


def writer(tmp_path, template, name, count, go, **env):
    script = tmp_path / "writer.py"
    if not script.exists():  # rewriting it while an earlier writer starts would hand that one an empty file
        script.write_text(WRITER)
    errors = tmp_path / f"{name}.stderr"  # a file, not a pipe: eight children never block on it
    proc = subprocess.Popen([sys.executable, str(script), str(template), name, str(count), str(go)],
                            env={**os.environ, **env}, stdout=subprocess.PIPE, stderr=errors.open("w"), text=True)
    proc.errors = errors
    _started.append(proc)
    return proc


def assert_ready(proc):
    line = proc.stdout.readline().strip()
    assert line == "ready", f"writer exited {proc.poll()} before it was ready: {proc.errors.read_text()[-2000:]}"


def assert_all_whole(expected_count=None):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a single torn or unreadable record fails the test
        records = read_results()
        for record in records:
            arrays = per_query(record)
            assert arrays["database_indices"].shape == (record["counts"]["queries"], record["per_query"]["k"])
    if expected_count is not None:
        assert len(records) == expected_count
    return records


@pytest.fixture
def template(make_record, tmp_path):
    def make(n_queries=111):
        record = make_record(kind="own", n_database=500, n_queries=n_queries, dataset="torture")
        path = tmp_path / f"template-{n_queries}.json"
        path.write_text(json.dumps(record))
        return path
    return make


def test_eight_writers_at_once_lose_nothing(tmp_path, template):
    go = tmp_path / "go"
    source = template()  # written once: rewriting it while an earlier writer reads it hands that one an empty file
    procs = [writer(tmp_path, source, f"w{w}", 15, go) for w in range(8)]
    for p in procs:
        assert_ready(p)  # imported and waiting: now start all at once
    go.touch()
    assert [p.wait(timeout=120) for p in procs] == [0] * 8
    records = assert_all_whole(expected_count=120)
    assert {(r["context"]["writer"], r["context"]["index"]) for r in records} == {(f"w{w}", i) for w in range(8) for i in range(15)}
    assert all(r["recall"]["1"] == r["context"]["index"] for r in records), "no record carries another's values"


@pytest.mark.parametrize("moment", ["npz", "json"])
def test_kill_9_in_the_middle_of_a_write_leaves_whole_records_only(tmp_path, template, moment):
    """Killed while the per-query file, or the record itself, is half on disk: the records stored
    before are intact, the interrupted one is absent, and the next writer works."""
    go = tmp_path / "go"
    go.touch()
    source = template(n_queries=3000)
    proc = writer(tmp_path, source, "first", 3, go, ANNOUNCE="1")
    assert_ready(proc)
    seen = []
    while len(seen) < 3 or seen[-1] != f".{moment}":  # let two records finish, kill in the third
        seen.append(proc.stdout.readline().strip().removeprefix("writing "))
    time.sleep(0.1)  # the temporary file is open and being written
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    leftovers = [p.name for p in results_dir().rglob(".*") if p.is_file()]
    assert leftovers, "the kill landed in the middle of a write"
    records = assert_all_whole(expected_count=1)
    assert records[0]["run_id"] == "first-000"
    later = writer(tmp_path, source, "after", 2, go)
    assert later.wait(timeout=60) == 0
    assert len(assert_all_whole()) == 3


def test_kill_9_at_seeded_random_moments(tmp_path, template):
    go = tmp_path / "go"
    go.touch()
    source = template(n_queries=3000)
    rng = np.random.default_rng(0)
    kills = 0
    for round_ in range(5):
        proc = writer(tmp_path, source, f"r{round_}", 50, go)
        assert_ready(proc)
        time.sleep(float(rng.uniform(0.0, 0.4)))
        os.kill(proc.pid, signal.SIGKILL)
        kills += proc.wait(timeout=30) == -signal.SIGKILL
        assert_all_whole()
    assert kills == 5


def test_full_disk_fails_cleanly_and_keeps_every_stored_record(small_disk, make_record, monkeypatch):
    disk = small_disk(1200)
    monkeypatch.setenv("XDG_CACHE_HOME", str(disk))  # the library's default cache: <disk>/vprbench
    record = make_record(kind="own", n_database=5000, n_queries=2000, dataset="full")
    saved = 0
    with pytest.raises(VPRBenchError, match=r"Cannot use .*results/[0-9a-f]{16}/[0-9a-f]{16}/run-\d+\.(npz|json): No space left on device; .* The result was not stored\."):
        for _ in range(100):
            save_result(dict(record, run_id=f"run-{saved:03d}"))
            saved += 1
    assert saved >= 2
    assert not [p for p in results_dir().rglob(".*") if p.is_file()], "no temporary file left behind"
    assert len(assert_all_whole()) == saved
    # the legacy store glued the next record to a torn line: here, once there is room, the next one is whole
    for path in sorted(results_dir().rglob("run-*.json"))[:2]:
        path.unlink()
        path.with_suffix(".npz").unlink()
    save_result(dict(record, run_id="after-room"))
    assert "after-room" in {r["run_id"] for r in assert_all_whole(expected_count=saved - 2 + 1)}


def test_read_only_cache_reads_and_refuses_to_write_with_a_message(read_only, make_record, tmp_path, monkeypatch):
    save_result(make_record())
    view = read_only(results_dir().parent.parent)
    monkeypatch.setenv("XDG_CACHE_HOME", str(view))
    assert len(assert_all_whole()) == 1
    with pytest.raises(VPRBenchError, match="Read-only file system"):
        save_result(make_record())


def test_what_killed_writers_left_is_removed_by_a_later_save_once_it_is_an_hour_old(tmp_path, make_record):
    """Temporary files and arrays whose record never came stayed in results/ for ever."""
    from vprbench.evaluation import save_result

    cache = tmp_path / "cache"
    folder = save_result(make_record(seed=0), cache).parent
    old = time.time() - 2 * 3600
    stale = [folder / ".x.json.abc.tmp", folder / "19990101T000000Z-dead.npz"]
    fresh = [folder / ".y.json.def.tmp", folder / "19990101T000000Z-live.npz"]  # a live writer's
    for path in stale + fresh:
        path.write_bytes(b"partial")
    for path in stale:
        os.utime(path, (old, old))
    written = save_result(make_record(seed=1), cache)
    assert written.parent == folder
    assert not any(p.exists() for p in stale) and all(p.exists() for p in fresh)
    assert len(list(folder.glob("*.json"))) == 2 and len(list(folder.glob("*.npz"))) == 3
