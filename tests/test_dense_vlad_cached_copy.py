"""A cached dense-vlad vocabulary is found by its folder's name (the key of the data and settings it is
fitted on). Another entry's file copied or moved there was served as this entry's: its centres keyed the
stores and the record said they were fitted on this entry's images. Its own metadata names what it was
fitted on: one that is not what the folder names is fitted again, said in a warning."""
import shutil
import warnings

import pytest

from vprbench.methods import create_method

SMALL = {"clusters": 8, "bin_sizes": (6,), "step": 8}


@pytest.fixture
def two_folders(shared_data, tmp_path):
    """Two folders of three Corridor images each, a cache, and the vocabulary identity dense-vlad fits on one."""
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    for folder, images in ((ours, range(0, 3)), (theirs, range(3, 6))):
        folder.mkdir()
        for path in sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[images.start:images.stop]:
            shutil.copyfile(path, folder / path.name)
    cache = tmp_path / "cache"

    def centres_of(folder):
        return create_method("dense-vlad", vocabulary=str(folder), cache_dir=cache, **SMALL).fingerprint()["vocabulary"]

    return ours, theirs, cache, centres_of


def test_another_entrys_vocabulary_copied_over_one_is_fitted_again_and_said(two_folders):
    ours, theirs, cache, centres_of = two_folders

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


def test_a_copied_vocabulary_is_said_once_and_not_by_a_run_that_finds_another_runs_fit(two_folders, monkeypatch):
    """Was: said twice by the run that fits it again (looked at before and under the fit's lock), and said
    ("fitting it again") by a run that, waiting for that lock, then found the other run's fit and used it."""
    from contextlib import contextmanager

    from vprbench import fsutil
    from vprbench.methods.dense_vlad import DenseVLAD

    ours, theirs, cache, centres_of = two_folders

    first, _ = centres_of(ours), centres_of(theirs)
    root = cache / "vocabularies" / "dense-vlad"
    cached, copied = next(root.glob("ours-*/vocabulary.pt")), next(root.glob("theirs-*/vocabulary.pt"))
    fitted = cached.read_bytes()
    shutil.copyfile(copied, cached)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert centres_of(ours) == first
    assert [str(w.message) for w in caught] == [
        f"The cached dense-vlad vocabulary {cached} was fitted on other data or settings than its folder names "
        "(another entry's file copied or moved there); fitting it again."]

    shutil.copyfile(copied, cached)
    lock = fsutil.lock

    @contextmanager
    def fitted_meanwhile(path, *args, **kwargs):  # another process held the lock and fitted it again
        cached.write_bytes(fitted)
        with lock(path, *args, **kwargs):
            yield

    monkeypatch.setattr(fsutil, "lock", fitted_meanwhile)
    monkeypatch.setattr(DenseVLAD, "fit_centres", lambda self, images: pytest.fail("fitted again"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert centres_of(ours) == first  # the other process's fit, used without a word
