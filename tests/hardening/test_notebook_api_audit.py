"""The public Python API called from a notebook with what a researcher may hand it: a Path where
text is meant, a wrong type, a folder argument that is no folder, a registration that cannot be
used, a hand-made Dataset. Each is accepted as the docs say or refused on entry in one line naming
the argument; never an AttributeError from deep inside, never a silent acceptance, nothing written."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hostile_files import tiny_images

from vprbench import VPRBenchError, available_methods, create_method, register_method
from vprbench.datasets import Dataset, GroundTruth, load_dataset
from vprbench.distributed import Ranks
from vprbench.evaluation import evaluate, find_result, recall_at_k, successes, top1_precision_recall
from vprbench.evaluation.metrics import correct_at
from vprbench.hashing import canonical_hash
from vprbench.leaderboard import build_board, publish
from vprbench.leaderboard.compare import compare
from vprbench.methods.hog import HOG
from vprbench.spec import RunSettings, resolve_spec
from vprbench.weights import read_torch_file, weights_provenance


def hand_made(folder: Path, **changes) -> Dataset:
    """Four database and two query images with frame ground truth, built in Python."""
    tiny_images(folder / "db", ["a.png", "b.png", "c.png", "d.png"])
    tiny_images(folder / "q", ["e.png", "f.png"])
    parts = dict(name="mine", database=sorted((folder / "db").iterdir()), queries=sorted((folder / "q").iterdir()),
                 ground_truth=GroundTruth("frames", 1, np.arange(4)[:, None], np.arange(2)[:, None]), root=folder)
    return Dataset(**{**parts, **changes})


def test_a_path_option_is_its_text():
    """weights=Path(...) is the path it names, as on the command line (was: 'not plain data')."""
    options = {"backbone": "dinov2_vits14", "aggregation": "gem"}
    as_path = resolve_spec("anyloc", "corridor", options={**options, "weights": Path("random")})
    assert as_path.key == resolve_spec("anyloc", "corridor", options={**options, "weights": "random"}).key


@pytest.mark.parametrize("dataset", [None, ["corridor"], 5, HOG()])
def test_resolve_spec_dataset_of_another_type(dataset):
    """(was: 'Unknown dataset 'None'', the text of whatever was passed, with a 'Did you mean' for a list)"""
    with pytest.raises(VPRBenchError, match=r"^resolve_spec's dataset takes a dataset's name .* or a Dataset; got "):
        resolve_spec("hog", dataset)


def test_folder_arguments_are_folders(tmp_path):
    """A cache or data folder that is no path is refused where it is given (was: taken silently)."""
    calls = [lambda: load_dataset("corridor", cache_dir=3), lambda: create_method("hog", cache_dir=5),
             lambda: create_method("hog", data_dir=[str(tmp_path)]), lambda: resolve_spec("hog", "corridor", data_dir=5),
             lambda: resolve_spec("hog", "corridor", cache_dir=5),
             lambda: publish(tmp_path / "docs", tmp_path / "cache", data_dir=5)]
    for call in calls:
        with pytest.raises(VPRBenchError, match=r"^(cache|data)_dir takes a folder path"):
            call()
    with pytest.raises(VPRBenchError, match="^publish's results take the folder"):
        publish(tmp_path / "docs", tmp_path / "cache", results=5)
    assert not (tmp_path / "docs").exists() and not (tmp_path / "cache").exists()


def test_evaluate_progress_and_ranks_checked_on_entry(tmp_path):
    """(was: an AttributeError, the progress one mid-run)"""
    spec, settings = resolve_spec("hog", "corridor"), RunSettings(cache_dir=tmp_path / "cache", data_dir=tmp_path)
    with pytest.raises(VPRBenchError, match="^evaluate's progress takes a rich Progress"):
        evaluate(spec, settings, progress=5)
    with pytest.raises(VPRBenchError, match="^evaluate's ranks take a vprbench.distributed.Ranks"):
        evaluate(spec, settings, ranks="0")
    assert isinstance(Ranks(), Ranks) and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("factory, parts, message", [
    (None, {}, "register it with a class or function"), (5, {}, "register it with a class or function"),
    ("my_package", {}, "register it with a class or function"), (HOG, {"defaults": [1]}, "defaults takes a dict"),
    (HOG, {"description": 5}, "its description is text")])
def test_register_method_refuses_what_cannot_be_used(factory, parts, message):
    """(was: registered, holding the name, and found out only by create_method; a list of defaults a TypeError)"""
    with pytest.raises(ValueError, match=message):
        register_method("audit-unusable", factory, **parts)
    assert "audit-unusable" not in available_methods()


@pytest.mark.parametrize("radius", [-5, float("nan"), float("inf"), "25", True])
def test_ground_truth_radius_is_a_number(radius):
    """(was: NaN made no pair positive, silently; -5 failed inside scikit-learn)"""
    with pytest.raises(ValueError, match="ground-truth radius must be a finite number >= 0"):
        GroundTruth("metres", radius, np.zeros((2, 2)), np.zeros((1, 2)))


def test_hand_made_dataset_takes_text_paths(tmp_path):
    """Image paths and root given as text work as Paths do (was: an AttributeError in its identity)."""
    as_paths = hand_made(tmp_path)
    as_text = hand_made(tmp_path, database=[str(p) for p in as_paths.database],
                        queries=[str(p) for p in as_paths.queries], root=str(tmp_path))
    assert as_text.fingerprint(tmp_path / "cache") == as_paths.fingerprint(tmp_path / "cache")
    for changes, fragment in (({"ground_truth": None}, "ground_truth takes a vprbench GroundTruth"),
                              ({"database": "abc"}, "database takes a list of image paths"),
                              ({"queries": [None]}, "queries takes a list of image paths")):
        with pytest.raises(VPRBenchError, match=fragment):
            hand_made(tmp_path, **changes)


def test_spec_of_a_hand_made_dataset_needs_it_again(tmp_path):
    """(was: 'Unknown dataset 'mine'', or for a benchmark's name its files loaded and a protocol mismatch)"""
    spec = resolve_spec("hog", hand_made(tmp_path / "data"), ks=[1])
    with pytest.raises(VPRBenchError, match=r"was given as a Dataset made in Python .*evaluate\(spec, settings, dataset="):
        evaluate(spec, RunSettings(cache_dir=tmp_path / "cache", data_dir=tmp_path / "data"))
    assert not (tmp_path / "cache" / "results").exists()


@pytest.mark.parametrize("identity", ["junk", "weights.pth", "sha256:abc", "hf:", ""])
def test_weights_provenance_refuses_what_is_no_identity(identity):
    """(was: any text recorded as the authors' official weights)"""
    with pytest.raises(VPRBenchError, match="^weights_provenance takes a weights identity"):
        weights_provenance(identity)
    assert weights_provenance("open_clip:ViT-B-32/laion2b")["source"] == "official"  # a source's own naming


def test_compare_names_the_argument_of_another_type(tmp_path):
    board = build_board([])
    with pytest.raises(VPRBenchError, match="^compare's dataset takes a column's name"):
        compare(board, "a", "b", hand_made(tmp_path))
    with pytest.raises(VPRBenchError, match="^compare's a takes a row's name"):
        compare(board, HOG(), "b", "corridor")


def test_find_result_fingerprints_of_another_type(tmp_path):
    """A Dataset (or a number) for its fingerprint (was: None, as if nothing were stored)."""
    spec = resolve_spec("hog", "corridor")
    with pytest.raises(VPRBenchError, match=r"^find_result's dataset_fingerprint takes Dataset.fingerprint\(\)"):
        find_result(spec, tmp_path, dataset_fingerprint=hand_made(tmp_path))
    with pytest.raises(VPRBenchError, match="^find_result's method_fingerprint takes"):
        find_result(spec, tmp_path, method_fingerprint="abc")


def test_metrics_refuse_what_they_cannot_score():
    """(was: R@0 = 0 %, K '5' a numpy UFuncTypeError, None a TypeError or all-zero PR metrics, a query dropped by zip)"""
    ranks = np.array([1, 0, 3])
    assert recall_at_k(ranks, [1, 5]) == {1: pytest.approx(100 / 3), 5: pytest.approx(200 / 3)}
    assert recall_at_k(np.array([], dtype=np.int64), [1]) == {1: 0.0}
    for call in (lambda: recall_at_k(ranks, [0]), lambda: successes(ranks, "5"), lambda: successes(ranks, True),
                 lambda: recall_at_k(None, [1]), lambda: successes(ranks.astype(float) + 0.5, 1),
                 lambda: correct_at(np.array([[0, 1], [1, 0]]), [np.array([0])]),
                 lambda: top1_precision_recall(None, None), lambda: top1_precision_recall([0.9, 0.1, 0.3], [True, False])):
        with pytest.raises(VPRBenchError, match="^(Recall@K takes|correct_at takes|top1_precision_recall takes)"):
            call()


def test_create_method_given_a_method_object():
    """(was: 'Unknown method <vprbench.methods.hog.HOG object at 0x...>')"""
    with pytest.raises(VPRBenchError, match="^create_method takes a method's name, e.g. 'hog'; got the method object 'hog'"):
        create_method(create_method("hog"))


def test_read_torch_file_mmap_is_a_flag(tmp_path):
    """(was: mmap='no' taken as True)"""
    import torch

    torch.save({"a": torch.zeros(2)}, tmp_path / "w.pth")
    assert set(read_torch_file(tmp_path / "w.pth", mmap=True)) == {"a"}
    with pytest.raises(VPRBenchError, match="^read_torch_file: option mmap takes True or False; got 'no'"):
        read_torch_file(tmp_path / "w.pth", mmap="no")


def test_positive_lists_are_a_list():
    """(was: text read character by character, 'invalid literal for int()')"""
    with pytest.raises(ValueError, match="unit 'positives' needs positive_lists, a list of index lists; got 'abc'"):
        GroundTruth("positives", positive_lists="abc")


def test_run_settings_with_options_of_another_type():
    """(was: an AttributeError, 'str' object has no attribute 'items')"""
    assert RunSettings().with_options({"batch_size": 4}).batch_size == 4
    with pytest.raises(VPRBenchError, match="^run settings come from a dict of option name -> value"):
        RunSettings().with_options("batch_size=4")


@pytest.mark.parametrize("length", [0, -1, 65, "4", 2.0])
def test_canonical_hash_length(length):
    """(was: '' for 0, 63 digits for -1, a slicing TypeError for '4')"""
    with pytest.raises(ValueError, match="canonical_hash's length takes a whole number from 1 to 64"):
        canonical_hash({"a": 1}, length)
