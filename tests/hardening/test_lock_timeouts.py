"""A lock timeout is a finite number of seconds >= 0, checked in the one place every lock is taken
(fsutil.lock): filelock waits forever for a negative timeout, and a NaN one never runs out."""
from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import pytest

from vprbench import VPRBenchError
from vprbench.fsutil import lock

from hostile_files import assert_refused

HOLD = "import sys, time; from filelock import FileLock; l = FileLock(sys.argv[1]); l.acquire(); print('held', flush=True); time.sleep(60)"


@pytest.fixture
def held(tmp_path):
    """A lock file held by another process (for up to a minute)."""
    path = tmp_path / "x.lock"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(path)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    yield path
    holder.kill()
    holder.wait()


def test_the_attack_is_real_filelock_waits_forever_for_a_negative_timeout(held):
    from filelock import FileLock

    done = threading.Event()
    waiter = threading.Thread(target=lambda: (FileLock(held).acquire(timeout=-5), done.set()), daemon=True)
    waiter.start()
    assert not done.wait(2.0), "a timeout of -5 s should have given up at once; filelock waits instead"


@pytest.mark.parametrize("timeout", [-5, -0.001, math.nan, math.inf, "10", True])
def test_a_lock_timeout_that_is_not_finite_seconds_is_refused_at_once(held, timeout):
    started = time.monotonic()
    with pytest.raises(VPRBenchError, match=r"lock timeout \(--lock-timeout\) is a finite number of seconds >= 0"):
        with lock(held, timeout, what="the test lock"):
            pass
    assert time.monotonic() - started < 1.0


def test_zero_and_positive_timeouts_still_time_out(held):
    from vprbench.fsutil import LockTimeout

    started = time.monotonic()
    with pytest.raises(LockTimeout, match="Timed out after 0.3 s waiting for the test lock"):
        with lock(held, 0.3, what="the test lock"):
            pass
    assert time.monotonic() - started < 5


@pytest.mark.parametrize("value", ["-5", "nan", "inf"])
def test_lock_timeout_on_the_command_line_is_one_line(value, cli, shared_data, tmp_path):
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
                       f"--lock-timeout={value}")
    assert_refused(code, err, None, "--lock-timeout", "finite number of seconds >= 0")
    code, _, err = cli("results", "import", tmp_path / "none.tar.gz", "--into", tmp_path / "repo",
                       f"--lock-timeout={value}")
    assert code == 1 and "Traceback" not in err and "finite number of seconds >= 0" in err, err
    assert not (tmp_path / "repo").exists() or not any((tmp_path / "repo").iterdir())
