"""A cached dense-vlad vocabulary is found by its folder's name (the key of the data and settings it is
fitted on). Another entry's file copied or moved there was served as this entry's: its centres keyed the
stores and the record said they were fitted on this entry's images. Its own metadata names what it was
fitted on: one that is not what the folder names is fitted again, said in a warning."""
import shutil
import warnings

import pytest

from vprbench.methods import create_method

SMALL = {"clusters": 8, "bin_sizes": (6,), "step": 8}


def test_another_entrys_vocabulary_copied_over_one_is_fitted_again_and_said(shared_data, tmp_path):
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    for folder, images in ((ours, range(0, 3)), (theirs, range(3, 6))):
        folder.mkdir()
        for path in sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[images.start:images.stop]:
            shutil.copyfile(path, folder / path.name)
    cache = tmp_path / "cache"

    def centres_of(folder):
        return create_method("dense-vlad", vocabulary=str(folder), cache_dir=cache, **SMALL).fingerprint()["vocabulary"]

    first, other = centres_of(ours), centres_of(theirs)
    assert first != other
    root = cache / "vocabularies" / "dense-vlad"
    cached = next(root.glob("ours-*/vocabulary.pt"))
    shutil.copyfile(next(root.glob("theirs-*/vocabulary.pt")), cached)
    with pytest.warns(UserWarning, match=rf"The cached dense-vlad vocabulary {cached} was fitted on other data or "
                                         r"settings than its folder names \(another entry's file copied or moved "
                                         r"there\); fitting it again\."):
        assert centres_of(ours) == first  # the same seeded fit, not the copied centres
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert centres_of(ours) == first and centres_of(theirs) == other  # fitted again in place: read silently
