"""Bad option values found by an audit of every command's options (0, negative, huge, nan, empty,
duplicates, -o spellings): each gets one clear line naming the option and a non-zero exit, with no
traceback, no crash and nothing stored."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from own_folders import corridor_folder

from vprbench.errors import VPRBenchError
from vprbench.search.approximate import check_options
from vprbench.methods.checks import choice, whole
from vprbench.spec import check_ks

from hostile_files import assert_refused

HOG = ["evaluate", "--method", "hog", "--dataset", "corridor", "--quiet"]
REPO = Path(__file__).resolve().parents[2]


def test_an_hnsw_graph_of_one_link_is_refused_not_a_crash(shared_data, tmp_path):
    """faiss's HNSW with M = 1 killed the process (a segmentation fault, no message) once the
    descriptors were computed: hnsw_m takes at least 2, checked when the run is specified."""
    with pytest.raises(VPRBenchError, match="hnsw_m takes a whole number >= 2; got 1"):
        check_options("hnsw", {"hnsw_m": 1})
    check_options("hnsw", {"hnsw_m": 2})
    env = {**os.environ, "VPRBENCH_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-m", "vprbench", *HOG, "--data-dir", str(shared_data), "--index", "hnsw",
                           "--index-option", "hnsw_m=1"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 1, (done.returncode, done.stderr)
    assert done.stderr.strip() == "error: --index hnsw option hnsw_m takes a whole number >= 2; got 1.", done.stderr
    assert not list((tmp_path / "cache").rglob("*.h5")), "a refused run wrote a descriptor store"


@pytest.mark.parametrize("given", ["./own", "own"])
def test_describe_names_a_folder_of_ones_own_given_as_dataset(given, shared_data, cli, tmp_path, monkeypatch):
    """It said "Unknown dataset './own' ... or pass a folder path for your own data": the very thing given."""
    (tmp_path / "own" / "database").mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    code, _, err = cli("describe", "--method", "hog", "--dataset", given, "--out", tmp_path / "d.npy",
                       shared_data / "corridor" / "query" / "0000000.jpg")
    assert_refused(code, err, None, f"{given} is a folder of your own; here a benchmark's name is needed: run "
                   "'vprbench datasets list' to see them.")
    assert not (tmp_path / "d.npy").exists()


@pytest.mark.parametrize("args", [["datasets", "import", "./own", "SRC"], ["datasets", "download", "./own"]])
def test_a_folder_where_a_benchmark_name_is_needed_is_named_as_such(args, cli, tmp_path, monkeypatch):
    (tmp_path / "own").mkdir()
    (tmp_path / "src").mkdir()
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(*[str(tmp_path / "src") if a == "SRC" else a for a in args], "--data-dir", tmp_path / "root")
    assert_refused(code, err, None, "./own is a folder of your own; here a benchmark's name is needed")
    assert not (tmp_path / "root").exists()


def test_datasets_import_refuses_an_empty_path_not_the_current_folder(cli, tmp_path, monkeypatch):
    """'' was read as the current folder: its layout was checked and a download into its parent suggested."""
    monkeypatch.chdir(tmp_path)
    code, _, err = cli("datasets", "import", "corridor", "", "--data-dir", tmp_path / "root")
    assert code == 2 and "argument path: expected a path, got ''" in err and "Traceback" not in err, err
    assert not (tmp_path / "root").exists()


def test_datasets_verify_refuses_sample_beside_all_images(shared_data, cli):
    """--sample was dropped without a word when --all-images decodes every image."""
    code, _, err = cli("datasets", "verify", "corridor", "--data-dir", shared_data, "--sample", "5", "--all-images")
    assert_refused(code, err, None, "--sample 5 is not used with --all-images (every image is decoded): leave it out.")


@pytest.mark.parametrize("name", ["centres.npy", "centres.txt"])
def test_vocabulary_fit_output_is_a_pt_file(name, cli, tmp_path):
    """A fit's --output is a torch file whatever its name: 'centres.npy' was written, then refused by every
    command that read it ('not a .npy file')."""
    code, _, err = cli("vocabulary", "fit", "--method", "dense-vlad", "--domain", "indoor", "--output", tmp_path / name)
    assert code == 2 and f"argument --output: expected a .pt file, got {tmp_path / name}" in err, err
    assert "Traceback" not in err and not (tmp_path / name).exists()


@pytest.mark.parametrize("args, flag", [
    (["leaderboard", "publish", "--to", "{tmp}/typo/docs"], "--to"),
    (["reproduce", "anyloc", "--table", "layer", "--data-dir", "{tmp}/no-data", "--publish", "{tmp}/typo/pages"],
     "--publish"),
    (["results", "import", "{tmp}/runs.tar.gz", "--into", "{tmp}/typo/repo"], "--into"),
])
def test_a_folder_to_write_under_a_missing_folder_is_refused_not_made(args, flag, cli, tmp_path):
    """A typo in --to, --publish or --into made the whole tree of folders (/nonexist/x from the root) and wrote
    there."""
    (tmp_path / "runs.tar.gz").write_bytes(b"")  # refused later, if it came to it: the folder is checked first
    code, out, err = cli(*[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert code == 1 and "Traceback" not in err, err
    assert err.strip() == (f"error: {flag} {tmp_path / 'typo' / args[-1].rsplit('/', 1)[-1]}: the folder "
                           f"{tmp_path / 'typo'} does not exist: create it first or write elsewhere."), err
    assert not (tmp_path / "typo").exists()


@pytest.mark.parametrize("args, flag", [
    (["publish", "--to", "{tmp}/docs", "--format", "csv"], "--format is for 'leaderboard show'; 'leaderboard publish'"),
    (["compare", "a", "b", "--dataset", "d", "--track", "sequence"],
     "--track is for 'leaderboard show'; 'leaderboard compare'"),
])
def test_leaderboard_show_options_given_to_another_action_are_refused(args, flag, cli, tmp_path):
    """--format and --track were dropped without a word by 'publish' and 'compare'."""
    code, _, err = cli("leaderboard", *[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert_refused(code, err, None, flag)
    assert not (tmp_path / "docs").exists()


def test_candidates_export_of_a_small_database_is_not_refused_for_recall_at_20(shared_data, cli, tmp_path):
    """On a database of fewer than 20 images every export stopped with 'K = 20 exceeds ...: give --k with values
    up to 3': the default Recall@K, which an export never computes, and --k there is the depth, already 2."""
    own = corridor_folder(shared_data, tmp_path / "own")
    export = ["candidates", "export", "--method", "hog", "--resize", "64", "64", "--dataset", own, "--quiet"]
    code, _, err = cli(*export, "--k", "2", "--out", tmp_path / "c.h5")
    assert code == 0 and "Wrote the top 2 candidates of 2 queries" in err, err
    code, _, err = cli(*export, "--k", "4", "--out", tmp_path / "d.h5")
    assert code == 1 and err.strip() == ("error: 4 candidates per query asked for, but the database of own holds 3 "
                                         "images: ask for at most 3."), err
    assert not (tmp_path / "d.h5").exists()


@pytest.mark.parametrize("args, message", [
    (["--batch-size", "2", "-o", "batch_size=4"], "--batch-size 2 and -o batch_size=4 disagree; give batch_size once."),
    (["--workers", "0", "-o", "workers=1"], "--workers 0 and -o workers=1 disagree; give workers once."),
    (["--search-memory", "1GB", "-o", "memory_budget=2GB"],
     "--search-memory 1GB and -o memory_budget=2GB disagree; give memory_budget once."),
])
def test_a_run_setting_given_two_values_is_refused(args, message, shared_data, cli):
    """The flag won and the -o value was dropped without a word; two values of a method option were refused."""
    code, _, err = cli(*HOG, "--data-dir", shared_data, *args)
    assert_refused(code, err, None, message)


def test_a_run_setting_given_twice_alike_runs(shared_data, cli):
    code, _, err = cli(*HOG, "--data-dir", shared_data, "--resize", "64", "64", "--search-memory", "1GB",
                       "-o", "memory_budget=1000MB", "--batch-size", "8", "-o", "batch_size=8")
    assert code == 0, err


@pytest.mark.parametrize("value, said", [("lots", "--search-memory (memory_budget) 'lots' is not understood"),
                                         ("0", "--search-memory (memory_budget) must be positive, got '0'"),
                                         # was: OverflowError: cannot convert float infinity to integer
                                         ("9" * 400, "--search-memory (memory_budget) '9999999999999999999999"),
                                         ("10000000000TB", "is more than any machine holds (at most "
                                                           "9,223,372,036,854,775,807 bytes): give e.g. 16GB.")])
def test_a_bad_search_memory_names_its_option(value, said, shared_data, cli, tmp_path):
    """(was: "Memory size 'lots' is not understood", naming no option)"""
    code, _, err = cli(*HOG, "--data-dir", shared_data, "--search-memory", value, "--cache-dir", tmp_path / "cache")
    assert_refused(code, err, None, said)
    assert not (tmp_path / "cache" / "stores").exists()


def test_an_option_value_too_long_for_a_file_name_is_judged_by_the_method(shared_data, cli, tmp_path):
    """A value longer than a file name may be (ENAMETOOLONG) was "cannot read the file of option cell": no file was
    meant; the method's own check names what the option takes."""
    code, _, err = cli(*HOG, "--data-dir", shared_data, "-o", "cell=" + "x" * 300, "--cache-dir", tmp_path / "cache")
    assert_refused(code, err, None, "hog: option cell takes a whole number >= 1")
    assert "cannot read the file" not in err and not (tmp_path / "cache" / "stores").exists()


@pytest.mark.parametrize("check", [check_ks, lambda big: whole("hog", "cell", big),
                                   lambda big: choice("hog", "norm", big, ["l2"])])
def test_a_value_thousands_of_characters_long_is_shown_short(check):
    """A 5,000-digit --k or method option was echoed whole: one line, but thousands of characters."""
    with pytest.raises(VPRBenchError) as refused:
        check("9" * 5000)
    assert len(str(refused.value)) < 300 and "..." in str(refused.value)
