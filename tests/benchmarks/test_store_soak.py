"""Opt-in soak of the store torture suite: kill -9 at every moment of an evaluation, and 50 random kills.

    pytest tests/benchmarks/test_store_soak.py --benchmark-enable -s
"""
import json
import subprocess
import sys
from pathlib import Path

DRIVER = Path(__file__).resolve().parents[1] / "store" / "torture_driver.py"


def test_kill_at_every_moment(shared_data, tmp_path):
    done = subprocess.run([sys.executable, str(DRIVER), "kills", str(shared_data), str(tmp_path), "--spread", "100000",
                           "--timed", "50"], capture_output=True, text=True, cwd=DRIVER.parent, timeout=7200)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout)
    assert report["problems"] == []
    killed = sum(r["killed"] for r in report["runs"])
    assert killed >= report["moments"]
    print(f"\n{killed} kills in {len(report['runs'])} runs ({report['moments']} moments, "
          f"{len(report['fit_write_moments'])} in the fit-state write): every resume bit-identical")
