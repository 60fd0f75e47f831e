"""One run, one specification: a flag given twice with different values is refused on every command
(argparse alone keeps the last value, and the run is not the one asked for)."""
from __future__ import annotations

import pytest

from vprbench.cli.main import build_parser

HOG = ["evaluate", "--method", "hog", "--dataset", "corridor"]


def assert_usage_error(code, err, message):
    assert code == 2, err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert err.startswith(f"error: {message}") and err.rstrip().endswith(" --help'"), err


@pytest.mark.parametrize("args, message", [
    (HOG + ["--k", "1", "5", "--k", "10"], "--k given twice (1 5, then 10): give it once, e.g. --k 1 5 10"),
    (HOG + ["--k", "1", "5", "--k", "5", "10"], "--k given twice (1 5, then 5 10): give it once, e.g. --k 1 5 10"),
    (["evaluate", "--method", "hog", "--method", "sad", "--dataset", "corridor"],
     "--method given twice (hog, then sad): give it once, e.g. --method hog sad"),
    (HOG + ["--layer", "3", "--layer", "4"], "--layer given twice (3, then 4): give it once, with the value you mean"),
    (HOG + ["--resize", "64", "64", "--resize", "32", "32"],
     "--resize given twice (64 64, then 32 32): give it once, with the value you mean"),
    (HOG + ["--device", "cpu", "--device", "cuda"], "--device given twice (cpu, then cuda)"),
    (HOG + ["-o", "cell=8", "-o", "cell=4"],
     "-o cell given twice (cell=8, then cell=4): give each key once, with the value you mean"),
    (HOG + ["--option", "cell=8", "-o", "cell=4"], "-o cell given twice (cell=8, then cell=4)"),
    (HOG + ["--index", "hnsw", "--index-option", "ef_search=8", "--index-option", "ef_search=16"],
     "--index-option ef_search given twice (ef_search=8, then ef_search=16)"),
    (HOG + ["--rerank", "aqe", "--rerank-option", "alpha=1", "--rerank-option", "alpha=2"],
     "--rerank-option alpha given twice (alpha=1, then alpha=2)"),
    # the spellings key_values reads as one key
    (HOG + ["--sequence", "seqslam", "--sequence-option", "max-speed=2", "--sequence-option", "max_speed=3"],
     "--sequence-option max_speed given twice (max-speed=2, then max_speed=3)"),
    # nested subcommands are parsers of the same class
    (["candidates", "export", "--method", "hog", "--dataset", "corridor", "--k", "10", "--k", "20",
      "--out", "c.h5"], "--k given twice (10, then 20)"),
    (["results", "export", "--run", "a", "--run", "b", "--to", "runs.tar.gz"],
     "--run given twice (a, then b): give it once, e.g. --run a b"),
    (["vocabulary", "fit", "--domain", "urban", "--domain", "indoor", "--method", "anyloc"],
     "--domain given twice (urban, then indoor)"),
    (["leaderboard", "--format", "table", "--format", "markdown"], "--format given twice (table, then markdown)"),
])
def test_a_flag_given_twice_is_refused(args, message, cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = cli(*args)
    assert_usage_error(code, err, message)
    assert out == ""


@pytest.mark.parametrize("args, dest, value", [
    (HOG + ["-o", "cell=8", "-o", "bins=9", "--option", "cell=8"], "option", ["cell=8", "bins=9", "cell=8"]),
    (HOG + ["--index-option", "nprobe=8", "--index-option", "nlist=64"], "index_option", ["nprobe=8", "nlist=64"]),
    (HOG + ["--k", "1", "5", "--k", "1", "5"], "k", ["1", "5"]),
    (HOG + ["--layer", "3", "--layer", "3", "--quiet", "--quiet"], "layer", 3),
])
def test_repeats_that_change_nothing_pass(args, dest, value):
    """Different keys are what the repeatable flags are for; the same value twice runs what was asked."""
    assert getattr(build_parser().parse_args(args), dest) == value


def test_each_parse_starts_afresh():
    parser = build_parser()
    assert parser.parse_args(HOG + ["--k", "1"]).k == ["1"]
    assert parser.parse_args(HOG + ["--k", "10"]).k == ["10"]  # not 'given twice' across two command lines
