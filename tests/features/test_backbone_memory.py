"""A backbone larger than the machine's memory is refused from its shapes, before it is built or a
weights file read (a 7B ViT built with random weights got the process killed without a word)."""
from __future__ import annotations

import torch

from vprbench.evaluation import provenance
from vprbench.features.backbones import create_model

from release_formats import official_state_dict
from test_bad_input_audit import assert_refused, evaluate, tiny


def test_a_backbone_larger_than_memory_is_refused_before_it_is_built(cli, shared_data, tmp_path, monkeypatch):
    spec = tiny("dinov2_vits14", monkeypatch)
    weights = tmp_path / "release.pth"
    torch.save(official_state_dict(create_model(spec), spec), weights)
    built = []
    with monkeypatch.context() as patched:  # undone alone: the test's cache folder stays set
        patched.setattr(torch.nn.Linear, "reset_parameters",
                        lambda self: self.weight.is_meta or built.append(self))  # initialised in memory
        patched.setattr(provenance, "memory_bytes", lambda: 2**20)  # 1 MiB: less than the tiny ViT's float32 weights
        for given in ("random", str(weights)):
            code, _, err = evaluate(cli, shared_data, spec.name, given)
            assert_refused(code, err, f"Backbone {spec.name} needs", "GiB for its float32 weights",
                           "more than this machine's 0.0 GiB of memory", "choose a smaller backbone")
    assert not built, "the model was built before it was refused"
    assert evaluate(cli, shared_data, spec.name, "random")[0] == 0  # the next run, with the memory it needs
