"""Caches under crashes, damage and limits, as two researchers sharing one cache folder meet them.

Descriptor stores and result records are covered by tests/store (torture, checksums, full
disks) and tests/leaderboard/test_store_torture.py; these are the gaps: the local features a
re-ranker keeps (stages/features.py) and saved vocabularies were trusted as read, a full disk while
features were kept crashed the process, and a file-size limit said what went wrong but not what to
do. Records in the wrong place: test_misplaced_records.py.
"""
from __future__ import annotations

import re
import resource
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from vprbench.aggregation.vocabulary import Vocabulary, load_vocabulary
from vprbench.errors import VPRBenchError
from vprbench.stages.features import FeatureStore

ROWS = 4


def features_of(row: int, points: int = 6) -> dict[str, np.ndarray]:
    """What an extractor computes for image `row` (deterministic: keypoints and descriptors)."""
    rng = np.random.default_rng(row)
    return {"points": rng.random((points, 2), dtype=np.float32),
            "descriptors": rng.integers(0, 255, (points, 128), dtype=np.uint8)}


@pytest.fixture
def kept(tmp_path):
    """(store, file): the local features of ROWS images, written once as a run would."""
    store = FeatureStore("sift", {"max_features": 6}, "corridor", {"database": "images-key"}, cache_dir=tmp_path)
    with store.opened("database", features_of) as get:
        for row in range(ROWS):
            get(row)
    return store, store.files("database")[0]  # one segment: written whole when the run ends


def read_all(store: FeatureStore) -> tuple[dict[int, dict], list[int], list[str]]:
    """Every image as a second run reads it: (arrays, rows computed again, warnings)."""
    computed = []

    def compute(row):
        computed.append(row)
        return features_of(row)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with store.opened("database", compute) as get:
            found = {row: get(row) for row in range(ROWS)}
    return found, computed, [str(w.message) for w in caught]


def flip(path: Path, offset: int, length: int, mask: int = 0x40) -> None:
    data = bytearray(path.read_bytes())
    for i in range(offset, offset + length):
        data[i] ^= mask
    path.write_bytes(bytes(data))


def test_flipped_bytes_in_local_features_are_recomputed_not_trusted(kept):
    """Was: a flipped byte in a kept keypoint was read back as it stood, and the re-ranking's
    recall changed without a word (hog + sift-ransac@5 on corridor: R@1 54.05 -> 59.46, exit 0)."""
    store, path = kept
    with h5py.File(path, "r") as f:
        where = [(f["images"][str(r)]["points"].id.get_offset(), f["images"][str(r)]["points"].nbytes)
                 for r in (1, 3)]
    for offset, _ in where:
        flip(path, offset + 3, 1)  # the exponent byte of the first coordinate
    found, computed, said = read_all(store)
    assert computed == [1, 3]
    assert all(np.array_equal(found[r][k], features_of(r)[k]) for r in range(ROWS) for k in ("points", "descriptors"))
    assert said == [f"Local features of 2 image(s) (1, 3) in {path} no longer matched the checksums written with them; "
                    "they were recomputed."]
    assert read_all(store)[1:] == ([], [])  # rewritten whole: the next run reads them


def test_local_features_whose_header_cannot_be_read_are_recomputed(kept):
    """Was: OSError 'Can't synchronously read data (bad global heap collection signature)'
    from reading the file's identity, which the command line showed as 'Cannot use
    feature_identity: ...', again on every run until the file was deleted by hand. Then: the file
    was discarded and its images recomputed without a word; now one line says so."""
    store, path = kept
    data = path.read_bytes()
    flip(path, data.index(b"GCOL"), 4)  # the heap holding the file's identity strings
    found, computed, said = read_all(store)
    assert computed == list(range(ROWS)) and said == [
        f"Local features {path} are damaged (Can't synchronously read data (bad global heap collection signature)); "
        "the file was discarded and its images are computed again."]
    assert all(np.array_equal(found[r]["points"], features_of(r)["points"]) for r in range(ROWS))


def test_a_damaged_image_group_discards_the_file_and_the_rerun_recovers(kept):
    """Was: HDF5's OSError from inside the re-ranking, on this run and every later one (the
    damaged file stayed). Now one line naming the file, which is discarded; the rerun recomputes.
    (Groups are read for segments written without a layout, by earlier versions.)"""
    store, path = kept
    with h5py.File(path, "a") as f:
        for key in ("arrays", "row_at", "row_crc32"):
            del f.attrs[key]
    data = path.read_bytes()
    heaps = [m.start() for m in re.finditer(b"HEAP", data) if b"points" in data[m.start():m.start() + 256]]
    assert heaps  # the local heaps naming each image's arrays
    for offset in heaps:
        flip(path, offset, 4)
    with pytest.raises(VPRBenchError) as refused:
        read_all(store)
    assert str(refused.value).startswith(f"Local features {path} are damaged (image 0 cannot be read: ")
    assert str(refused.value).endswith("the file was discarded: run again to recompute it.")
    assert not path.exists()
    found, computed, said = read_all(store)
    assert computed == list(range(ROWS)) and said == []
    assert all(np.array_equal(found[r]["descriptors"], features_of(r)["descriptors"]) for r in range(ROWS))


def test_a_layout_past_the_end_of_its_file_discards_the_file_and_the_rerun_recovers(kept):
    """Where a segment's arrays lie (its layout, read without HDF5) pointing outside the file: one
    line naming the file, which is discarded; the rerun recomputes."""
    store, path = kept
    with h5py.File(path, "a") as f:
        at = f.attrs["row_at"]
        at[0, 0, 0] = path.stat().st_size
        f.attrs["row_at"] = at
    with pytest.raises(VPRBenchError) as refused:
        read_all(store)
    assert str(refused.value).startswith(f"Local features {path} are damaged (image 0 cannot be read: ")
    assert "lies outside the file" in str(refused.value) and not path.exists()
    found, computed, said = read_all(store)
    assert computed == list(range(ROWS)) and said == []
    assert all(np.array_equal(found[r]["points"], features_of(r)["points"]) for r in range(ROWS))


def test_features_written_without_checksums_are_recomputed_once(kept):
    """A file from before groups carried a crc32: its images are computed again (never trusted),
    quietly, once."""
    store, path = kept
    with h5py.File(path, "a") as f:
        del f.attrs["rows"]  # files of that time did not list their rows either
        for row in range(ROWS):
            del f["images"][str(row)].attrs["crc32"]
    assert read_all(store)[1:] == (list(range(ROWS)), [])
    assert read_all(store)[1:] == ([], [])


def test_a_file_size_limit_says_what_to_do(shared_data, tmp_path, cli):
    """`ulimit -f` below a store's size (as on shared machines): the write fails with EFBIG.
    Was: 'Cannot use .../database.rank0-of-1.partial.h5: File too large.' and nothing more."""
    images = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]
    cache = tmp_path / "cache"

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))  # a hog store of 3 images is 430 KB

    done = subprocess.run([sys.executable, "-m", "vprbench", "describe", "--method", "hog", "--quiet", "--out",
                           tmp_path / "d.npy", "--cache-dir", cache, *images], capture_output=True, text=True,
                          timeout=120, preexec_fn=limited)
    store = next(cache.glob("stores/hog-*/describe-images-*"))
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.strip() == (
        f"error: Cannot use {store / 'queries.rank0-of-1.partial.h5'}: File too large; the file size limit "
        "(ulimit -f) or the filesystem's largest file is reached: raise the limit, or point --cache-dir at a "
        "folder on another disk.")
    assert [p.name for p in store.iterdir()] == [".lock"]  # nothing half-written left to trust
    code, _, err = cli("describe", "--method", "hog", "--quiet", "--out", tmp_path / "d.npy", "--cache-dir", cache,
                       *images)
    assert code == 0 and err.startswith("Wrote 3 descriptors")  # the limit lifted, the same cache simply runs
    assert np.load(tmp_path / "d.npy").shape == (3, 35721)


def test_a_saved_vocabulary_with_a_flipped_byte_is_refused(tmp_path, cli):
    """torch.load does not check the bytes it reads. Was: a cached vocabulary with one flipped bit
    loaded as it stood (dense-vlad fitted on a folder, corridor: every descriptor described again
    with the damaged centres, R@1 76.58 -> 77.48, exit 0, no word)."""
    centres = torch.arange(8 * 16, dtype=torch.float32).reshape(8, 16) / 7
    path = Vocabulary(centres, {"source": "indoor"}).save(tmp_path / "vocabulary.pt")
    assert torch.equal(load_vocabulary(path).centres, centres)  # whole: loads as saved
    data = path.read_bytes()
    flip(path, data.index(centres.numpy().tobytes()[:64]) + 41, 1)
    code, out, err = cli("vocabulary", "show", path)
    assert (code, out) == (1, "") and err == (
        f"error: Vocabulary file {path} is damaged: its centres no longer match the checksum written with them. "
        "Delete it and fit it again (`vprbench vocabulary fit`).\n")
    torch.save({"centres": centres, "meta": {}}, tmp_path / "earlier.pt")  # saved before vocabularies had a checksum
    torch.save(centres, tmp_path / "released.pt")  # the authors' bare tensor
    assert all(torch.equal(load_vocabulary(tmp_path / name).centres, centres) for name in ("earlier.pt", "released.pt"))


FILL_FEATURES = """
import sys
from pathlib import Path
from test_crash_audit import features_of
from vprbench.errors import VPRBenchError
from vprbench.stages.features import FeatureStore
store = FeatureStore("sift", {"max_features": 300}, "corridor", {"database": "images-key"}, cache_dir=Path(sys.argv[1]))
try:
    with store.opened("database", lambda row: features_of(row, 300)) as get:
        for row in range(40):  # 40 KB each: the limit is reached at the 7th or so
            get(row)
except VPRBenchError as error:
    sys.exit(f"error: {error}")
"""


def test_a_disk_filling_up_while_features_are_kept_is_one_line_and_resumes(tmp_path):
    """A write that fails (a file-size limit here; a full disk fails the same way). Was: HDF5's
    sieve buffer failed when h5py freed it ('Exception ignored ... Can't decrement id ref count
    (file write failed ... No space left on device)'), then the process died of a segmentation
    fault (exit -11) in the next flush: hog + sift-ransac on a nearly full tmpfs exited 139."""
    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))

    done = subprocess.run([sys.executable, "-c", FILL_FEATURES, tmp_path], capture_output=True, text=True, timeout=120,
                          preexec_fn=limited, cwd=Path(__file__).parent)
    store = FeatureStore("sift", {"max_features": 300}, "corridor", {"database": "images-key"}, cache_dir=tmp_path)
    path = store.path / "database.1.h5"  # the 40 images' segment (1.6 MB) is over the file size limit
    assert (done.returncode, done.stderr) == (1, f"error: Cannot use {path}: File too large; the file size limit "
                                                 "(ulimit -f) or the filesystem's largest file is reached: raise the "
                                                 "limit, or use a folder on another disk.\n")
    computed = []

    def compute(row):
        computed.append(row)
        return features_of(row, 300)

    with store.opened("database", compute) as get:  # the limit lifted: the next run completes
        found = {row: get(row) for row in range(40)}
    assert computed == list(range(40))  # nothing was written whole (a full disk keeps what was: test_disk_errors)
    assert all(np.array_equal(found[r][k], features_of(r, 300)[k]) for r in range(40)
               for k in ("points", "descriptors"))


KILLED_WRITING = """
import os, signal, sys
from pathlib import Path
from test_crash_audit import features_of
from vprbench.stages import features
features.SEGMENT_IMAGES = 4
checksum, calls = features._checksum, []

def killed(arrays):  # the 10th image checksummed: the 2nd of the 3rd segment, mid-write
    calls.append(1)
    if len(calls) == 10:
        os.kill(os.getpid(), signal.SIGKILL)
    return checksum(arrays)

features._checksum = killed
store = features.FeatureStore("sift", {"max_features": 6}, "corridor", {"database": "images-key"}, cache_dir=Path(sys.argv[1]))
with store.opened("database", features_of) as get:
    for row in range(16):
        get(row)
"""


def test_a_kill_while_a_segment_is_written_keeps_the_segments_before_it(tmp_path, monkeypatch):
    """kill -9 in the middle of writing local features: the segments written whole are read, the
    one half-written (a temporary file) is removed unread, and only its images and later ones are
    computed again."""
    done = subprocess.run([sys.executable, "-c", KILLED_WRITING, tmp_path], capture_output=True, text=True,
                          timeout=120, cwd=Path(__file__).parent)
    assert done.returncode == -9, done.stderr
    store = FeatureStore("sift", {"max_features": 6}, "corridor", {"database": "images-key"}, cache_dir=tmp_path)
    assert [p.name for p in store.files("database")] == ["database.1.h5", "database.2.h5"]
    assert len(list(store.path.glob(".database.3.h5.*.tmp"))) == 1  # the half-written segment
    computed = []

    def compute(row):
        computed.append(row)
        return features_of(row)

    monkeypatch.setattr("vprbench.stages.features.SEGMENT_IMAGES", 4)
    with store.opened("database", compute) as get:
        found = {row: get(row) for row in range(16)}
    assert computed == list(range(8, 16))
    assert all(np.array_equal(found[r][k], features_of(r)[k]) for r in range(16) for k in ("points", "descriptors"))
    assert [p.name for p in store.files("database")] == [f"database.{n}.h5" for n in (1, 2, 3, 4)]
    assert not list(store.path.glob("*.tmp"))


def test_images_computed_before_an_interrupt_are_written(tmp_path):
    """Ctrl-C (or an image that cannot be read) before a segment is full: what was computed is
    written on the way out, so the rerun starts where the run stopped."""
    store = FeatureStore("sift", {"max_features": 6}, "corridor", {"database": "images-key"}, cache_dir=tmp_path)

    def interrupted(row):
        if row == 5:
            raise KeyboardInterrupt
        return features_of(row)

    with pytest.raises(KeyboardInterrupt), store.opened("database", interrupted) as get:
        for row in range(ROWS + 2):
            get(row)
    store.computed = 0
    assert read_all(store)[1:] == ([], []) and store.computed == 0


class _StoredRows:
    """Rows as a store gives them: an array, the folder they lie in, and a key of their content."""

    def __init__(self, array, folder, content):
        from vprbench.row_sources import ArrayRows

        self._rows, self.folder, self._content = ArrayRows(array), folder, content
        self.row_count, self.dim, self.dtype = self._rows.row_count, self._rows.dim, self._rows.dtype
        self.read_rows, self.read_rows_at = self._rows.read_rows, self._rows.read_rows_at

    def content_key(self) -> str:
        return self._content


def test_a_post_processing_state_copied_from_other_rows_is_refitted(tmp_path):
    """Found by its file name alone: a PCA state fitted on another store's rows, copied under the
    name these rows' state has, was loaded and applied to them."""
    from vprbench.aggregation.pca import PCAWhitening
    from vprbench.evaluation.postprocess import fit_postprocessor

    rng = np.random.default_rng(0)
    mine, other = (rng.standard_normal((64, 16)).astype(np.float32) for _ in range(2))
    theirs = fit_postprocessor(PCAWhitening(8), _StoredRows(other, tmp_path / "b", "b" * 16), 2**28)
    (tmp_path / "a").mkdir()
    expected = fit_postprocessor(PCAWhitening(8), _StoredRows(mine, tmp_path / "a", "a" * 16), 2**28)
    assert expected["file"] != theirs["file"] and expected["key"]["rows"]["content"] == "a" * 16
    shutil.copyfile(theirs["file"], expected["file"])  # the other rows' state under this name
    refit = PCAWhitening(8)
    with pytest.warns(UserWarning, match="post-processing state .* is unusable .*fitted on other rows"):
        info = fit_postprocessor(refit, _StoredRows(mine, tmp_path / "a", "a" * 16), 2**28)
    assert info["state"] == "fitted"
    fresh = PCAWhitening(8).fit(mine)
    np.testing.assert_allclose(refit.transform(mine), fresh.transform(mine), atol=1e-5)  # fitted on these rows
    again = PCAWhitening(8)
    assert fit_postprocessor(again, _StoredRows(mine, tmp_path / "a", "a" * 16), 2**28)["state"] == "loaded"
