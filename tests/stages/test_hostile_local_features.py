"""A local-features segment of the right extractor and images whose checksums were written again over
arrays the stage does not compute (crafted, edited by hand, or an earlier version's): the image is
recomputed and said so in one warning naming the file, never handed to the stage (before: a
traceback from OpenCV or numpy, or 3-d keypoints silently read as 2-d ones)."""
import copy
import warnings

import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.stages import StageContext, create_stage
from vprbench.stages.features import FeatureStore

GOOD = {"points": np.arange(8, dtype=np.float32).reshape(4, 2),
        "descriptors": (np.arange(512) % 256).astype(np.uint8).reshape(4, 128)}
#: image 0's arrays as a crafted segment holds them, and what the warning says of them
HOSTILE = {
    "narrower descriptors": (dict(GOOD, descriptors=GOOD["descriptors"][:, :64].copy()),
                             r"descriptors uint8 \(4, 64\), not uint8 \(n, 128\)"),
    "no points": ({"descriptors": GOOD["descriptors"]}, r"arrays \['descriptors'\], not \['descriptors', 'points'\]"),
    "3-d points": (dict(GOOD, points=np.zeros((4, 3), np.float32)), r"points float32 \(4, 3\), not float32 \(n, 2\)"),
    "fewer points than descriptors": (dict(GOOD, points=GOOD["points"][:2].copy()),
                                      r"arrays of \[2, 4\] rows, not one row per feature"),
    "float descriptors": (dict(GOOD, descriptors=GOOD["descriptors"].astype(np.float32)),
                          r"descriptors float32 \(4, 128\), not uint8 \(n, 128\)"),
    "a scalar": (dict(GOOD, descriptors=np.array(5, np.uint8)), r"descriptors uint8 \(\), not uint8 \(n, 128\)"),
    "points not finite": (dict(GOOD, points=np.full((4, 2), np.nan, np.float32)), r"points holds values that are not finite"),
}


def written_aside(store: FeatureStore, split: str, images: dict) -> None:
    """`images` as a segment of `store`'s folder with checksums matching them, as a store that checks
    nothing (a crafted file) writes them."""
    writer = copy.copy(store)
    writer.form = None
    writer.path.mkdir(parents=True, exist_ok=True)
    writer._write(split, images)


def read_twice(store: FeatureStore, good: dict, said: str) -> None:
    """The first read recomputes image 0 and says why, naming the file; the second serves the recomputed one, silently."""
    computed = []

    def compute(row):
        computed.append(row)
        return good

    with pytest.warns(UserWarning, match=r"Local features of 1 image\(s\) \(0\) in \S+database\.1\.h5 are not what "
                                         rf"'{store.name}' computes \({said}\); they were recomputed\."):
        with store.opened("database", compute) as get:
            found = get(0)
    assert computed == [0] and all(np.array_equal(found[key], good[key]) for key in good)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with store.opened("database", compute) as get:
            found = get(0)
    assert computed == [0] and all(np.array_equal(found[key], good[key]) for key in good)


def store_of(stage_name: str, options: dict, corridor, cache_dir) -> FeatureStore:
    """The feature store the stage reads and writes on Corridor."""
    stage = create_stage(stage_name, options)
    return stage._store(StageContext(dataset=corridor, database=None, queries=None, cache_dir=cache_dir))


@pytest.mark.parametrize("alone", [True, False], ids=["read-at-offsets", "read-by-group"])
@pytest.mark.parametrize("case", HOSTILE)
def test_sift_arrays_the_stage_does_not_compute_are_recomputed_and_said(case, alone, corridor, tmp_path):
    arrays, said = HOSTILE[case]
    store = store_of("sift-ransac", {"k": 5}, corridor, tmp_path)
    # alone, the segment has a layout (read without HDF5); beside an image of other arrays it has none
    written_aside(store, "database", {0: arrays} if alone else {0: arrays, 1: GOOD})
    read_twice(store, GOOD, said)


def test_patch_mnn_recomputes_stored_patches_of_another_width(corridor, tmp_path):
    store = store_of("patch-mnn", {"k": 5, "backbone": "dinov2_vits14", "layer": 1, "resize": "56x70",
                                   "weights": "random"}, corridor, tmp_path)
    written_aside(store, "database", {0: {"patches": np.ones((20, 64), np.float16)}})
    read_twice(store, {"patches": np.ones((20, 384), np.float16)}, r"patches float16 \(20, 64\), not float16 \(n, 384\)")


@pytest.mark.parametrize("attribute, said", [("feature_identity", r"another extractor \('unknown' with "),
                                             ("images_key", "other images")])
def test_an_identity_attribute_edited_into_an_array_is_refused_naming_the_file(attribute, said, corridor, tmp_path):
    """Was: 'ValueError: The truth value of an array with more than one element is ambiguous', a traceback."""
    import h5py

    store = store_of("sift-ransac", {"k": 5}, corridor, tmp_path)
    written_aside(store, "database", {0: GOOD})
    with h5py.File(store.files("database")[0], "a") as f:
        f.attrs[attribute] = np.array(["a", "b"], dtype=h5py.string_dtype())
    with pytest.raises(VPRBenchError, match=rf"^Local features \S+database\.1\.h5 were computed by {said}.*: delete "
                                            r"that file \(it is recomputed\)\.$"):
        with store.opened("database", lambda row: GOOD):
            pass
