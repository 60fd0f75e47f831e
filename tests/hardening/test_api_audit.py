"""The Python API as a researcher calls it from a notebook, with the wrong arguments: a wrong type,
an unknown name, an out-of-range number, a method object renamed or built with other options, a
results folder that is a file or the wrong folder. Each is one VPRBenchError naming the argument
and what to pass, raised before any work; never a bare TypeError/AttributeError from deep inside,
never a silently wrong result, never anything written."""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pytest

from vprbench import VPRBenchError, create_method
from vprbench.datasets import load_dataset
from vprbench.evaluation import evaluate, find_result, per_query, read_results, save_result
from vprbench.leaderboard import build_board, publish
from vprbench.leaderboard.compare import compare
from vprbench.methods.hog import HOG
from vprbench.reference import paper_results
from vprbench.spec import RunSettings, resolve_spec, spec_for


@pytest.fixture(scope="module")
def stored(shared_data, tmp_path_factory):
    """A cache holding one real run: hog [resize=16x16] on Corridor (its data read in place)."""
    cache = tmp_path_factory.mktemp("api-audit") / "cache"
    spec = resolve_spec("hog", "corridor", options={"resize": [16, 16]}, ks=(1, 5))
    save_result(evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=cache)), cache)
    return cache, spec


def refused(call, *expected: str) -> str:
    with pytest.raises(VPRBenchError) as error:
        call()
    message = str(error.value)
    assert "\n" not in message and all(part in message for part in expected), message
    return message


# ---------------------------------------------------------------- a method object that is not the spec's
def test_a_method_built_with_other_options_than_the_spec_is_refused(tmp_path):
    """It ran, and its results were recorded under the spec's options (hog 64x64 labelled 32x32)."""
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=(1,))
    method = create_method("hog", resize=[64, 64])
    refused(lambda: evaluate(spec, RunSettings(cache_dir=tmp_path / "cache", data_dir=tmp_path / "data"), method=method),
            "The method given is 'hog' with options {'resize': [64, 64]}", "spec is 'hog' with options "
            "{'resize': [32, 32]}", "spec_for(method, dataset)")
    assert not (tmp_path / "cache").exists()


def test_a_renamed_method_is_refused(tmp_path):
    """A HOG whose name was set to 'sad' made a 'sad' spec and was recorded, and ranked, as sad."""
    method = create_method("hog", resize=[32, 32])
    method.name = "sad"
    expected = ("The method object was created as 'hog' with options {'resize': [32, 32]}, but now says 'sad'",
                "create_method(name, ...)")
    refused(lambda: spec_for(method, "corridor"), *expected)
    spec = resolve_spec("sad", "corridor", options={"resize": [32, 32]}, ks=(1,))
    refused(lambda: evaluate(spec, RunSettings(cache_dir=tmp_path / "cache"), method=method), *expected)
    assert not (tmp_path / "cache").exists()
    built_by_hand = HOG()  # not stamped by create_method: its class must be its name's
    built_by_hand.name = "sad"
    refused(lambda: spec_for(built_by_hand, "corridor"), "The method object is a HOG, but its name says 'sad', which "
            "is a SAD", "create_method('sad', ...)")


def test_a_preset_renamed_to_another_of_its_class_or_given_other_options_is_refused(tmp_path):
    """An AnyLoc-VLAD object renamed 'anyloc-gem-dinov2' (the same class) made a GeM spec, and its
    VLAD descriptors would have been recorded and ranked as GeM's; options edited after creation
    likewise labelled the run with options it did not run with."""
    method = create_method("anyloc-vlad-dinov2", weights="random")
    method.name = "anyloc-gem-dinov2"
    expected = ("created as 'anyloc-vlad-dinov2' with options {'weights': 'random'}, but now says "
                "'anyloc-gem-dinov2'", "create_method(name, ...)")
    refused(lambda: spec_for(method, "corridor"), *expected)
    hog = create_method("hog", resize=[32, 32])
    hog.options = {"resize": [64, 64]}
    refused(lambda: spec_for(hog, "corridor"), "created as 'hog' with options {'resize': [32, 32]}, but now says "
            "'hog' with options {'resize': [64, 64]}")
    assert spec_for(create_method("hog", resize=[32, 32]), "corridor").given == {"resize": [32, 32]}


def test_the_batch_size_of_the_settings_applies_to_a_method_given(tmp_path):
    """RunSettings(batch_size=-1) was silently ignored when the method was given already built."""
    method = create_method("hog", resize=[32, 32])
    spec = spec_for(method, "corridor", ks=(1,))
    refused(lambda: evaluate(spec, RunSettings(cache_dir=tmp_path / "cache", batch_size=-1), method=method),
            "hog: option batch_size takes a whole number >= 1 (images per batch); got -1.")
    assert not (tmp_path / "cache").exists()


# ---------------------------------------------------------------- wrong types: one line naming the argument
SPEC = resolve_spec("hog", "corridor", ks=(1,))
WRONG_TYPES = [
    # each was an AttributeError or TypeError from deep inside
    (lambda: evaluate(None), "evaluate(spec) takes a RunSpec", "resolve_spec"),
    (lambda: evaluate(SPEC.to_json()), "evaluate(spec) takes a RunSpec", "got dict {"),
    (lambda: evaluate(SPEC, {"cache_dir": "x"}), "evaluate's settings take a vprbench.spec.RunSettings"),
    (lambda: evaluate(SPEC, dataset="corridor"), "dataset takes a vprbench Dataset", "load_dataset(name)"),
    (lambda: evaluate(SPEC, method="hog"), "method takes a vprbench.Method object", "create_method"),
    (lambda: spec_for("hog", "corridor"), "method takes a vprbench.Method object", "got str 'hog'."),
    (lambda: resolve_spec(None, "corridor"), "resolve_spec's method takes a method's name, e.g. 'hog'"),
    (lambda: resolve_spec(["hog"], "corridor"), "resolve_spec's method takes a method's name"),
    (lambda: resolve_spec(create_method("hog"), "corridor"), "for the method object 'hog'", "use vprbench.spec.spec_for"),
    (lambda: resolve_spec("hog", "corridor", options="resize=64"), "options takes a dict of option name -> value"),
    (lambda: resolve_spec("hog", "corridor", options={5: 1}), "Option names are text", "got 5."),
    (lambda: resolve_spec("hog", "corridor", stages=5), "stages takes a list of stages"),
    # run settings were dropped: evaluate(spec) then ran on the default device
    (lambda: resolve_spec("hog", "corridor", options={"device": "cuda"}), "device is a run setting, not part of a "
     "run's spec: pass it to evaluate as vprbench.spec.RunSettings(device='cuda')"),
    (lambda: resolve_spec("hog", "corridor", ks=5.5), "--k (ks) takes whole numbers >= 1", "got 5.5."),
    (lambda: resolve_spec("hog", "corridor", ks=math.nan), "--k (ks) takes whole numbers >= 1", "got nan."),
    (lambda: resolve_spec("hog", "corridor", ks={1: 5}), "--k (ks) takes whole numbers >= 1 in a list"),
    (lambda: resolve_spec("hog", "corridor", protocol=5), "Dataset 'corridor' has no protocol 5."),
    (lambda: resolve_spec("hog", "corridor", protocol=["vpr-bench"]), "has no protocol ['vpr-bench']."),
    (lambda: resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {5: 1}}), "--index hnsw does not take 5"),
    (lambda: create_method(None), "Unknown method None."),
    (lambda: load_dataset(None), "load_dataset takes a dataset's name", "or the path of a folder"),
    (lambda: load_dataset("corridor", 5), "data_dir takes a folder path (a str or pathlib.Path)", "got int 5."),
    (lambda: RunSettings(cache_dir=5), "cache_dir takes a folder path", "got int 5."),
    (lambda: RunSettings(cache_dir=""), "cache_dir takes a folder path", "got str ''."),  # was the current folder
    (lambda: RunSettings(candidates=5), "candidates takes the path of an exported candidates file"),
    (lambda: find_result("hog"), "find_result(spec) takes a RunSpec"),
    (lambda: find_result(SPEC, 5), "cache_dir takes a folder path"),
    (lambda: read_results(5), "cache_dir takes a folder path"),
    (lambda: save_result("run.json"), "save_result takes a result record"),
    (lambda: per_query("run.json"), "per_query takes a result record"),
    (lambda: build_board("cache"), "built from a list of result records", "read_results(cache_dir)"),
    (lambda: build_board([5]), "built from a list of result records"),
    (lambda: compare([], "hog", "sad", "corridor"), "compare takes a Board", "build_board(read_results(cache_dir))"),
    (lambda: publish(None), "publish takes the docs folder"),
    (lambda: paper_results("nope"), "No reported numbers for paper 'nope'. Available: anyloc."),
    (lambda: paper_results("../../x"), "No reported numbers for paper '../../x'."),
    (lambda: paper_results(table="IX"), "The anyloc paper has no table 'IX'; its tables: II"),  # was an empty frame
]


@pytest.mark.parametrize("case", WRONG_TYPES, ids=[case[1][:40] for case in WRONG_TYPES])
def test_a_wrong_argument_is_one_line_naming_it(case, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    call, *expected = case
    refused(call, *expected)
    assert list(tmp_path.iterdir()) == []


def test_a_text_flag_is_not_read_as_true(tmp_path):
    """fetch='no' is truthy: load_dataset downloaded; strict='no' made counts strict."""
    refused(lambda: load_dataset("corridor", tmp_path / "data", fetch="no"),
            "load_dataset: option fetch takes True, False or None (only into the default data root); got 'no'.")
    refused(lambda: load_dataset("corridor", tmp_path / "data", strict="no"), "option strict takes True or False")
    refused(lambda: RunSettings(download="yes"), "run: option download takes True, False or None")
    refused(lambda: RunSettings(strict="no"), "run: option strict takes True or False; got 'no'.")
    assert list(tmp_path.iterdir()) == []


def test_arguments_of_the_forms_a_researcher_writes_mean_what_they_say():
    assert resolve_spec("hog", "corridor", ks="15").ks == (15,)  # fifteen, not 1 and 5
    assert resolve_spec("hog", "corridor", ks=5.0).ks == (5,)  # was TypeError: 'float' object is not iterable
    assert resolve_spec("hog", "corridor", ks={5, 1}).ks == (1, 5)
    # one stage by name was read letter by letter: "Unknown stage 'a'"
    assert [s.name for s in resolve_spec("hog", "corridor", stages="aqe").stages] == ["aqe"]
    assert [s.name for s in resolve_spec("hog", "corridor", stages={"name": "aqe", "k": 50}).stages] == ["aqe"]
    assert resolve_spec("hog", Path("corridor")).dataset.name == "corridor"


# ---------------------------------------------------------------- the results store, and what reads it
def test_the_results_folder_given_as_the_cache_is_named(stored):
    """Passing <cache>/results found nothing, silently (and a save would nest a second store)."""
    cache, spec = stored
    expected = (f"{cache / 'results'} is a results folder, not a cache folder: pass the cache folder that holds it, "
                f"{cache}.")
    refused(lambda: read_results(cache / "results"), expected)
    refused(lambda: find_result(spec, cache / "results"), expected)
    assert sorted(p.name for p in (cache / "results").iterdir()) == sorted(["LAYOUT", "methods", spec.dataset.protocol_hash])


def test_a_cache_folder_that_is_a_file_is_named(stored, tmp_path):
    """It read as an empty store: no result, no records, no word."""
    _, spec = stored
    (tmp_path / "cache").write_text("not a folder")
    for call in (lambda: read_results(tmp_path / "cache"), lambda: find_result(spec, tmp_path / "cache")):
        refused(call, f"The cache folder {tmp_path / 'cache'} (cache_dir) is a file, not a folder")


def test_the_stored_run_still_reads(stored):
    cache, spec = stored
    found = find_result(spec, cache)
    assert found is not None and set(found["recall"]) == {"1", "5"}
    assert per_query(found)["first_positive_rank"].shape == (111,)
    assert [r["run_id"] for r in read_results(str(cache))] == [found["run_id"]]


def test_per_query_of_a_record_read_by_hand_says_why(stored):
    """A record loaded with json.load has no _source: the warning named an AttributeError."""
    cache, spec = stored
    record = json.loads(open(find_result(spec, cache)["_source"]).read())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert per_query(record) is None and per_query({"per_query": 5}) is None
    shown = [str(w.message) for w in caught]
    assert "was not read from the store: read it with read_results or find_result" in shown[0]
    assert "per-query section of run None is int, not a table" in shown[1]


@pytest.mark.parametrize("k, seed", [(0, 0), (-1, 0), (1.5, 0), (math.nan, 0), (True, 0), ("5", 0), (1, -1), (1, "x")])
def test_compare_takes_a_whole_k_and_seed(stored, k, seed):
    """k=0, -1, 1.5, NaN and True compared 'R@k' and returned numbers; '5' and bad seeds were tracebacks."""
    cache, _ = stored
    board = build_board(read_results(cache))
    name = board.rows[0].name
    refused(lambda: compare(board, name, name, "corridor", k=5), "name the same run")  # k=5 passed, to the row check
    wrong = (f"--k takes a whole number >= 1 (the K of Recall@K compared); got {k!r}" if seed == 0 else
             f"--seed takes a whole number >= 0 (the bootstrap's); got {seed!r}")
    refused(lambda: compare(board, name, name, "corridor", k=k, seed=seed), f"{wrong}.")


def test_publish_refuses_a_bad_seed_before_writing(stored, tmp_path):
    cache, _ = stored
    # only the seed is named: publish takes no K (was: "got --k 1 --seed -1")
    refused(lambda: publish(tmp_path / "docs", cache, seed=-1), "--seed takes a whole number >= 0 (the bootstrap's); got -1.")
    refused(lambda: publish(tmp_path / "docs", cache, seed=1.5), "--seed takes a whole number >= 0 (the bootstrap's); got 1.5.")
    assert not (tmp_path / "docs").exists()


def test_a_renamed_dataset_is_refused(shared_data, tmp_path):
    """A Corridor whose name was set to 'other' was recorded as dataset 'other' under Corridor's protocol."""
    dataset = load_dataset("corridor", shared_data)
    dataset.name = "other"
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=(1,), data_dir=shared_data)
    refused(lambda: evaluate(spec, RunSettings(cache_dir=tmp_path / "cache"), dataset=dataset),
            "The dataset given is named 'other'", "'corridor'")
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("name", [["hog"], 5, None])
def test_a_method_name_that_is_no_text_is_unknown(name):
    refused(lambda: create_method(name), f"Unknown method {name!r}.")


def test_a_label_is_one_line_whatever_its_options_hold(shared_data):
    """A line break in an option's value printed a line of its own wherever the label is shown
    (a forged 'ok' line in `results verify`)."""
    spec = resolve_spec("dense-vlad", "corridor", options={"vocabulary": "a\nrun x: ok"}, data_dir=shared_data)
    assert spec.label() == "dense-vlad [vocabulary=a\\nrun x: ok]"
