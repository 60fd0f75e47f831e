"""A method object changed after `create_method` (`m.size = 4`, another HOGDescriptor) is refused by
`spec_for` and `evaluate(method=m)`, naming what differs, before anything is stored or recorded: it
was evaluated under the name and options it was created with, and its descriptors served a later
run of those options (a plain `--method hog --resize 64 64` read 729 dimensions instead of 441)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

import vprbench
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.images import load_image
from vprbench.methods import create_method
from vprbench.spec import RunSettings, resolve_spec, spec_for


class Thumb(vprbench.Method):  # the thumbnail of docs/add-your-method.md
    def __init__(self, size: int = 16):
        self.size = size

    def fingerprint(self) -> dict:
        return {"size": self.size}

    def describe(self, images):
        rows = [np.asarray(load_image(p, "L").resize((self.size, self.size)), dtype=np.float32).ravel() for p in images]
        return vprbench.methods.l2_normalise(np.stack(rows) - 100)


def _nothing_stored(cache) -> bool:
    return not (cache / "stores").exists() and not (cache / "results").exists()


def test_a_method_changed_after_create_method_is_refused_naming_the_option(scratch_methods, shared_data, tmp_path):
    vprbench.register_method("thumb", Thumb, defaults={"size": 16})
    settings = RunSettings(cache_dir=tmp_path / "cache", data_dir=shared_data, workers=0)
    method = create_method("thumb")
    spec = spec_for(method, "corridor", ks=(1, 5))
    method.size = 4
    for call in (lambda: evaluate(spec, settings, method=method), lambda: spec_for(method, "corridor")):
        with pytest.raises(VPRBenchError, match=r"differs \(size: 16 then, 4 now\).*create_method\('thumb', size=4\)"):
            call()
    assert _nothing_stored(settings.cache_dir)
    assert evaluate(spec_for(create_method("thumb", size=4), "corridor", ks=(1, 5)), settings,
                    method=create_method("thumb", size=4))["descriptor_dim"] == 16  # made so, it runs


def test_a_hog_given_another_descriptor_is_refused_and_leaves_the_store_of_its_options(shared_data, tmp_path):
    settings = RunSettings(cache_dir=tmp_path / "cache", data_dir=shared_data, workers=0)
    method = create_method("hog", resize=[64, 64])
    spec = spec_for(method, "corridor", ks=(1, 5))
    method.hog = cv2.HOGDescriptor((32, 32), (16, 16), (8, 8), (16, 16), 9)
    with pytest.raises(VPRBenchError, match=r"fingerprint differs \(descriptor: .*leave its attributes as made"):
        evaluate(spec, settings, method=method)
    assert _nothing_stored(settings.cache_dir)
    unchanged = create_method("hog", resize=[64, 64])  # evaluated twice: its dataset set, it is still as made
    for _ in range(2):
        record = evaluate(spec, settings, method=unchanged)
        assert record["descriptor_dim"] == 441
    plain = evaluate(resolve_spec("hog", "corridor", options={"resize": [64, 64]}, ks=(1, 5)), settings)
    assert plain["descriptor_dim"] == 441 and plain["descriptors_computed"] == {"database": 0, "queries": 0}


def test_hogs_fingerprint_names_what_computes_its_rows():
    """The store is keyed by the fingerprint: a HOGDescriptor or window set by hand is named in it; the
    parameters' own keep the key every store made so far has."""
    method = create_method("hog", resize=[64, 64])
    assert "descriptor" not in method.fingerprint()
    method.size = (32, 32)
    assert method.fingerprint()["descriptor"]["image"] == [32, 32]
