"""One computation, one identity, however its options are written; two computations, two identities,
however alike their options read: a number written as text, an option the final-norm CLS token never
reads, weights in a folder named by a bare word."""
from __future__ import annotations

import re

import pytest

from vprbench.errors import VPRBenchError
from vprbench.methods import create_method
from vprbench.methods.objects import check_method
from vprbench.spec import resolve_spec, spec_for

TINY = {"backbone": "dinov2_vits14", "weights": "random", "resize": [28, 28]}


@pytest.mark.parametrize("method, numbers, texts", [
    ("anyloc", {**TINY, "aggregation": "gem", "layer": 4, "gem_p": 2.5}, {**TINY, "aggregation": "gem", "layer": "4",
                                                                           "gem_p": "2.5"}),
    ("anyloc", {**TINY, "clusters": 8, "pca_dim": 16}, {**TINY, "clusters": "8.0", "pca_dim": "16"}),
    ("hog", {"resize": [64, 64], "cell": 8}, {"resize": [64, 64], "cell": "8"}),
])
def test_a_number_written_as_text_is_that_number(method, numbers, texts):
    """`layer = "4"` in a plan (or from Python) was a run of its own beside `layer = 4`: the method reads both
    as 4, so a second row of the same numbers and a recompute."""
    spec, written = resolve_spec(method, "corridor", options=numbers), resolve_spec(method, "corridor", options=texts)
    assert (written.key, written.row_key, written.given) == (spec.key, spec.row_key, spec.given)
    assert spec_for(create_method(method, **texts), "corridor").key == spec.key
    # a default written as text is the default; a word stays a word for the method to name
    assert resolve_spec("hog", "corridor", options={"cell": "16"}).given == {}
    with pytest.raises(VPRBenchError, match=re.escape("option cell takes a whole number >= 1 (pixels per cell side); "
                                                      "got 'eight'")):
        create_method("hog", cell="eight")


@pytest.mark.parametrize("option", [{"facet": "key"}, {"layer": 3}, {"layer_for": "dinov2_vitg14:20"}])
def test_a_block_option_under_the_final_norm_cls_token_is_refused(option):
    """The final-norm CLS token comes after the last block whatever the layer or facet: `--facet key` named a
    second row of the same numbers (and recomputed them)."""
    for method in ("dinov2-cls", "anyloc"):
        options = {**TINY, "aggregation": "cls", **option}
        name, value = next(iter(option.items()))
        for make in (lambda: resolve_spec(method, "corridor", options=options), lambda: create_method(method, **options)):
            with pytest.raises(VPRBenchError, match=re.escape(f"option {name}={value!r} is not used here (the CLS token "
                                                              "comes from the final norm, after the last block)")):
                make()
    # the last block written out is the block it uses anyway; DINO v1's CLS is a chosen block's, so it counts
    assert resolve_spec("dinov2-cls", "corridor", options={**TINY, "layer": 11}).given == TINY
    dino = {"weights": "random", "resize": [32, 32]}
    assert resolve_spec("dino-cls", "corridor", options={**dino, "facet": "key"}).key != \
        resolve_spec("dino-cls", "corridor", options=dino).key


def test_weights_in_a_folder_named_by_a_bare_word_are_known_by_its_files(tmp_path, monkeypatch):
    """`--weights ckpt` (a folder in the working directory holding the release's file) was identified by the
    word: other weights in another `ckpt` folder made the same run key and row, one result for both."""
    from vprbench.features.backbones import backbone_spec

    name = backbone_spec("dinov2_vits14").source.file_name
    rows = []
    for place, content in (("one", b"first weights"), ("two", b"other weights"), ("three", b"first weights")):
        (tmp_path / place / "ckpt").mkdir(parents=True)
        (tmp_path / place / "ckpt" / name).write_bytes(content)
        monkeypatch.chdir(tmp_path / place)
        spec = resolve_spec("anyloc", "corridor", options={**TINY, "weights": "ckpt", "aggregation": "gem"},
                            cache_dir=tmp_path / "cache")
        assert spec.files["weights"].startswith("ckpt@folder:")
        rows.append((spec.key, spec.row_key))
    assert rows[0] != rows[1] and rows[0] == rows[2]  # other bytes: another run; the same bytes elsewhere: the same
    # 'random' is random initialisation, never a folder or file of that name the working directory holds
    plain = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem"}, cache_dir=tmp_path / "cache")
    for made in ("random", "random/notes.txt"):
        (tmp_path / "one" / made).mkdir() if made == "random" else (tmp_path / "one" / made).write_text("notes")
        monkeypatch.chdir(tmp_path / "one")
        spec = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem"}, cache_dir=tmp_path / "cache")
        assert ("weights" not in spec.files, spec.key, spec.row_key) == (True, plain.key, plain.row_key)


def test_an_evaluation_refuses_anylocs_dataset_option_naming_another_dataset():
    """Before: `-o dataset=pitts30k` on Corridor was overridden by the evaluated dataset, computed without it,
    yet named a row of its own."""
    method = create_method("anyloc", **TINY, aggregation="gem", dataset="pitts30k")
    with pytest.raises(VPRBenchError, match=re.escape("anyloc: option dataset='pitts30k' names another dataset than "
                                                      "the one evaluated ('corridor'), whose settings apply: drop it")):
        method.use_dataset("corridor")
    method.use_dataset("pitts30k")
    unnamed = create_method("anyloc", **TINY, aggregation="gem")  # a sweep's method, one dataset after another
    unnamed.use_dataset("pitts30k")
    unnamed.use_dataset("corridor")
    assert unnamed.dataset == "corridor"


def test_files_of_one_content_named_by_bare_words_stay_apart(tmp_path, monkeypatch):
    """A bare word ('key', 'value') may be a name the method knows: two such files of one content keep
    their words, so facet=key and facet=value are not made one run by the working directory's files."""
    from vprbench.content_identity import file_identity

    monkeypatch.chdir(tmp_path)
    for word in ("key", "value", "w.pth"):
        (tmp_path / word).write_bytes(b"same bytes")
    key, value, path = file_identity("key"), file_identity("value"), file_identity("w.pth")
    assert key.startswith("key@sha256:") and value.startswith("value@sha256:")
    assert key.split("@")[1] == value.split("@")[1] == path  # a file with a suffix is known by its bytes alone


def test_anylocs_dataset_option_naming_the_dataset_evaluated_is_the_run_without_it():
    """Unset, AnyLoc's `dataset` is the dataset evaluated (use_dataset): written equal to it, one run, one
    row, in its spec and in the spec of a method created with it; another dataset's name stays its own."""
    unset = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem"})
    written = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem", "dataset": "corridor"})
    assert (written.key, written.row_key, written.label()) == (unset.key, unset.row_key, unset.label())
    assert "dataset" not in written.options
    created = create_method("anyloc", **TINY, aggregation="gem", dataset="corridor")
    assert spec_for(created, "corridor").key == unset.key
    check_method(created, spec_for(created, "corridor"))  # evaluate takes that method with that spec
    other = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem", "dataset": "pitts30k"})
    assert other.given["dataset"] == "pitts30k" and other.row_key != unset.row_key


def test_anylocs_dataset_option_naming_the_dataset_evaluated_shares_the_store(shared_data, tmp_path):
    """The spec dropped `dataset=corridor` on Corridor, but the store was keyed by the method's own settings,
    which kept it: the same run from the command line computed all 222 descriptors again."""
    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings

    run = RunSettings(cache_dir=tmp_path / "cache", data_dir=shared_data, workers=0)
    created = create_method("anyloc", **TINY, aggregation="gem", dataset="corridor")
    first = evaluate(spec_for(created, "corridor", data_dir=shared_data), run, method=created)
    unset = resolve_spec("anyloc", "corridor", options={**TINY, "aggregation": "gem"}, data_dir=shared_data)
    again = evaluate(unset, run)  # as the command line runs it
    assert first["descriptors_computed"] == {"database": 111, "queries": 111}
    assert again["descriptors_computed"] == {"database": 0, "queries": 0}
    assert again["context"]["store"]["folders"] == first["context"]["store"]["folders"]
    assert "dataset" not in again["method_fingerprint"]["settings"]
    # and one record: the Python route's method_settings kept dataset=corridor, the command line's did not
    assert first["method_settings"] == again["method_settings"] == unset.options
    assert "dataset" not in first["method_settings"] and first["method_settings"]["aggregation"] == "gem"
