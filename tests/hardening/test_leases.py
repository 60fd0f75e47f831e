"""Leases of a sweep's claims cannot make a run wait or steal: a lease dated ahead of now (a
clock set ahead, a file touched by hand) is judged by a clock nobody can set and goes stale
after one lease period; a lease that is not a finite number of seconds is refused; processes
with different leases never judge each other's live claims dead."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from vprbench import VPRBenchError
from vprbench.evaluation import read_results
from vprbench.sweep.claims import MIN_LEASE_S, Claims
from vprbench.sweep.plan import read_plan

from hostile_files import assert_refused

DAY = 86400


@pytest.fixture
def plan(tmp_path) -> Path:
    path = tmp_path / "plan.toml"
    path.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')
    return path


def test_a_lease_dated_a_day_ahead_goes_stale_after_one_lease_period(plan, tmp_path, shared_data):
    cache = tmp_path / "cache"
    (cell,) = read_plan(plan).cells
    lease = cache / "sweeps" / "claims" / f"{cell.key}.lease"
    lease.parent.mkdir(parents=True)
    lease.write_text(json.dumps({"worker": "clock-ahead:7", "token": "t"}))
    os.utime(lease, (time.time() + DAY, time.time() + DAY))
    # the attack is real: by its date the lease is a day younger than now, so "age < lease" holds for a day
    assert time.time() - lease.stat().st_mtime < -DAY + 60
    env = {**os.environ, "VPRBENCH_CACHE": str(cache), "VPRBENCH_DATA": str(shared_data)}
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "vprbench.cli.main", "run", str(plan), "--lease", "2"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"warning: The claim {lease} is dated" in done.stderr and "ahead of this host's clock" in done.stderr
    (record,) = read_results(cache)
    assert record["context"]["sweep"]["resumed"].startswith("taken over from clock-ahead:7 (its date, ahead of this host's clock, unchanged for")
    assert time.monotonic() - started < 200  # minutes at most, not a day (the lease is 2 s; the rest is the run)


@pytest.mark.parametrize("lease", [math.nan, math.inf, -math.inf, 0, -1, 0.5, "abc", None, True])
def test_a_lease_that_is_not_a_finite_number_of_seconds_is_refused(lease, tmp_path):
    if lease is math.nan:  # the attack is real: no age is below a NaN lease, so every live claim looks stale
        assert not any(age < lease for age in (0.0, 0.1, 1.0))
    with pytest.raises(VPRBenchError, match=rf"The lease must be a finite number of seconds, at least "
                                            rf"{MIN_LEASE_S:g} .*; got {lease!r}"):
        Claims(tmp_path, lease_s=lease)


def test_a_nan_lease_on_the_command_line_is_one_line(plan, shared_data, cli):
    code, _, err = cli("run", plan, "--lease", "nan", "--data-dir", shared_data)
    assert_refused(code, err, None, "lease")
    # one evaluation makes no claim, but its --lease is checked all the same (it once ran with 'nan')
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data, "--lease", "nan")
    assert_refused(code, err, None, "The lease must be a finite number of seconds, at least 1")


def test_a_short_lease_never_takes_a_long_leased_live_claim(tmp_path):
    holder = Claims(tmp_path, lease_s=600)
    judge = Claims(tmp_path, lease_s=MIN_LEASE_S)
    try:
        assert holder.claim("cell", lambda: False) == ("claimed", "")
        deadline = time.monotonic() + 3 * MIN_LEASE_S
        while time.monotonic() < deadline:  # three of the judge's lease periods
            assert judge.claim("cell", lambda: False) == ("busy", holder.worker)
            time.sleep(0.1)
        assert holder.still_mine("cell")
        holder.close()  # the holder dies: no more heartbeats
        time.sleep(2 * MIN_LEASE_S)
        state, detail = judge.claim("cell", lambda: False)
        assert state == "claimed" and detail.startswith(f"taken over from {holder.worker} (no heartbeat for")
    finally:
        holder.close()
        judge.close()


def test_a_process_stalled_past_its_lease_while_storing_cannot_store_beside_the_one_that_took_over(
        plan, tmp_path, shared_data, monkeypatch):
    """The check that this process still holds the cell and the store of its result are one step under the
    cell's lock: a takeover either comes before it (the stalled result is dropped) or sees the cell complete."""
    from vprbench.spec import RunSettings
    from vprbench.sweep import runner

    cache = tmp_path / "cache"
    (cell,) = read_plan(plan).cells
    stalled, other = Claims(cache, lease_s=MIN_LEASE_S), Claims(cache, lease_s=MIN_LEASE_S)
    seen = {}
    save = runner.save_result

    def stall_while_storing(record, cache_dir):  # frozen (no heartbeat) past the lease, then stores
        stalled._stop.set()
        time.sleep(2 * MIN_LEASE_S)
        taker = threading.Thread(target=lambda: seen.update(state=other.claim(cell.key, lambda: bool(read_results(cache)))))
        taker.start()
        taker.join(timeout=5)  # with the fix it waits for this store, under the cell's lock
        save(record, cache_dir)

    monkeypatch.setattr(runner, "save_result", stall_while_storing)
    try:
        assert stalled.claim(cell.key, lambda: False) == ("claimed", "")
        outcome = runner._run_claimed(cell, stalled, "", RunSettings(cache_dir=cache, data_dir=shared_data), None, str(plan))
        deadline = time.monotonic() + 30
        while "state" not in seen and time.monotonic() < deadline:
            time.sleep(0.05)
        assert outcome.status == runner.RAN, outcome.detail
        assert seen["state"] == ("complete", "")  # not taken over: the stalled process stored first, and only it
        (record,) = read_results(cache)
        assert record["run_id"] == outcome.record["run_id"]
    finally:
        stalled.close()
        other.close()
