"""Two `vprbench datasets import` at once both stay recorded: the registry is read, changed and
rewritten under one lock. The test first shows the lost update is real: the same two imports,
with the lock taken out, both print 'Imported' and one is lost."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vprbench.datasets import read_registry

from hostile_files import tiny_images

#: runs `vprbench ARGS...` with a slow disk: both processes read their copies, meet, then read the
#: registry, which takes 0.5 s to come back, so the two read-modify-writes overlap for certain
CHILD = """
import contextlib, sys, time
from pathlib import Path
from vprbench.datasets import storage
from vprbench.cli.main import main

meeting, me, other, mode = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
read_layout, read_registry = storage.read_layout, storage.read_registry

def met(*args):
    dataset = read_layout(*args)
    (meeting / me).touch()
    deadline = time.time() + 60
    while not (meeting / other).exists() and time.time() < deadline:
        time.sleep(0.01)
    return dataset

def slow(*args, **kwargs):
    entries = read_registry(*args, **kwargs)
    time.sleep(0.5)
    return entries

storage.read_layout, storage.read_registry = met, slow
if mode == "without-lock":
    storage.lock = lambda *args, **kwargs: contextlib.nullcontext()
sys.exit(main(sys.argv[5:]))
"""


@pytest.fixture
def two_copies(tmp_path, shared_data) -> dict[str, Path]:
    """corridor (the real one) and a small Gardens Point copy, both outside the data root."""
    gardens = tmp_path / "elsewhere" / "gardens"
    names = [f"Image{i:03d}.jpg" for i in range(200)]  # the manifest's counts: its positives are indices
    tiny_images(gardens / "day_right", names)
    tiny_images(gardens / "night_right", names)
    rows = np.empty((200, 2), dtype=object)
    for i in range(200):
        rows[i] = i, [i]
    np.save(gardens / "gardens_gt.npy", rows, allow_pickle=True)
    return {"corridor": shared_data / "corridor", "gardens-point": gardens}


def import_both(tmp_path, copies: dict[str, Path], mode: str) -> tuple[list, dict]:
    data = tmp_path / "data"
    data.mkdir(exist_ok=True)
    meeting = tmp_path / f"meeting-{mode}"
    meeting.mkdir()
    env = {**os.environ, "VPRBENCH_CACHE": str(tmp_path / "cache")}
    runs = []
    for me, other in (("corridor", "gardens-point"), ("gardens-point", "corridor")):
        args = ["datasets", "import", me, str(copies[me]), "--data-dir", str(data)]
        command = [sys.executable, "-c", CHILD, str(meeting), me, other, mode, *args]
        runs.append(subprocess.Popen(command, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE))
    outputs = [run.communicate(timeout=240) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], outputs
    assert all("Imported" in out and "Traceback" not in err for out, err in outputs), outputs
    return outputs, json.loads((data / "datasets.json").read_text())


def test_two_imports_at_once_are_both_kept(tmp_path, two_copies):
    # the lost update is real: without the lock, both say 'Imported' and only one is recorded
    _, unlocked = import_both(tmp_path, two_copies, "without-lock")
    assert len(unlocked) == 1
    (tmp_path / "data" / "datasets.json").unlink()

    _, locked = import_both(tmp_path, two_copies, "with-lock")
    assert locked == {name: str(path.resolve()) for name, path in two_copies.items()}
    assert read_registry(tmp_path / "data") == locked

