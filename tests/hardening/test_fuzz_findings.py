"""Bad input found by a randomized walk over every command and option: values OpenCV's HOG cannot
take and a path that is a symbolic-link loop. Each was a traceback; now one line, exit 1, nothing
stored."""
from __future__ import annotations

import os

import pytest

from vprbench.paths import cache_root

from hostile_files import assert_refused

HOG = ["evaluate", "--method", "hog", "--dataset", "corridor", "--quiet"]


@pytest.mark.parametrize("args, message", [
    # OpenCV: 'integer won't fit into a C int', as a traceback
    (["-o", "bins=3000000000"], "hog: option bins takes at most 180 orientation bins (one a degree of OpenCV's 0-180 degree range); got 3000000000."),
    # OpenCV: an 'Insufficient memory' traceback at the first image, after the stores were opened
    (["-o", "bins=100000000"], "hog: option bins takes at most 180 orientation bins (one a degree of OpenCV's 0-180 degree range); got 100000000."),
    (["--resize", 16, 16, "-o", "cell=8", "-o", "block=16", "-o", f"block_stride={2**70}"],
     f"hog: option block_stride takes at most 2147483647 pixels (OpenCV's limit); got {2**70}."),
])
def test_hog_sizes_past_opencvs_range_are_one_line(args, message, shared_data, cli):
    code, _, err = cli(*HOG, *args, "--data-dir", shared_data)
    assert_refused(code, err, None, message)
    assert not (cache_root() / "stores").exists(), "a refused run opened a descriptor store"


def test_a_symlink_loop_as_cache_folder_is_one_line(shared_data, tmp_path, cli):
    loop = tmp_path / "loop"
    os.symlink(tmp_path / "back", loop)
    os.symlink(loop, tmp_path / "back")
    code, _, err = cli("describe", "--method", "hog", "--resize", 32, 32, "--out", tmp_path / "d.npy", "--quiet",
                       "--cache-dir", loop, shared_data / "corridor" / "query" / "0000000.jpg")
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    # the same line on every Python (pathlib's loop is a RuntimeError before 3.13, an OSError from 3.13 on)
    assert err.startswith(f"error: Cannot use {loop}/stores/hog-"), err
    assert err.rstrip().endswith(": Too many levels of symbolic links; a symbolic link in this path leads back to "
                                 "itself: fix or remove the link, or give another path."), err
    assert not (tmp_path / "d.npy").exists()


def test_a_path_of_bytes_that_are_not_utf8_is_taken(shared_data, tmp_path, monkeypatch, cli):
    """Linux paths are bytes: Python hands b'\\xff' over as '\\udcff', which the lock's holder note (the
    command line, for people) could not encode, so every command that took a lock was a traceback."""
    cache = tmp_path / "cache\udcff"
    # first: the note keeps the command's first 200 characters
    args = ["describe", "--cache-dir", str(cache), "--method", "hog", "--resize", "32", "32", "--out",
            str(tmp_path / "d.npy"), "--quiet", str(shared_data / "corridor" / "query" / "0000000.jpg")]
    monkeypatch.setattr("sys.argv", ["vprbench", *args])
    code, _, err = cli(*args)
    assert code == 0 and "Traceback" not in err, err
    assert (tmp_path / "d.npy").is_file() and os.fsencode(cache).endswith(b"cache\xff")
    assert list(cache.glob("stores/hog-*/describe-images-*"))  # the store was made in the folder given


@pytest.mark.parametrize("given", [["--vocabulary", "indoor"], ["-o", "vocabulary=c_centers.pt"]])
def test_a_vocabulary_given_to_a_fit_is_refused_not_ignored(given, shared_data, cli):
    """The fit ran and stored its centres; the vocabulary named was never read."""
    code, _, err = cli("vocabulary", "fit", "--dataset", "corridor", "--method", "anyloc", "--backbone", "dinov2_vits14",
                       "--weights", "random", "--layer", 1, "--clusters", 2, "--resize", 28, 28, "--budget", 50,
                       "--quiet", *given, "--data-dir", shared_data)
    assert_refused(code, err, None, f"vocabulary fit: --vocabulary {given[-1].split('=')[-1]} names centres to use, "
                   "and a fit makes them; drop it (--domain or --dataset says what to fit on).")
    assert not (cache_root() / "vocabularies").exists()


@pytest.mark.parametrize("flag", ["--data-dir", "--cache-dir"])
def test_an_empty_folder_option_is_refused_not_read_as_the_default(flag, shared_data, tmp_path, monkeypatch, cli):
    """--data-dir '' (an unset shell variable) was the default data root, and the dataset was downloaded there."""
    monkeypatch.setenv("VPRBENCH_DATA", str(tmp_path / "default-data"))
    code, _, err = cli(*HOG, "--resize", 32, 32, flag, "")
    assert_refused(code, err, None, f"{flag} is '', which names no folder: give a folder, or leave it unset.")
    assert not (tmp_path / "default-data").exists()
