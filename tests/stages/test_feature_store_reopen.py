"""Reopening the local-feature store (which segment holds which image) at Pitts-250k size: 1,442
segments of 64 images. Was: every image group's attributes read (~7 ms a segment, 28 s under
load, nothing shown), and the stored bytes per image every group and array (~70 ms a segment); each
segment now lists its rows and their bytes in attributes written last."""
from __future__ import annotations

import h5py
import numpy as np

from vprbench.stages.features import FeatureStore


def arrays(row: int) -> dict[str, np.ndarray]:
    return {"points": np.full((5, 2), row, np.float32), "descriptors": np.full((5, 128), row % 251, np.uint8)}


def written(tmp_path, monkeypatch, rows: int = 12) -> FeatureStore:
    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 4)
    store = FeatureStore("sift", {"benchmark": 1}, "pitts250k", {"database": "d"}, tmp_path)
    with store.opened("database", arrays) as get:
        for row in range(rows):
            get(row)
    assert [p.name for p in store.files("database")] == ["database.1.h5", "database.2.h5", "database.3.h5"]
    return store


def test_reopening_reads_no_image_group(tmp_path, monkeypatch):
    store = written(tmp_path, monkeypatch)
    visited = []
    item = h5py.Group.__getitem__

    def counted(self, name):
        if name != "/":  # h5py's own, for a file's attributes
            visited.append(name)
        return item(self, name)

    monkeypatch.setattr(h5py.Group, "__getitem__", counted)
    with store.opened("database", lambda row: (_ for _ in ()).throw(AssertionError(f"image {row} computed"))) as get:
        assert visited == []  # the index came from 3 attributes per segment, no group opened
        assert [int(get(row)["points"][0, 0]) for row in (11, 0, 5)] == [11, 0, 5]
    visited.clear()
    # the record's stored bytes, asked after every re-ranking run: was every group and array (~70 ms a segment)
    assert store.bytes_per_image() == 5 * 2 * 4 + 5 * 128 and visited == []


def test_segments_without_their_row_list_are_still_read(tmp_path, monkeypatch):
    """Segments written by earlier versions (no `rows` attribute): found by their groups, not recomputed."""
    store = written(tmp_path, monkeypatch)
    for path in store.files("database"):
        with h5py.File(path, "a") as f:
            del f.attrs["rows"], f.attrs["row_bytes"]
    computed = []
    with store.opened("database", lambda row: computed.append(row) or arrays(row)) as get:
        assert [int(get(row)["points"][0, 0]) for row in range(12)] == list(range(12))
    assert computed == [] and store.bytes_per_image() == 5 * 2 * 4 + 5 * 128
