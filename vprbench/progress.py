"""Progress of long work, for a person at a terminal and for a batch job's log.

Every long loop (extraction, a sweep's cells) reports through the small interface of rich's
`Progress`: `add_task(description, total=, completed=)`, `advance(task, n)`, `update(task, ...)`,
used as a context manager. `progress_for(stream)` picks how it is shown: rich's live bars on a
terminal; without one (nohup, SLURM, CI) one plain line per task at most every `interval`
seconds, with phase, done/total, rate and time left; `quiet` shows nothing. A phase that
cannot count its work (fitting a vocabulary, a search) runs inside `phase(progress, what)`:
a spinner on a terminal, a line with the time elapsed every `interval` seconds in a log.
"""
from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

from .text import literal

#: at most one line per task this often, in a log
LOG_INTERVAL_S = 30.0


class Silent:
    """Progress that shows nothing."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **_) -> int:
        return 0

    def advance(self, task: int, advance: float = 1) -> None:
        pass

    def update(self, task: int, **_) -> None:
        pass


@dataclass
class _Task:
    description: str
    total: float | None
    completed: float
    started: float = field(default_factory=time.monotonic)
    shown: float = field(default_factory=time.monotonic)
    start_done: float = 0.0
    printed: bool = False


class LogProgress(Silent):
    """One line per task at most every `interval` seconds while it runs, and one when a task that
    printed ends: `progress: <phase> 1,200/3,576 (34 %), 41.2/s, about 58 s left`. A task done
    within `interval` prints nothing (short runs stay quiet)."""

    def __init__(self, stream=None, interval: float | None = None, clock=time.monotonic):
        self.stream, self.clock = stream or sys.stderr, clock
        self.interval = float(LOG_INTERVAL_S if interval is None else interval)
        self.tasks: dict[int, _Task] = {}

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **_) -> int:
        now = self.clock()
        number = len(self.tasks) + 1
        self.tasks[number] = _Task(description, total, completed, now, now, completed)
        return number

    def advance(self, task: int, advance: float = 1) -> None:
        found = self.tasks.get(task)
        if found is None:
            return
        found.completed += advance
        self._maybe(found)

    def update(self, task: int, *, description: str | None = None, total: float | None = None,
               completed: float | None = None, advance: float | None = None, **_) -> None:
        found = self.tasks.get(task)
        if found is None:
            return
        if description is not None:
            found.description = description
        if total is not None:
            found.total = total
        if completed is not None:
            found.completed = completed
        if advance:
            found.completed += advance
        self._maybe(found)

    def _maybe(self, task: _Task) -> None:
        done = task.total is not None and task.completed >= task.total
        if (done and task.printed) or (not done and self.clock() - task.shown >= self.interval):
            self._line(task, "done" if done else "")

    def _line(self, task: _Task, state: str) -> None:
        now = self.clock()
        task.shown, task.printed = now, True
        if task.total is None:
            count = f"{task.completed:,.0f}"
        else:
            share = f" ({100 * task.completed / task.total:.0f} %)" if task.total else ""
            count = f"{task.completed:,.0f}/{task.total:,.0f}{share}"
        elapsed, moved = now - task.started, task.completed - task.start_done
        rate = f", {moved / elapsed:,.1f}/s" if elapsed > 0 and moved > 0 else ""
        left = ""
        if task.total is not None and moved > 0 and task.completed < task.total:
            left = f", about {_duration((task.total - task.completed) * elapsed / moved)} left"
        what = " done" if state == "done" else ""
        print(literal(f"progress: {task.description}{what} {count}{rate}{left}"), file=self.stream, flush=True)


@contextmanager
def phase(progress, description: str):
    """Work that reports no counts, shown as alive: rich shows a spinner; a log gets
    `progress: <description>, 1 min elapsed` every interval (and `done in ...` if it printed)."""
    if progress is None or type(progress) is Silent:
        yield
        return
    if not isinstance(progress, LogProgress):  # rich: a task without a total is an indeterminate bar
        task = progress.add_task(description, total=None)
        try:
            yield
        finally:
            progress.update(task, total=1, completed=1)
        return
    stop, started, printed = threading.Event(), progress.clock(), []

    def beat():
        while not stop.wait(progress.interval):
            printed.append(True)
            print(literal(f"progress: {description}, {_duration(progress.clock() - started)} elapsed"),
                  file=progress.stream, flush=True)

    beater = threading.Thread(target=beat, name="vprbench-progress", daemon=True)
    beater.start()
    try:
        yield
    finally:
        stop.set()
        beater.join()
        if printed:
            print(literal(f"progress: {description} done in {_duration(progress.clock() - started)}"),
                  file=progress.stream, flush=True)


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 120:
        return f"{seconds} s"
    if seconds < 7200:
        return f"{seconds // 60} min"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"


def progress_for(stream=None, *, quiet: bool = False):
    """Live bars on a terminal, log lines otherwise, nothing when quiet."""
    stream = stream or sys.stderr
    if quiet:
        return Silent()
    if stream.isatty():
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
        from rich.text import Text

        class Literal(TextColumn):  # descriptions name methods and datasets: text, not markup or controls
            def render(self, task):
                return Text(literal(task.description))

        return Progress(Literal("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                        console=Console(file=stream, markup=False, emoji=False), transient=True)
    return LogProgress(stream)
