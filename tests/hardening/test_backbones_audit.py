"""Bad input of AnyLoc's backbones found by an audit from a user's seat, through the command line,
on random-initialised models: a vocabulary fitted with an aggregation whose features VLAD never
reads, a stride the backbone cannot run, a cached vocabulary of another cluster count or width in
a key's folder, checkpoint values that are no float tensors, files whose name and content
disagree, a truncated checkpoint, and the evaluation's own table of a run on random weights.
Each refusal: one line naming the values and what to do, exit 1, no traceback, nothing cached."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vprbench.aggregation import Vocabulary
from vprbench.aggregation.vocabulary import vocabulary_dir
from vprbench.paths import cache_root

from hostile_files import assert_refused


def nothing_cached() -> None:
    assert not list(cache_root().rglob("vocabulary.pt")), "a refused run cached a vocabulary"
    assert not (cache_root() / "stores").exists(), "a refused run made a descriptor store folder"


def describe(cli, shared_data, tmp_path, *options):
    images = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:2]
    return cli("describe", "--method", "anyloc", *options, "--out", tmp_path / "out.npy", "--quiet", *images)


# ---------------------------------------------------------------- vocabulary fit
@pytest.mark.parametrize("method, options, aggregation", [
    ("anyloc", ["--backbone", "dino_vits8", "--layer", "9", "--facet", "key", "--aggregation", "gem"], "gem"),
    ("dinov2-cls", ["--backbone", "dinov2_vits14", "--layer", "2", "--facet", "value"], "cls"),
])
def test_vocabulary_fit_refuses_an_aggregation_that_reads_other_features(method, options, aggregation, cli,
                                                                         shared_data):
    """DINO's GeM reads patches unnormalised and a final-norm CLS reads the last block's tokens, yet the
    centres were cached under the VLAD key of the layer and facet asked for (and used by VLAD runs)."""
    code, _, err = cli("vocabulary", "fit", "--dataset", "corridor", "--method", method, *options, "--weights",
                       "random", "--clusters", "4", "--budget", "500", "--resize", "28", "28", "--data-dir", shared_data)
    assert_refused(code, err, None, f"vocabulary fit: method {method} has aggregation={aggregation}, which uses no "
                                    "vocabulary", "give --aggregation vlad")
    nothing_cached()


# ---------------------------------------------------------------- stride
@pytest.mark.parametrize("backbone, stride, said", [
    ("dinov3_vits16", 8, "anyloc: option stride=8: backbone dinov3_vits16 runs at its patch stride 16 only; leave "
                         "stride unset or give 16"),
    ("dinov2_vits14", 5, "anyloc: option stride=5 does not divide the patch 14 of dinov2_vits14; give one of 1, 2, 7, "
                         "14"),
])
def test_a_stride_the_backbone_cannot_run_is_refused_before_anything_is_made(backbone, stride, said, cli, shared_data,
                                                                             tmp_path):
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", backbone, "--weights", "random", "--layer", "1",
                            "--aggregation", "gem", "--resize", "48", "48", "-o", f"stride={stride}")
    assert_refused(code, err, None, said)
    nothing_cached()


# ---------------------------------------------------------------- cached vocabularies
@pytest.mark.parametrize("centres, option, said", [
    ((32, 384), "domain", "has 32 clusters but sits in the cache folder of 4-cluster vocabularies: move it to "),
    ((32, 384), "indoor", "has 32 clusters but sits in the cache folder of 4-cluster vocabularies: move it to "),
    ((4, 1536), "domain", "has 1536-dimensional centres but the features are 384-dimensional"),
])
def test_a_cached_vocabulary_of_another_count_or_width_in_a_keys_folder_is_refused(centres, option, said, cli,
                                                                                   shared_data, tmp_path):
    """The authors' bare c_centers.pt (no metadata) copied into the folder of another cluster count was
    used as it was: 32-cluster descriptors under a 4-cluster fingerprint."""
    folder = vocabulary_dir("dinov2_vits14@random", 2, "value", 4, "indoor")
    folder.mkdir(parents=True)
    torch.save(torch.randn(*centres), folder / "c_centers.pt")
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov2_vits14", "--weights", "random", "--layer",
                            "2", "--clusters", "4", "--vocabulary", option, "--dataset", "gardens-point", "--resize",
                            "28", "28", "--fit-on", shared_data / "corridor" / "ref")
    assert_refused(code, err, None, f"Vocabulary {folder / 'c_centers.pt'} ", said)
    if centres[0] == 32:
        assert str(vocabulary_dir("dinov2_vits14@random", 2, "value", 32, "indoor")) in err
    assert not (tmp_path / "out.npy").exists()


def test_a_vocabulary_file_of_another_count_says_which_count_to_give(cli, shared_data, tmp_path):
    path = tmp_path / "v.pt"
    Vocabulary(torch.randn(4, 384), {"backbone": "dinov2_vits14@random", "layer": 2, "facet": "value"}).save(path)
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov2_vits14", "--weights", "random", "--layer",
                            "2", "--clusters", "8", "--vocabulary", path, "--resize", "28", "28")
    assert_refused(code, err, None, f"Vocabulary {path} has 4 clusters, the method asks for 8: give --clusters 4 to "
                                    "use it, or fit one of 8")


# ---------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("change, said", [
    (lambda s: {**s, "cls_token": 5}, "cls_token (int)"),
    (lambda s: {**s, "norm.weight": s["norm.weight"].tolist()}, "norm.weight (list)"),
    (lambda s: {**s, "norm.bias": s["norm.bias"].to(torch.int32)}, "norm.bias (int32)"),
])
def test_checkpoint_values_that_are_no_float_tensors_are_named(change, said, tiny_dinov3, cli, shared_data, tmp_path):
    path = tmp_path / "dinov3.pth"
    torch.save(change(tiny_dinov3), path)
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov3_vits16", "--weights", path, "--layer",
                            "1", "--aggregation", "gem", "--resize", "32", "32")
    assert_refused(code, err, None, f"{path} for backbone dinov3_vits16: The weights file holds values that are no "
                                    f"floating-point tensors: {said}", "a state dict of float tensors")


def test_a_weights_file_is_read_by_its_content_whatever_its_name(tiny_dinov3, cli, shared_data, tmp_path):
    """torch.load reads any *.safetensors path as safetensors (a PyTorch file so named was a traceback),
    and a .safetensors file named .pth was 'damaged'."""
    from safetensors.torch import save_file

    torch.save(tiny_dinov3, tmp_path / "torch.safetensors")
    save_file(tiny_dinov3, str(tmp_path / "safetensors.pth"))
    torch.save(tiny_dinov3, tmp_path / "torch.pth")
    found = {}
    for name in ("torch.safetensors", "safetensors.pth", "torch.pth"):
        code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov3_vits16", "--weights",
                                tmp_path / name, "--layer", "1", "--aggregation", "gem", "--resize", "32", "32")
        assert code == 0, err
        found[name] = np.load(tmp_path / "out.npy")
    assert np.array_equal(found["torch.safetensors"], found["torch.pth"])
    assert np.array_equal(found["safetensors.pth"], found["torch.pth"])


def test_a_vocabulary_named_safetensors_is_refused_in_one_line(cli, shared_data, tmp_path):
    path = tmp_path / "centres.safetensors"
    path.write_bytes(b"\xff" * 64)
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov2_vits14", "--weights", "random", "--layer",
                            "2", "--clusters", "4", "--vocabulary", path, "--resize", "28", "28")
    assert_refused(code, err, None, f"Cannot read vocabulary file {path}: it is damaged or not a PyTorch file")


def test_a_truncated_checkpoint_is_named_once_without_torchs_internals(tiny_dinov3, cli, shared_data, tmp_path):
    path = tmp_path / "dinov3.pth"
    torch.save(tiny_dinov3, path)
    path.write_bytes(path.read_bytes()[:100_000])
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov3_vits16", "--weights", path, "--layer",
                            "1", "--aggregation", "gem", "--resize", "32", "32")
    assert_refused(code, err, None, f"Backbone dinov3_vits16: Cannot read weights file {path}: it is damaged or not a "
                                    "PyTorch file (RuntimeError: PytorchStreamReader failed reading zip archive",
                   "a download or copy that stopped early leaves such a file: get it again (one vprbench "
                   "downloaded: delete it, and the next run downloads it anew).")
    assert err.count(str(path)) == 1 and "miniz" not in err


# ---------------------------------------------------------------- random weights
def test_the_evaluation_table_of_a_run_on_random_weights_says_so(tiny_dinov3, cli, shared_data):
    code, out, err = cli("evaluate", "--method", "anyloc", "--backbone", "dinov3_vits16", "--weights", "random",
                         "--layer", "1", "--aggregation", "gem", "--resize", "32", "32", "--dataset", "corridor",
                         "--data-dir", shared_data, "--quiet")
    assert code == 0, err
    assert "on corridor:vpr-bench (random weights: a pipeline check, not a result)" in " ".join(out.split())


def test_the_summary_of_several_runs_marks_those_on_random_weights(tiny_dinov3, cli, shared_data):
    code, out, err = cli("evaluate", "--method", "anyloc", "--backbone", "dinov3_vits16", "--weights", "random",
                         "--layer", "1", "--aggregation", "gem", "--resize", "32", "32", "--dataset", "corridor",
                         "corridor", "--data-dir", shared_data, "--quiet")
    assert code == 0, err
    assert "random weights: a pipeline check, not a result" in " ".join(out.split())


def test_the_json_record_of_a_run_on_random_weights_is_said_to_be_a_pipeline_check(tiny_dinov3, cli, shared_data):
    """Before: with --json no table titles the run, and nothing on the terminal said its numbers are no result."""
    code, out, err = cli("evaluate", "--method", "anyloc", "--backbone", "dinov3_vits16", "--weights", "random",
                         "--layer", "1", "--aggregation", "gem", "--resize", "32", "32", "--dataset", "corridor",
                         "--data-dir", shared_data, "--quiet", "--json")
    assert code == 0, err
    assert json.loads(out)["provenance"]["weights"]["source"] == "random"  # stdout: the record alone
    assert err.strip() == "random weights: a pipeline check, not a result"


def test_results_verify_says_a_run_on_random_weights_is_a_pipeline_check(tiny_dinov3, cli, shared_data, tmp_path):
    """Before: 'ok, re-scored from its arrays: R@1 ...' read alike for a run on random weights and a real one
    (export and import take both: the board leaves the random one out, and now verify says why)."""
    for method in (("anyloc", "--backbone", "dinov3_vits16", "--weights", "random", "--layer", "1", "--aggregation",
                    "gem", "--resize", "32", "32"), ("hog", "--resize", "16", "16")):
        code, _, err = cli("evaluate", "--method", *method, "--dataset", "corridor", "--data-dir", shared_data, "--quiet")
        assert code == 0, err
    lines = {}
    for method in ("anyloc", "hog"):
        bundle = tmp_path / f"{method}.tar.gz"
        assert cli("results", "export", "--method", method, "--dataset", "corridor", "--to", bundle)[0] == 0
        code, out, err = cli("results", "verify", bundle, "--data-dir", shared_data)
        assert code == 0, err
        [lines[method]] = out.splitlines()
    assert lines["anyloc"].endswith("(random weights: a pipeline check, not a result; it fills no leaderboard cell)")
    assert "pipeline check" not in lines["hog"] and ": ok, re-scored from its arrays: R@1 " in lines["hog"]


def test_describe_says_descriptors_of_random_weights_are_a_pipeline_check(tiny_dinov3, cli, shared_data, tmp_path):
    """Before: 'Wrote 2 descriptors of dimension 384 to out.npy', as for the released weights."""
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov3_vits16", "--weights", "random", "--layer",
                            "1", "--aggregation", "gem", "--resize", "32", "32")
    assert code == 0, err
    assert err.strip().endswith("out.npy (random weights: a pipeline check, not a result)"), err


def test_a_missing_file_of_gated_weights_says_where_access_is_requested(cli, shared_data, tmp_path):
    code, _, err = describe(cli, shared_data, tmp_path, "--backbone", "dinov3_vits16", "--weights", tmp_path / "no.pth",
                            "--layer", "1", "--aggregation", "gem", "--resize", "32", "32")
    assert_refused(code, err, None, f"weights file {tmp_path / 'no.pth'} does not exist; download model.safetensors",
                   "The weights are gated (DINOv3 License): request access at https://github.com/facebookresearch/dinov3")
