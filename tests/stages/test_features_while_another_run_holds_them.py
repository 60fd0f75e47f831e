"""Two runs re-ranking on the same images at once share one local-features folder, whose lock a run holds for
its whole stage. The stored bytes per image (each re-ranking record's cost, asked after the stage) took that
lock too: a run whose stage had ended waited, without a word, for the other run's whole stage, or failed its
--lock-timeout with all its work done. Segments never change once in place: they are read without it."""
from __future__ import annotations

import subprocess
import sys

import numpy as np

from vprbench.stages.features import FeatureStore

#: holds the lock file given (an flock, as vprbench's lock takes) until killed
HOLD = ("import fcntl, sys, time; f = open(sys.argv[1], 'a'); fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); "
        "time.sleep(60)")


def arrays(row: int) -> dict[str, np.ndarray]:
    return {"points": np.full((5, 2), row, np.float32), "descriptors": np.full((5, 128), row % 251, np.uint8)}


def test_stored_bytes_are_read_while_another_run_holds_the_features(tmp_path, monkeypatch):
    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 4)
    store = FeatureStore("sift", {"benchmark": 1}, "corridor", {"database": "d"}, tmp_path, lock_timeout=2)
    with store.opened("database", arrays) as get:
        for row in range(8):
            get(row)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(store.path / ".lock")], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline() == "held\n"  # another run, in its stage
        assert store.bytes_per_image() == 5 * 2 * 4 + 5 * 128  # was: LockTimeout after 2 s
        # a segment that run discarded between this listing and its read: the others still count
        listed = store.files("database")
        monkeypatch.setattr(store, "files", lambda split: listed + [store.path / "database.3.h5"])
        assert store.bytes_per_image() == 5 * 2 * 4 + 5 * 128
    finally:
        holder.kill()
        holder.wait()
