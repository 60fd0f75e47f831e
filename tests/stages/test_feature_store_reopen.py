"""Reopening the local-feature store (which segment holds which image) at Pitts-250k size: 1,442
segments of 64 images. Was: every image group's attributes read (~7 ms a segment, 28 s under
load, nothing shown), and the stored bytes per image every group and array (~70 ms a segment); each
segment now lists its rows and their bytes in attributes written last.

Reading at that size: with more segments than kept open, nearly every read opened one with HDF5
(2.35 ms a read, 100,000 random reads in 234.5 s); each segment now also says where its arrays lie,
read with one plain file read each."""
from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest

from vprbench.stages.features import FeatureStore


def arrays(row: int) -> dict[str, np.ndarray]:
    return {"points": np.full((5, 2), row, np.float32), "descriptors": np.full((5, 128), row % 251, np.uint8)}


def written(tmp_path, monkeypatch, rows: int = 12) -> FeatureStore:
    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 4)
    store = FeatureStore("sift", {"benchmark": 1}, "pitts250k", {"database": "d"}, tmp_path)
    with store.opened("database", arrays) as get:
        for row in range(rows):
            get(row)
    assert [p.name for p in store.files("database")] == [f"database.{n}.h5" for n in range(1, rows // 4 + 1)]
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


def hdf5_opens(monkeypatch) -> list:
    opened, open_file = [], h5py.h5f.open
    monkeypatch.setattr(h5py.h5f, "open", lambda *args, **kwargs: opened.append(args[0]) or open_file(*args, **kwargs))
    return opened


def test_reading_images_of_more_segments_than_kept_open_opens_none_with_hdf5(tmp_path, monkeypatch):
    """Random reads over 12 segments, 2 kept open, nothing kept in memory: was one HDF5 open (and
    close) for nearly every read (about 0.7 ms of 1 ms a read at Pitts-250k size)."""
    store = written(tmp_path, monkeypatch, rows=48)
    monkeypatch.setattr("vprbench.stages.features.OPEN_SEGMENTS", 2)
    store.kept_bytes = 0
    opened = hdf5_opens(monkeypatch)
    order = np.random.default_rng(0).permutation(np.tile(np.arange(48), 4))
    with store.opened("database", lambda row: pytest.fail(f"image {row} computed")) as get:
        assert len(opened) == 12  # the index: each segment's attributes, once
        for row in order:
            found = get(int(row))
            assert all(np.array_equal(found[key], value) for key, value in arrays(int(row)).items())
    assert len(opened) == 12


def test_segments_without_a_layout_are_read_by_group(tmp_path, monkeypatch):
    """Segments of the version before layouts (rows listed, no offsets): read through HDF5, not recomputed."""
    store = written(tmp_path, monkeypatch)
    for path in store.files("database"):
        with h5py.File(path, "a") as f:
            for key in ("arrays", "row_at", "row_crc32"):
                del f.attrs[key]
    opened = hdf5_opens(monkeypatch)
    with store.opened("database", lambda row: pytest.fail(f"image {row} computed")) as get:
        assert [int(get(row)["points"][0, 0]) for row in range(12)] == list(range(12))
    assert len(opened) == 6  # the index, then each segment once (up to OPEN_SEGMENTS kept open)


def test_an_image_without_keypoints_is_read_back_by_layout(tmp_path, monkeypatch):
    """Empty arrays have no place in the file (HDF5 stores nothing): read back empty, with their shape."""
    store = FeatureStore("sift", {"benchmark": 1}, "pitts250k", {"database": "d"}, tmp_path)
    def none(row):
        return {key: value[:0] if row == 1 else value for key, value in arrays(row).items()}
    with store.opened("database", none) as get:
        [get(row) for row in range(3)]
    opened = hdf5_opens(monkeypatch)
    with store.opened("database", lambda row: pytest.fail(f"image {row} computed")) as get:
        assert [get(row)["descriptors"].shape for row in range(3)] == [(5, 128), (0, 128), (5, 128)]
    assert len(opened) == 1


@pytest.mark.parametrize("attr, edit, reason", [
    # before: OverflowError out of the index, on every run (the segment stayed)
    ("arrays", lambda found: '[["descriptors", "|u1", [1e400]], ["points", "<f4", [2]]]',
     "a layout's trailing shape [inf]"),
    # before: cast to int64 (NaN with numpy's "invalid value encountered in cast" warning)
    ("row_at", lambda found: np.full(found.shape, np.nan), "a layout of float64 values"),
])
def test_a_layout_of_other_numbers_than_whole_ones_is_recomputed(tmp_path, monkeypatch, attr, edit, reason):
    """A segment whose layout is not what vprbench writes is discarded and its images computed
    again, said in one line naming the file (was: without a word)."""
    store = written(tmp_path, monkeypatch)
    path = store.files("database")[0]
    with h5py.File(path, "a") as f:
        f.attrs[attr] = edit(f.attrs[attr])
    computed = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with store.opened("database", lambda row: computed.append(row) or arrays(row)) as get:
            for row in range(12):
                assert all(np.array_equal(get(row)[key], value) for key, value in arrays(row).items())
    assert computed == [0, 1, 2, 3] and not path.exists()
    assert [str(w.message) for w in caught] == [
        f"Local features {path} are damaged ({reason}); the file was discarded and its images are computed again."]


def test_a_stage_keeps_a_quarter_of_its_memory_budget_of_features_per_split(tmp_path, monkeypatch):
    """Per-image arrays read back are kept for the images that recur, within the stage's budget: it was
    a fixed 256 MB per open split whatever --search-memory said."""
    from types import SimpleNamespace

    from traced import peak_of
    from vprbench.stages.base import StageContext

    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 4)
    images = SimpleNamespace(name="pitts250k", images_fingerprint=lambda cache_dir: {"database": "d"})
    context = StageContext(dataset=images, database=None, queries=None, cache_dir=tmp_path, memory_budget=4 * 2**20)
    store = context.features("wide", {"benchmark": 1})
    wide = lambda row: {"values": np.full((2**18,), row, np.float32)}  # noqa: E731  (1 MB an image)
    with store.opened("database", wide) as get:
        for row in range(16):
            get(row)
    with store.opened("database", lambda row: pytest.fail(f"image {row} computed")) as get:
        get(0)
        _, peak = peak_of(lambda: [float(get(row)["values"][0]) for row in range(16)])
    assert peak < 4 * 2**20, peak  # the kept MB and one image read (its bytes, its array), not all 16
    assert store.kept_bytes == 2**20
