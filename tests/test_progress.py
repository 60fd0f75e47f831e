"""Progress in a batch job's log (stderr not a terminal): a line per phase at most every
interval, with done/total, rate and time left; opaque phases (a fit, a search) say they are
alive; --quiet prints none."""
import io
import re
import time

from vprbench import progress
from vprbench.cli.main import main
from vprbench.progress import LogProgress, Silent, phase


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_log_lines_at_most_every_interval_with_rate_and_time_left():
    stream, clock = io.StringIO(), Clock()
    shown = LogProgress(stream, interval=30, clock=clock)
    task = shown.add_task("hog corridor database", total=1000)
    for _ in range(50):  # 20 images a second
        clock.now += 1
        shown.advance(task, 20)
    assert stream.getvalue().splitlines() == [
        "progress: hog corridor database 600/1,000 (60 %), 20.0/s, about 20 s left",
        "progress: hog corridor database done 1,000/1,000 (100 %), 20.0/s"]
    quick = shown.add_task("hog corridor queries", total=5)
    clock.now += 1
    shown.advance(quick, 5)  # done within the interval: nothing printed
    assert len(stream.getvalue().splitlines()) == 2


def test_a_task_that_printed_says_when_it_is_done():
    stream, clock = io.StringIO(), Clock()
    shown = LogProgress(stream, interval=30, clock=clock)
    task = shown.add_task("dense-vlad corridor queries", total=111)
    clock.now = 31
    shown.advance(task, 56)
    clock.now = 62
    shown.advance(task, 55)
    assert stream.getvalue().splitlines() == [
        "progress: dense-vlad corridor queries 56/111 (50 %), 1.8/s, about 30 s left",
        "progress: dense-vlad corridor queries done 111/111 (100 %), 1.8/s"]


def test_a_phase_without_counts_prints_the_time_elapsed_and_its_end():
    stream = io.StringIO()
    with phase(LogProgress(stream, interval=0.05), "dense-vlad corridor fitting on 111 database images"):
        time.sleep(0.18)
    lines = stream.getvalue().splitlines()
    assert len(lines) >= 3 and lines[0] == "progress: dense-vlad corridor fitting on 111 database images, 0 s elapsed"
    assert lines[-1] == "progress: dense-vlad corridor fitting on 111 database images done in 0 s"
    quiet = io.StringIO()
    with phase(LogProgress(quiet, interval=60), "short"):
        pass
    with phase(Silent(), "nothing"):
        pass
    assert quiet.getvalue() == ""


def test_evaluate_in_a_batch_job_logs_every_phase_and_quiet_logs_none(capsys, shared_data, monkeypatch):
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.001)  # about every step: a line
    args = ["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data), "--resize", "64", "64"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    phases = {re.sub(r" [\d,]+/\d.*| done .*|, \d+ s elapsed", "", line) for line in err.splitlines()}
    assert {"progress: hog corridor database", "progress: hog corridor queries",
            "progress: hog corridor search (exact, 111 queries x 111 database)"} <= phases, err
    assert all(line.startswith("progress: ") for line in err.splitlines())
    assert "R@1" in out
    assert main(args + ["--quiet", "--k", "1"]) == 0  # served from the store, searched again: no line at all
    assert capsys.readouterr().err == ""
