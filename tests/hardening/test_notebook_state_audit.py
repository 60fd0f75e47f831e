"""The Python API in one long-lived process with the researcher's own torch settings: their
default dtype, their random stream and their seed are theirs; results do not depend on them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import vprbench
from vprbench.datasets import load_dataset
from vprbench.features import backbones
from vprbench.loader import describe_batches


@pytest.fixture
def fresh_backbones(monkeypatch):
    """No model loaded by an earlier test is served again; the caller's torch defaults restored."""
    monkeypatch.setattr(backbones, "_LOADED", {})
    dtype = torch.get_default_dtype()
    yield
    torch.set_default_dtype(dtype)


def test_random_weights_ignore_the_callers_default_dtype_and_keep_their_random_stream(fresh_backbones):
    """weights="random" under torch.set_default_dtype(float64) gave other weights (under the same
    fingerprint, so a store made by a default-dtype run was served for them), and reseeded the
    caller's random stream."""
    expected = backbones.load_backbone("dinov2_vits14", "random")[0].blocks[0].attn.qkv.weight.clone()
    backbones._LOADED.clear()
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(7)
    torch.manual_seed(7)
    model = backbones.load_backbone("dinov2_vits14", "random")[0]
    following = torch.rand(3)
    weight = model.blocks[0].attn.qkv.weight
    assert weight.dtype == torch.float32 and torch.equal(weight, expected)
    assert torch.get_default_dtype() == torch.float64
    torch.manual_seed(7)
    assert torch.equal(following, torch.rand(3))  # the stream went on as if nothing had been drawn


def test_describing_draws_nothing_from_the_callers_random_stream(shared_data):
    paths = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]
    method = vprbench.create_method("hog", resize=(64, 64))
    torch.manual_seed(3)
    expected = torch.rand(3)
    torch.manual_seed(3)
    rows = np.concatenate([r for _, r in describe_batches(method, paths)])
    assert rows.shape[0] == 3 and torch.equal(torch.rand(3), expected)


def test_random_matcher_weights_ignore_the_callers_default_dtype(fresh_backbones):
    from baselines.lightglue import SuperPointLightGlueOptions, load_models

    options = SuperPointLightGlueOptions(weights="random")
    expected = [m.state_dict() for m in load_models(options)]
    torch.set_default_dtype(torch.float64)
    for model, reference in zip(load_models(options), expected):
        for name, tensor in model.state_dict().items():
            assert tensor.dtype == reference[name].dtype and torch.equal(tensor, reference[name]), name


def test_reprs_say_what_was_made_in_one_line(shared_data):
    """(was: '<vprbench.methods.hog.HOG object at 0x...>', and a Dataset printed every image path)"""
    assert repr(vprbench.create_method("hog", resize=(64, 64))) == "HOG('hog', options={'resize': [64, 64]})"
    dataset = load_dataset("corridor", shared_data)
    assert repr(dataset) == (f"Dataset('corridor', 111 database, 111 queries, positive lists, protocol "
                             f"corridor:vpr-bench, root={str(shared_data / 'corridor')!r})")
    assert repr(dataset.ground_truth) == "GroundTruth('positives', 111 positive lists)"

    class Odd(vprbench.Method):
        @property
        def options(self):
            raise RuntimeError("not yet")

        def describe(self, images):
            return np.ones((len(images), 1), np.float32)

    assert repr(Odd()).startswith("<") and "Odd object at" in repr(Odd())  # a property that raises: still a repr


def test_a_name_registered_again_after_an_edit_says_what_to_do(scratch_methods):

    class Mine(vprbench.Method):
        def describe(self, images):
            return np.ones((len(images), 1), np.float32)

    vprbench.register_method("mine-notebook", Mine)
    vprbench.register_method("mine-notebook", Mine)  # the same registration again: no clash

    class Mine(vprbench.Method):  # noqa: F811 (the cell run again after an edit: another class of that name)
        def describe(self, images):
            return np.zeros((len(images), 1), np.float32)

    with pytest.raises(ValueError, match=r"Method name 'mine-notebook' is taken \(registered by [\w.]+ already, "
                                         r"with another definition.*restart Python"):
        vprbench.register_method("mine-notebook", Mine)


def test_a_default_device_set_by_the_caller_moves_nothing(shared_data):
    """torch.set_default_device (a notebook's "cuda"; "meta" here) put the loader's seed and AnyLoc's
    mean and std on it: 'Tensor.item() cannot be called on meta tensors', 'not on the expected device'."""
    from vprbench.features.preprocess import to_normalised_tensor

    paths = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]
    expected = np.concatenate([r for _, r in describe_batches(vprbench.create_method("hog", resize=(64, 64)), paths)])
    torch.set_default_device("meta")
    try:
        rows = np.concatenate([r for _, r in describe_batches(vprbench.create_method("hog", resize=(64, 64)), paths)])
        normalised = to_normalised_tensor(np.full((2, 2, 3), 255, np.uint8))
    finally:
        torch.set_default_device(None)
    np.testing.assert_array_equal(rows, expected)
    assert normalised.device.type == "cpu" and torch.allclose(normalised[:, 0, 0], torch.tensor([2.2489, 2.4286, 2.64]),
                                                              atol=1e-4)
