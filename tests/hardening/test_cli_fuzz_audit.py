"""Bad input found by an audit of every command and option: values past a library's range, empty
paths and names, options the chosen action ignores, a stage given as the other kind, files where
folders are needed and names too long. Each gets one clear line and a non-zero exit, with no
traceback and nothing stored under a wrong name."""
from __future__ import annotations

import pytest

from vprbench.cli.main import main
from vprbench.paths import cache_root

from hostile_files import assert_refused

IMAGE = ["corridor", "query", "0000000.jpg"]
HOG = ["evaluate", "--method", "hog", "--dataset", "corridor", "--quiet"]


def image(shared_data):
    return shared_data.joinpath(*IMAGE)


# ---------------------------------------------------------------- numbers past what a library takes
@pytest.mark.parametrize("args, message", [
    # the data loader crashed on a batch beyond sys.maxsize after the store was opened
    (["--batch-size", "99999999999999999999"], "hog: option batch_size takes at most 2147483647 images per batch"),
    (["-o", "batch_size=99999999999999999999"], "hog: option batch_size takes at most 2147483647 images per batch"),
    # an infinite stage option could not be hashed into the run's identity (JSON has no inf)
    (["--rerank", "aqe", "--rerank-option", "alpha=inf"], "Stage 'aqe' option alpha: Input should be a finite number"),
    (["--rerank", "sift-ransac", "--rerank-k", "3", "--rerank-option", "threshold=inf"],
     "Stage 'sift-ransac' option threshold: Input should be a finite number"),
])
def test_values_past_a_librarys_range_are_one_line(args, message, shared_data, cli):
    code, _, err = cli(*HOG, *args, "--data-dir", shared_data)
    assert_refused(code, err, None, message)


def test_an_infinite_bundle_size_is_one_line(tmp_path, cli):
    code, _, err = cli("results", "verify", tmp_path / "runs.tar.gz", "--max-size", "inf")
    assert_refused(code, err, None, "--max-size takes a positive number of MiB, got inf.")


@pytest.mark.parametrize("args, message", [
    (["--seed", str(2**32)], f"seed (--seed) must be a whole number >= 0, got {2**32}; the largest is {2**32 - 1}"),
    (["--budget", "99999999999999999999999"], "more than this machine's memory"),
    (["--exact", "--budget", "5"], "--budget bounds the sampled fit and --exact fits on every patch: give one of them."),
    # was 'Sample budget must be at least 1 feature', naming no option
    (["--budget", "0"], "--budget takes a whole number >= 1 (the features kept for the fit), got 0."),
])
def test_vocabulary_fit_sizes_are_checked_before_any_image(args, message, shared_data, cli):
    code, _, err = cli("vocabulary", "fit", "--dataset", "corridor", "--method", "anyloc", "--backbone", "dinov2_vits14",
                       "--weights", "random", "--layer", 1, "--clusters", 2, "--resize", 28, 28, *args,
                       "--data-dir", shared_data)
    assert_refused(code, err, None, message)
    assert not (cache_root() / "vocabularies").exists()


# ---------------------------------------------------------------- empty values
@pytest.mark.parametrize("args, flag", [
    (["describe", "--method", "hog", "--out", "", "x.jpg"], "--out"),
    (["candidates", "export", "--method", "hog", "--dataset", "corridor", "--out", ""], "--out"),
    (["results", "export", "--run", "x", "--to", ""], "--to"),
    (["results", "import", "runs.tar.gz", "--into", ""], "--into"),
    (["leaderboard", "publish", "--to", ""], "--to"),
    (["reproduce", "anyloc", "--table", "2", "--publish", ""], "--publish"),
    (["run", ""], "plan"),  # was: "Cannot read plan .: Is a directory."
])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(args, flag, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(args)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "Traceback" not in err
    assert f"argument {flag}: expected a path, got ''" in err
    assert not list(tmp_path.iterdir()), "something was written into the current folder"


def test_an_empty_device_is_refused_not_taken_as_auto(shared_data, cli):
    code, _, err = cli(*HOG, "--device", "", "--data-dir", shared_data)
    assert_refused(code, err, None, "hog: option device takes a non-empty text (e.g. cpu or cuda); got ''.")


@pytest.mark.parametrize("command", [HOG, ["datasets", "info"], ["datasets", "verify"]])
def test_an_empty_dataset_name_is_unknown_not_the_current_folder(command, shared_data, cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    dataset = command.index("--dataset") + 1 if "--dataset" in command else None
    args = [*command[:dataset], "", *command[dataset + 1:]] if dataset else [*command, ""]
    code, _, err = cli(*args, "--data-dir", shared_data)
    assert_refused(code, err, None, "Unknown dataset ''.")


# ---------------------------------------------------------------- names the command ignored
def test_describe_refuses_an_unknown_dataset(shared_data, cli, tmp_path):
    code, _, err = cli("describe", "--method", "hog", "--dataset", "nosuch", "--out", tmp_path / "d.npy", image(shared_data))
    assert_refused(code, err, None, "Unknown dataset 'nosuch'")
    assert not (tmp_path / "d.npy").exists()


@pytest.mark.parametrize("args, message", [
    (["show", "--format", "csv", "--to", "{tmp}/board.csv"], "--to is for 'leaderboard publish'; 'leaderboard show'"),
    (["show", "--dataset", "corridor"], "--dataset is for 'leaderboard compare'; 'leaderboard show'"),
    (["show", "--k", "5"], "--k is for 'leaderboard compare'; 'leaderboard show'"),
    (["publish", "--to", "{tmp}/docs", "--k", "5"], "--k is for 'leaderboard compare'; 'leaderboard publish'"),
])
def test_leaderboard_options_of_another_action_are_refused(args, message, cli, tmp_path):
    code, _, err = cli("leaderboard", *[a.format(tmp=tmp_path) for a in args])
    assert_refused(code, err, None, message, "drop it.")
    assert not (tmp_path / "board.csv").exists() and not (tmp_path / "docs").exists()


@pytest.mark.parametrize("args, message", [
    (["--rerank", "seqslam"], "Stage 'seqslam' is a sequence stage: give it with --sequence seqslam, not --rerank."),
    (["--sequence", "aqe"], "Stage 'aqe' is a re-ranker: give it with --rerank aqe, not --sequence."),
])
def test_a_stage_given_as_the_other_kind_is_refused(args, message, shared_data, cli):
    code, _, err = cli(*HOG, *args, "--data-dir", shared_data)
    assert_refused(code, err, None, message)


# ---------------------------------------------------------------- files, folders and names
def test_a_dataset_path_that_is_a_file_is_named_as_one(cli, tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    code, _, err = cli("datasets", "info", plain)
    assert_refused(code, err, None, f"Dataset folder {plain} is a file, not a folder")


def test_a_candidates_folder_is_one_line(shared_data, cli, tmp_path):
    code, _, err = cli(*HOG, "--rerank", "aqe", "--candidates", tmp_path, "--data-dir", shared_data)
    assert_refused(code, err, None, f"Candidates file {tmp_path} is a folder")


def test_an_output_under_a_file_names_the_file_as_not_a_folder(shared_data, cli, tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    code, _, err = cli("describe", "--method", "hog", "--out", plain / "d.npy", image(shared_data))
    assert code == 2 and err.strip() == (f"error: argument --out: {plain} is a file, not a folder: check the path; "
                                         "see 'vprbench describe --help'"), err
    assert not list(cache_root().rglob("*.h5")), "the output path is checked before any work"


def test_an_output_that_is_a_folder_is_refused_before_any_work(shared_data, cli, tmp_path):
    folder = tmp_path / "d.npy"
    folder.mkdir()
    code, _, err = cli("describe", "--method", "hog", "--out", folder, image(shared_data))
    assert code == 2 and err.strip() == (f"error: argument --out: {folder} is a folder: give a file name in it; "
                                         "see 'vprbench describe --help'"), err
    assert not cache_root().exists(), "the output path is checked before any work"


def test_an_output_that_is_a_named_pipe_is_refused_before_any_work(shared_data, cli, tmp_path):
    """Was: described, then renamed over the pipe, so a reader waiting on it hung and the pipe was gone."""
    import os
    import stat

    pipe = tmp_path / "d.npy"
    os.mkfifo(pipe)
    code, _, err = cli("describe", "--method", "hog", "--out", pipe, image(shared_data))
    assert code == 2 and err.strip() == (f"error: argument --out: {pipe} is a named pipe, device or socket, not a "
                                         "file: give the path of a file to write; see 'vprbench describe --help'"), err
    assert stat.S_ISFIFO(os.lstat(pipe).st_mode) and not cache_root().exists(), "checked before any work"


@pytest.mark.parametrize("args, flag", [
    (["describe", "--method", "hog", "IMAGE", "--out", "OUT/d.npy"], "--out"),
    (["candidates", "export", "--method", "hog", "--dataset", "corridor", "--out", "OUT/c.h5"], "--out"),
    (["vocabulary", "fit", "--method", "dense-vlad", "--domain", "indoor", "--output", "OUT/v.pt"], "--output"),
    (["results", "export", "--method", "hog", "--dataset", "corridor", "--to", "OUT/r.tar.gz"], "--to"),
])
def test_an_output_in_a_missing_folder_is_refused_before_any_work(args, flag, shared_data, cli, tmp_path):
    """The folders were created (a typo wrote /nonexist/x.npy at the root), after all the work."""
    missing = tmp_path / "no" / "such"
    args = [str(image(shared_data)) if a == "IMAGE" else a.replace("OUT", str(missing)) for a in args]
    code, _, err = cli(*args, *(["--data-dir", shared_data] if args[0] != "results" else []))
    assert code == 2 and err.count("\n") == 1 and "usage:" not in err, err
    assert f"argument {flag}: the folder {missing} does not exist" in err
    assert not (tmp_path / "no").exists() and not list(cache_root().rglob("*.h5"))


@pytest.mark.parametrize("args, expected", [
    (["describe", "--method", "hog", "x.jpg", "--out", "d.txt"], "expected a .npy file, got d.txt"),
    (["candidates", "export", "--method", "hog", "--dataset", "corridor", "--out", "c.txt"],
     "expected a .h5 or .hdf5 file, got c.txt"),
])
def test_an_output_of_the_wrong_kind_is_refused_in_one_line(args, expected, cli):
    code, _, err = cli(*args)
    assert code == 2 and err.count("\n") == 1 and expected in err, err


def test_an_output_name_too_long_is_named_not_its_folder(shared_data, cli, tmp_path):
    out = tmp_path / ("d" * 300 + ".npy")
    code, _, err = cli("describe", "--method", "hog", "--out", out, image(shared_data))
    assert code == 2 and f"argument --out: Cannot use {out}: File name too long; use a shorter name; see" in err, err
    assert not list(cache_root().rglob("*.h5")), "the output path is checked before any work"


def test_describe_names_a_link_to_a_missing_image_as_such(cli, tmp_path):
    """'Image not found: a.jpg' of a link that `ls` shows there; an own folder's lister names it as the link it is."""
    link = tmp_path / "a.jpg"
    link.symlink_to(tmp_path / "moved" / "a.jpg")
    code, _, err = cli("describe", "--method", "hog", "--out", tmp_path / "d.npy", link)
    assert_refused(code, err, None, f"Image {link} is a symbolic link to a missing file (or a link loop): point it "
                                    "at the image or remove it.")


def test_describe_names_a_folder_given_as_an_image(shared_data, cli, tmp_path):
    """'Image not found: .' said of a folder that is there."""
    code, _, err = cli("describe", "--method", "hog", "--out", tmp_path / "d.npy", shared_data / "corridor" / "query")
    assert_refused(code, err, None, f"{shared_data / 'corridor' / 'query'} is a folder: give its image files")
    code, _, err = cli("describe", "--method", "hog", "--out", tmp_path / "d.npy", image(shared_data))
    assert code == 0 and "Wrote 1 descriptor of dimension" in err, err


# ---------------------------------------------------------------- a second audit (names, values, files)
@pytest.mark.parametrize("option", ["ef_search", "hnsw_m", "ef_construction"])
def test_an_index_option_past_faiss_int_is_one_line(option, shared_data, cli):
    """faiss's setter raised OverflowError (a traceback) after the descriptors were computed."""
    code, _, err = cli(*HOG, "--index", "hnsw", "--index-option", f"{option}=99999999999999999999",
                       "--data-dir", shared_data)
    assert_refused(code, err, None, f"--index hnsw option {option} takes at most 2147483647; got 99999999999999999999.")


def test_describe_refuses_an_empty_dataset_name(shared_data, cli, tmp_path):
    """'' was taken as no dataset: its settings silently not applied."""
    code, _, err = cli("describe", "--method", "hog", "--dataset", "", "--out", tmp_path / "d.npy", image(shared_data))
    assert_refused(code, err, None, "Unknown dataset ''.")
    assert not (tmp_path / "d.npy").exists()


def test_describe_names_a_fit_on_folder_without_images(shared_data, cli, tmp_path):
    """Was 'No images to describe in the database split', naming neither the folder nor the option."""
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = cli("describe", "--method", "hog", "--fit-on", empty, "--out", tmp_path / "d.npy", image(shared_data))
    assert_refused(code, err, None, f"--fit-on folder {empty} holds no images: give the folder of database images.")


def test_describe_says_the_fit_on_images_in_subfolders_it_does_not_read(shared_data, cli, tmp_path):
    """A --fit-on folder with images only in subfolders was 'holds no images'; with one image at the top the
    vocabulary was fitted on that one alone, silently (an own folder's database/ says both)."""
    import shutil

    fit = tmp_path / "fit"
    (fit / "sub").mkdir(parents=True)
    for name in ("0000000.jpg", "0000001.jpg"):
        shutil.copy(shared_data / "corridor" / "ref" / name, fit / "sub" / name)
    out = tmp_path / "d.npy"
    code, _, err = cli("describe", "--method", "dense-vlad", "--fit-on", fit, "--out", out, image(shared_data))
    assert_refused(code, err, None, f"--fit-on folder {fit} holds no images directly (only in its subfolders "
                                    "'sub': move them up into it)")
    shutil.copy(shared_data / "corridor" / "ref" / "0000002.jpg", fit / "top.jpg")
    with pytest.warns(UserWarning, match=r"--fit-on .*fit: the images in its subfolders \('sub'\) are not read"):
        code, _, err = cli("describe", "--method", "hog", "--fit-on", fit, "--out", out, image(shared_data))
    assert code == 1 and "fits nothing" in err, err  # hog fits nothing: warned first, then refused


def test_vocabulary_fit_refuses_an_empty_domain(shared_data, cli):
    """'' fell through to a map-specific fit of dataset None ('- None: load_dataset takes...')."""
    code, _, err = cli("vocabulary", "fit", "--domain", "", "--method", "anyloc", "--data-dir", shared_data)
    assert_refused(code, err, None, "Unknown vocabulary domain ''; known: indoor")


@pytest.mark.parametrize("args, shown", [
    (HOG + ["-o", "a\nb=1"], "does not take option(s) a\\nb. It accepts"),
    (HOG + ["--rerank", "aqe", "--rerank-option", "a\nb=1"], "does not take option a\\nb. It accepts"),
    (["vocabulary", "download", "a\nb"], "unrecognized arguments: a\\nb; see"),
])
def test_a_line_break_in_a_name_is_written_out_not_a_second_line(args, shown, shared_data, cli):
    """A name holding a line break split the message, the second line free to forge anything."""
    code, _, err = cli(*args, *(["--data-dir", shared_data] if args[0] == "evaluate" else []))
    assert code in (1, 2) and err.count("\n") == 1 and shown in err, err


def test_a_line_break_in_a_path_is_written_out(cli, tmp_path):
    odd = tmp_path / "a\nerror: forged"
    odd.write_bytes(b"junk")
    code, _, err = cli("vocabulary", "show", odd)
    assert_refused(code, err, None, f"Cannot read vocabulary file {tmp_path}/a\\nerror: forged: it is damaged")


def test_a_plan_keeps_one_problem_a_line(cli, tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[methods]]\nname = "x\\nerror: all fine"\n[[datasets]]\nname = "corridor"\n')
    code, _, err = cli("run", plan, "--cache-dir", tmp_path / "c", "--data-dir", tmp_path / "no-data")
    assert code == 1 and err.splitlines() == [f"error: Plan {plan} has 1 problem(s); nothing was run:",
                                              f"  {plan}:2: unknown method 'x\\nerror: all fine'. Run 'vprbench methods list'."], err


def test_a_line_break_in_a_plan_path_is_written_out(cli, tmp_path):
    """A ProblemList keeps its line breaks: the plan's path in its first line printed one of its own."""
    plan = tmp_path / "p\nerror: forged.toml"
    plan.write_text('[[methods]]\nname = "x"\n[[datasets]]\nname = "corridor"\n')
    code, _, err = cli("run", plan, "--cache-dir", tmp_path / "c", "--data-dir", tmp_path / "no-data")
    shown = str(plan).replace("\n", "\\n")
    assert code == 1 and err.splitlines() == [f"error: Plan {shown} has 1 problem(s); nothing was run:",
                                              f"  {shown}:2: unknown method 'x'. Run 'vprbench methods list'."], err


def test_an_unreadable_vocabulary_is_not_called_damaged(cli, tmp_path, monkeypatch):
    """Permission denied was reported as 'damaged or not a PyTorch file ... get it again'."""
    import torch

    path = tmp_path / "v.pt"
    torch.save(torch.zeros(2, 3), path)

    def refuse(source, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(source))
    monkeypatch.setattr(torch, "load", refuse)
    code, _, err = cli("vocabulary", "show", path)
    assert_refused(code, err, None, f"Cannot read vocabulary file {path}: Permission denied; check that it is a file "
                   "this user may read.")
    assert "damaged" not in err


def test_import_vpr_bench_names_a_file_as_one(shared_data, cli, tmp_path):
    """A file was said not to exist."""
    plain = tmp_path / "matches.txt"
    plain.write_text("x")
    code, _, err = cli("results", "import-vpr-bench", plain, "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, f"VPR-Bench folder {plain} is a file, not a folder: give the folder")


@pytest.mark.parametrize("kind", ["empty", "file"])
def test_publish_refuses_a_results_folder_that_is_no_repository(kind, cli, tmp_path):
    """A folder holding no records was accepted and added nothing, exit 0: a wrong path went unseen."""
    results = tmp_path / "not-a-repository"
    results.mkdir() if kind == "empty" else results.write_text("x")
    code, _, err = cli("leaderboard", "publish", "--to", tmp_path / "site", "--results", results)
    expected = "holds no records" if kind == "empty" else "is a file, not a folder"
    assert_refused(code, err, None, f"The results repository {results} {expected}: give the folder")
    assert not (tmp_path / "site").exists()


@pytest.mark.parametrize("args, env, expected", [
    (["--cache-dir", "   "], {}, "--cache-dir is '   ', which names no folder"),
    ([], {"VPRBENCH_CACHE": " "}, "$VPRBENCH_CACHE is ' ', which names no folder"),
])
def test_a_blank_folder_is_refused_not_made(args, env, expected, cli, tmp_path, monkeypatch):
    """A folder named '   ' was made in the current one, and the run stored there."""
    monkeypatch.chdir(tmp_path)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    code, _, err = cli("leaderboard", *args)
    assert_refused(code, err, None, expected)
    assert not list(tmp_path.iterdir())


def test_a_plan_with_an_infinite_resize_is_one_line(cli, tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[methods]]\nname = "hog"\noptions = {resize = [inf, 32]}\n[[datasets]]\nname = "corridor"\n')
    code, _, err = cli("run", plan, "--cache-dir", tmp_path / "c", "--data-dir", tmp_path / "no-data")
    assert code == 1 and "Traceback" not in err and "plan.toml:3: Method 'hog'" in err, err


@pytest.mark.parametrize("device, message", [
    # mps: RuntimeError 'PyTorch is not linked with support for mps devices' (a traceback) at the first image
    ("mps", "hog: device 'mps' was asked for but this machine's PyTorch cannot use it; use --device cpu."),
    ("meta", "hog: device 'meta' holds no data, so it computes nothing; use --device cpu or cuda."),
])
def test_a_device_this_machine_lacks_is_one_line(device, message, shared_data, cli):
    code, _, err = cli(*HOG, "--device", device, "--data-dir", shared_data)
    assert_refused(code, err, None, message)


def test_datasets_info_refuses_protocol_with_protocols(cli):
    """--protocol was ignored beside --protocols (exit 0, every protocol listed)."""
    code, out, err = cli("datasets", "info", "corridor", "--protocols", "--protocol", "nosuch")
    assert_refused(code, err, None, "--protocols lists every protocol and --protocol shows the dataset under one")
    assert out == ""


@pytest.mark.parametrize("resize, said", [("[-1, 32]", "must be positive, got -1x32"), ("{a = 1}", "takes HEIGHT WIDTH")])
def test_a_plan_with_a_bad_resize_is_a_plan_problem(resize, said, cli, shared_data, tmp_path):
    """Was: the plan was accepted and each cell failed when it ran (docs/sweeps.md: every plan problem is
    listed before anything runs)."""
    plan = tmp_path / "plan.toml"
    plan.write_text(f'[[methods]]\nname = "hog"\noptions = {{resize = {resize}}}\n[[datasets]]\nname = "corridor"\n')
    code, out, err = cli("run", plan, "--cache-dir", tmp_path / "c", "--data-dir", shared_data)
    assert code == 1 and "has 1 problem(s); nothing was run" in err and said in err, err
    assert not (tmp_path / "c" / "results").exists()
