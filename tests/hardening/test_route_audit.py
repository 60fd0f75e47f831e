"""One run, one specification, whichever route starts it: an option given twice is refused rather
than one of its values dropped, and `describe` of a dataset's own images fills the stores `evaluate`
reads (and the other way round)."""
from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.mark.parametrize("given, expected", [
    (("-o", "layer=3", "--layer", "4"), "--layer 4 and -o layer=3 disagree; give layer once."),
    (("--resize", "32", "32", "-o", "resize=32x48"), "--resize 32 32 and -o resize=32x48 disagree; give resize once."),
])
def test_a_method_option_given_twice_with_two_values_is_refused(given, expected, cli, shared_data, tmp_path):
    """`-o layer=3 --layer 4` ran layer 3, silently: the flag the user also wrote was dropped."""
    code, out, err = cli("evaluate", "--method", "anyloc", "--backbone", "dinov2_vits14", "--weights", "random",
                         *given, "--dataset", "corridor", "--data-dir", shared_data, "--cache-dir", tmp_path)
    assert (code, err.strip()) == (1, f"error: {expected}")
    assert not (tmp_path / "results").exists()


def test_describe_then_evaluate_computes_nothing_again(corridor_copy, cli, capsys):
    """describe kept its stores under 'describe-corridor' and by file name, evaluate under 'corridor' by
    the name in the dataset: the same descriptors of the same images were computed twice."""
    data, cache = corridor_copy.parent, corridor_copy.parent.parent / "cache"
    queries = sorted((corridor_copy / "query").glob("*.jpg"))
    common = ("--method", "hog", "--resize", "32", "32", "--data-dir", data, "--cache-dir", cache, "--quiet")
    out = cache.parent / "d.npy"
    assert cli("describe", *common, "--dataset", "corridor", "--fit-on", corridor_copy / "ref", *queries, "--out", out)[0] == 0
    code, printed, _ = cli("evaluate", *common, "--dataset", "corridor", "--k", "1", "--json")
    record = json.loads(printed)
    assert code == 0 and record["descriptors_computed"] == {"database": 0, "queries": 0}
    assert record["counts"]["queries"] == len(queries) == np.load(out).shape[0] == 111

    # images outside the dataset are not its own: they keep describe's label and file names
    elsewhere = cache.parent / "mine.jpg"
    elsewhere.write_bytes(queries[0].read_bytes())
    assert cli("describe", *common, "--dataset", "corridor", elsewhere, "--out", out)[0] == 0
    assert sorted(p.name.rsplit("-", 1)[0] for p in (cache / "stores").glob("*/*")) == [
        "corridor-database", "corridor-queries", "describe-corridor-queries"]


def test_a_plan_names_a_methods_options_as_a_single_run_does(shared_data, cli, tmp_path):
    """A sweep listed device and batch_size among dense-vlad's options (and offered them for 'resize'):
    they are run settings, which a single run leaves out of the list."""
    common = ("--resize", "64", "64", "--dataset", "corridor", "--data-dir", shared_data, "--cache-dir", tmp_path)
    one = cli("evaluate", "--method", "dense-vlad", *common)[2]
    several = cli("evaluate", "--method", "dense-vlad", "hog", *common)[2]
    accepts = "It accepts: clusters, bin_sizes, step, max_side, sample, seed, vocabulary."
    assert accepts in one and "Did you mean: bin_sizes?" in one
    assert f"({accepts})" in several and "Did you mean: bin_sizes?" in several


def test_describe_with_anylocs_dataset_option_naming_its_dataset_shares_evaluates_store(shared_data, cli, tmp_path):
    """`-o dataset=corridor` on Corridor is the run without it, and evaluate keys its store so; describe keyed
    its store by the method's own settings, which kept it: the same descriptors were computed again."""
    cache, corridor = tmp_path / "cache", shared_data / "corridor"
    common = ("--method", "anyloc", "--backbone", "dinov2_vits14", "--weights", "random", "--resize", "28", "28",
              "--aggregation", "gem", "--data-dir", shared_data, "--cache-dir", cache, "--quiet")
    assert cli("evaluate", *common, "--dataset", "corridor", "--k", "1")[0] == 0
    stores = sorted(cache.glob("stores/*/*"))
    code, _, err = cli("describe", *common, "-o", "dataset=corridor", "--dataset", "corridor",
                       *sorted((corridor / "query").glob("*.jpg")), "--out", tmp_path / "d.npy")
    assert code == 0, err
    assert sorted(cache.glob("stores/*/*")) == stores, "describe made a store of its own"
