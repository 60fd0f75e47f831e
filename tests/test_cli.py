"""The command line end to end on real data, and every class of bad input."""
import json
import os
import shutil

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.paths import cache_root


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_evaluate_hog_on_corridor_then_served_from_store(capsys, shared_data):
    code, out, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data), "--json")
    assert code == 0, err
    record = json.loads(out)
    assert record["counts"] == {"database": 111, "queries": 111, "queries_without_positives": 0, "positive_pairs": 549,
                                "all_zero_queries": 0, "all_zero_database": 0}
    assert record["descriptors_computed"] == {"database": 111, "queries": 111}
    assert set(record["recall"]) == {"1", "5", "10", "20"}
    assert record["recall"]["1"] <= record["recall"]["5"] <= record["recall"]["10"] <= record["recall"]["20"]
    assert {"vprbench", "torch", "faiss"} <= set(record["versions"])

    code, out, _ = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data),
                       "--json", "--k", "1", "3")
    again = json.loads(out)
    assert again["descriptors_computed"] == {"database": 0, "queries": 0}
    assert again["recall"]["1"] == record["recall"]["1"] and set(again["recall"]) == {"1", "3"}

    code, out, _ = run(capsys, "leaderboard", "--format", "markdown")
    assert code == 0 and "| hog " in out and "corridor" in out


def test_describe_writes_descriptors_in_input_order(capsys, shared_data, tmp_path):
    a, b = shared_data / "corridor" / "ref" / "0000003.jpg", shared_data / "corridor" / "query" / "0000050.jpg"
    code, _, err = run(capsys, "describe", "--method", "hog", "--resize", "64", "64", str(a), str(b), "--out", str(tmp_path / "ab.npy"))
    assert code == 0, err
    run(capsys, "describe", "--method", "hog", "--resize", "64", "64", str(b), str(a), "--out", str(tmp_path / "ba.npy"))
    ab, ba = np.load(tmp_path / "ab.npy"), np.load(tmp_path / "ba.npy")
    assert ab.shape[0] == 2 and ab.dtype == np.float32
    np.testing.assert_array_equal(ab, ba[::-1])
    np.testing.assert_allclose(np.linalg.norm(ab, axis=1), 1, rtol=1e-5)


def test_publish_writes_markdown(capsys, shared_data, tmp_path):
    run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data), "--resize", "64", "64")
    code, out, _ = run(capsys, "leaderboard", "publish", "--to", str(tmp_path / "docs"))
    page = (tmp_path / "docs" / "leaderboard" / "index.md").read_text()
    assert code == 0 and "| hog [resize=64x64] | " in page and "[corridor](corridor.md)" in page


# --- bad input: clear message, exit 1, no traceback, nothing stored ------------------------------

def assert_user_error(code, err, *fragments):
    assert code == 1
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, err
    assert not read_results(), "a failed evaluation must not add a result"


def test_unknown_method_suggests(capsys, shared_data):
    code, _, err = run(capsys, "evaluate", "--method", "hogg", "--dataset", "corridor", "--data-dir", str(shared_data))
    assert_user_error(code, err, "Unknown method 'hogg'", "Did you mean: hog")


def test_unknown_dataset_suggests(capsys):
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "coridor")
    assert_user_error(code, err, "Unknown dataset 'coridor'", "corridor")


def test_option_the_method_does_not_take(capsys, shared_data):
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--layer", "3", "--dataset", "corridor", "--data-dir", str(shared_data))
    assert_user_error(code, err, "does not take option(s) layer")


@pytest.mark.parametrize("ks, message", [(["0"], "--k (ks) takes whole numbers >= 1"), (["abc"], "whole numbers"), (["500"], "exceeds the 111")])
def test_invalid_k(capsys, shared_data, ks, message):
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data), "--k", *ks)
    assert_user_error(code, err, message)


def test_missing_data_root_without_network(capsys, tmp_path, monkeypatch):
    import pooch

    def offline(*args, **kwargs):
        raise ConnectionError("no network")

    monkeypatch.setattr(pooch.Pooch, "fetch", offline)
    # a data root the user named is never downloaded into unless asked
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(tmp_path / "nothing"))
    assert_user_error(code, err, "not in the data root", "add --download")
    assert not (tmp_path / "nothing").exists(), "nothing created where the user did not ask"
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(tmp_path / "nothing"),
                       "--download")
    assert_user_error(code, err, "Downloading 'corridor'", "failed", "rerun")
    assert not (tmp_path / "nothing" / "corridor").exists(), "no half-downloaded dataset in place"


def corridor_copy(shared_data, tmp_path):
    root = tmp_path / "data" / "corridor"
    shutil.copytree(shared_data / "corridor", root, copy_function=os.symlink)
    return root


def test_missing_folder_named(capsys, shared_data, tmp_path):
    root = corridor_copy(shared_data, tmp_path)
    shutil.rmtree(root / "query")
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(root.parent))
    assert_user_error(code, err, "expected folder 'query'")


def test_corrupt_ground_truth_named(capsys, shared_data, tmp_path):
    root = corridor_copy(shared_data, tmp_path)
    (root / "ground_truth_new.npy").unlink()
    (root / "ground_truth_new.npy").write_bytes(b"garbage")
    code, _, err = run(capsys, "datasets", "info", "corridor", "--data-dir", str(root.parent))
    assert_user_error(code, err, "ground_truth_new.npy")


def test_corrupt_image_named_and_store_not_complete(capsys, shared_data, tmp_path):
    root = corridor_copy(shared_data, tmp_path)
    (root / "query" / "0000042.jpg").unlink()
    (root / "query" / "0000042.jpg").write_bytes(b"\xff\xd8 truncated jpeg")
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(root.parent), "--resize", "64", "64")
    assert_user_error(code, err, "0000042.jpg")
    assert not list(cache_root().rglob("queries.h5")), "the query store must not be complete"


def test_count_mismatch_warns_or_fails_strict(capsys, shared_data, tmp_path):
    root = corridor_copy(shared_data, tmp_path)
    (root / "query" / "0000110.jpg").unlink()  # the last query, and its ground-truth row
    gt = np.load(shared_data / "corridor" / "ground_truth_new.npy", allow_pickle=True)
    (root / "ground_truth_new.npy").unlink()
    np.save(root / "ground_truth_new.npy", gt[:110], allow_pickle=True)
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(root.parent), "--strict")
    assert_user_error(code, err, "110 query images", "expects 111")
    with pytest.warns(UserWarning, match="expects 111"):
        code, _, _ = run(capsys, "datasets", "info", "corridor", "--data-dir", str(root.parent), "--json")
    assert code == 0
    # a database image fewer shifts what the ground truth's indices name: refused, --strict or not
    (root / "ref" / "0000110.jpg").unlink()
    code, _, err = run(capsys, "datasets", "info", "corridor", "--data-dir", str(root.parent))
    assert_user_error(code, err, "110 database images", "names database images by their position")


def test_describe_bad_inputs(capsys, tmp_path):
    code, _, err = run(capsys, "describe", "--method", "hog", str(tmp_path / "none.jpg"), "--out", str(tmp_path / "x.npy"))
    assert_user_error(code, err, "Image not found", "none.jpg")
    code, _, err = run(capsys, "describe", "--method", "dense-vlad", __file__, "--out", str(tmp_path / "x.npy"))
    assert_user_error(code, err, "--fit-on")


def test_leaderboard_without_results(capsys, tmp_path, monkeypatch):
    monkeypatch.delenv("VPRBENCH_CACHE")  # the user cache, not made before the first run
    code, _, err = run(capsys, "leaderboard")
    assert_user_error(code, err, f"No results yet in the cache folder {tmp_path / 'user-cache' / 'vprbench'}: run")


def test_leaderboard_names_a_cache_folder_that_does_not_exist(capsys, tmp_path):
    """A mistyped --cache-dir said 'No results yet', as if the results were lost."""
    for command in (["leaderboard"], ["leaderboard", "compare", "hog", "sad", "--dataset", "corridor"],
                    ["leaderboard", "publish", "--to", str(tmp_path / "site")]):
        code, _, err = run(capsys, *command, "--cache-dir", str(tmp_path / "cahce"))
        assert_user_error(code, err, f"No results: the cache folder {tmp_path / 'cahce'} does not exist; check --cache-dir")
    assert not (tmp_path / "site").exists() and not (tmp_path / "cahce").exists()


def test_ablations_get_their_own_leaderboard_rows(capsys, shared_data):
    common = ["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data)]
    run(capsys, *common, "--resize", "64", "64")
    run(capsys, *common, "--resize", "128", "128", "--device", "cpu")
    code, out, _ = run(capsys, "leaderboard", "--format", "csv")
    rows = {line.split(",")[0] for line in out.splitlines()[1:] if line}
    assert code == 0 and rows == {"hog [resize=64x64]", "hog [resize=128x128]"}


def test_the_cli_answers_without_importing_heavy_libraries():
    """--help, methods list, datasets list and datasets info parse and answer with torch, timm, faiss,
    h5py, pandas and matplotlib not imported (they are imported where they are used)."""
    import subprocess
    import sys

    probe = ("import sys, io, contextlib\nfrom vprbench.cli.main import main\n"
             "for argv in (['methods', 'list'], ['datasets', 'list'], ['datasets', 'info', 'nordland', '--protocols']):\n"
             "    with contextlib.redirect_stdout(io.StringIO()):\n"
             "        assert main(argv) == 0, argv\n"
             "heavy = {'torch', 'timm', 'faiss', 'h5py', 'pandas', 'matplotlib', 'torchvision'}\n"
             "print(sorted(heavy & set(sys.modules)))\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", done.stdout


def test_summary_counts_one_query_in_the_singular(capsys, shared_data, tmp_path):
    own = tmp_path / "mydata"  # own-data.md's example: two database images, one query
    for split, folder, names in (("database", "ref", ("0000000", "0000050")), ("queries", "query", ("0000000",))):
        (own / split).mkdir(parents=True)
        for name in names:
            shutil.copyfile(shared_data / "corridor" / folder / f"{name}.jpg", own / split / f"{name}.jpg")
    (own / "positions.csv").write_text("image,x,y\ndatabase/0000000.jpg,0,0\ndatabase/0000050.jpg,100,0\n"
                                       "queries/0000000.jpg,1,0\n")
    code, out, err = run(capsys, "evaluate", "--method", "hog", "--resize", "32", "32", "--dataset", str(own), "--k", "1")
    assert code == 0, err
    assert "2 database, 1 query (0 without positives" in " ".join(out.split()), out  # the caption wraps


def test_every_leaderboard_option_is_explained_in_its_help():
    import argparse

    from vprbench.cli.main import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    unexplained = [a.option_strings for a in commands.choices["leaderboard"]._actions if a.option_strings and not a.help]
    assert unexplained == []


def test_describe_offers_no_strict_it_would_ignore(capsys, tmp_path):
    """--strict checks a dataset's image counts; describe loads no dataset (--dataset only applies its
    per-method settings), so it offered a flag that did nothing: now refused by name."""
    import argparse

    from vprbench.cli.main import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert "--strict" in commands.choices["evaluate"].format_help()  # evaluate loads a dataset: it checks
    assert "--strict" not in commands.choices["describe"].format_help()
    with pytest.raises(SystemExit) as exited:
        main(["describe", "--method", "hog", "--strict", __file__, "--out", str(tmp_path / "x.npy")])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and err.strip() == "error: unrecognized arguments: --strict; see 'vprbench describe --help'", err
