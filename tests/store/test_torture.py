"""kill -9 at many moments (the fit-state write included) and concurrent runs on one cache, in real processes.

The driver (torture_driver.py) forks a process per run; see its docstring. A longer soak
(every moment, more random kills) is in tests/benchmarks/test_store_soak.py.
"""
import json
import subprocess
import sys
from pathlib import Path

DRIVER = Path(__file__).with_name("torture_driver.py")


def drive(*args, timeout=600) -> dict:
    done = subprocess.run([sys.executable, str(DRIVER), *map(str, args)], capture_output=True, text=True,
                          cwd=DRIVER.parent, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def test_kill_minus_nine_at_many_moments_resumes_bit_identically(shared_data, tmp_path):
    report = drive("kills", shared_data, tmp_path, "--spread", 12, "--timed", 6)
    # every resume: exit 0, stores and fit bit-identical to a clean run, only the rows not flagged
    # done at the kill described again, a saved fit reused, nothing left over or discarded
    assert report["problems"] == []
    runs = report["runs"]
    assert len(report["fit_write_moments"]) >= 5  # the fit-state write has several moments: each one is killed
    in_fit_write = [r for r in runs if r["kind"] == "moment" and r["at"] in report["fit_write_moments"]]
    assert len(in_fit_write) == len(report["fit_write_moments"]) and all(r["killed"] for r in in_fit_write)
    assert all(r["killed"] for r in runs if r["kind"] == "moment") and sum(r["killed"] for r in runs) >= 16


def test_three_identical_and_four_different_runs_at_once(shared_data, tmp_path):
    report = drive("concurrent", shared_data, tmp_path)
    assert set(report["statuses"].values()) == {0}
    runs = report["runs"]
    assert all(run["same_as_alone"] for run in runs.values()), runs
    sharing = [runs[label] for label in ("same-1", "same-2", "same-3", "other-k")]  # one store between them
    assert sorted(sum(r["computed"].values()) for r in sharing) == [0, 0, 0, 222]  # described once, reused three times
    assert sum(r["fits"] for r in sharing) == 1
    assert all(not run["warnings"] for run in runs.values())  # nothing discarded: no one deleted another's work
    assert report["leftovers"] == [] and report["complete_stores"] == 8
