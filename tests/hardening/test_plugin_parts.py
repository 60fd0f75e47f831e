"""Every part of a plugin vprbench calls (a method's factory, fingerprint, fit, provenance; a stage's and a
post-processor's methods) that raises is one line naming the plugin, the part and its line; a
post-processor's key names its state exactly; a name has one Unicode form."""
from __future__ import annotations

import re
import unicodedata

import numpy as np
import pytest
from pydantic import field_validator

from hostile_files import assert_refused
from test_plugin_audit import Returns, Transform, plugin
from vprbench import register_method
from vprbench.errors import VPRBenchError
from vprbench.evaluation.results import read_results
from vprbench.methods import registry
from vprbench.stages import RerankOptions, Stage, register_stage


pytestmark = pytest.mark.usefixtures("scratch_methods", "scratch_stages")  # what a test registers is its own


def evaluate(cli, shared_data, method, *extra):
    return cli("evaluate", "--method", method, "--dataset", "corridor", "--data-dir", shared_data, "--k", 1, *extra)


def boom(*_):
    raise RuntimeError("server said no")


def line_of(function) -> str:
    return f"test_plugin_parts.py:{function.__code__.co_firstlineno + 1}; fix the plugin, or report it to its authors."


class Arrayed(Transform):
    """A post-processor keyed by its array: as text, '[0. 0. 0. ... 0. 0. 0.]' whatever its values."""

    def key(self, rows, memory_budget):
        return {"projection": np.zeros(2000)}

    def transform(self, rows):
        return np.asarray(rows, dtype=np.float32)


def test_a_postprocessor_key_holding_an_array_is_refused(cli, shared_data):
    # before: keyed by the array's summarised text, so another array loaded this one's state
    code, _, err = evaluate(cli, shared_data, plugin("arrayed", postprocessor=lambda self: Arrayed()))
    assert_refused(code, err, None, "Post-processor Arrayed: key() holds a ndarray at projection, which is not plain "
                                    "data", stores_allowed=True)


@pytest.mark.parametrize("part, attributes", [
    ("its factory Crashes", {"__init__": boom}),
    ("fingerprint", {"fingerprint": boom}),
    ("fit", {"fit": boom, "needs_fit": True}),
    ("provenance", {"provenance": boom}),
    ("postprocessor", {"postprocessor": boom}),
    ("fitted_image_digests", {"fitted_image_digests": boom}),
])
def test_a_method_part_that_raises_is_one_line(part, attributes, cli, shared_data):
    code, _, err = evaluate(cli, shared_data, plugin("crashes", __module__="my_plugin", **attributes))
    # before: a traceback through vprbench
    assert_refused(code, err, None, f"Method 'crashes' (my_plugin) failed in {part}(): RuntimeError: server said no at ",
                   line_of(boom), stores_allowed=True)


def test_a_factory_option_without_a_default_is_asked_for(cli, shared_data):
    class NeedsSize(Returns):
        def __init__(self, size, device: str = "cpu"):
            self.size = size

    register_method("needs-size", NeedsSize)
    code, _, err = evaluate(cli, shared_data, "needs-size")
    # before: "failed in its factory NeedsSize(): TypeError: ... missing ... 'size' at vprbench/methods/registry.py:NNN"
    assert_refused(code, err, None, "Method 'needs-size' (", ") needs option(s) size, for which it has no default: "
                                    "give it, e.g. -o size=VALUE.")
    assert "registry.py" not in err
    code, _, err = evaluate(cli, shared_data, "needs-size", "-o", "size=3")
    assert code == 0, err


@pytest.mark.parametrize("returned", [["a" * 64], {"vocabulary": "a" * 64}])
def test_fitted_image_digests_of_another_shape_is_refused(returned, cli, shared_data):
    # before: vprbench's own `.items()` (or a set of a string's characters) on what the plugin returned
    code, _, err = evaluate(cli, shared_data, plugin("shapeless", fitted_image_digests=lambda self: returned))
    assert_refused(code, err, None, "Method 'shapeless': fitted_image_digests() must return a dict of part -> set of "
                                    "sha256", stores_allowed=True)


@pytest.mark.parametrize("returned, fragment", [([np.zeros(3)], "(got list)"),
                                               ({"mean": [[1, 2], [3]]}, "inhomogeneous")])
def test_a_fit_state_of_another_shape_is_refused(returned, fragment, cli, shared_data):
    # before: "failed in fit_state(): AttributeError ... at vprbench/evaluation/extract.py:NNN" (vprbench's line
    # named as the plugin's), or a traceback for a ragged array
    method = plugin("shapeless-fit", needs_fit=True, fit=lambda self, database: None, fit_state=lambda self: returned)
    code, _, err = evaluate(cli, shared_data, method)
    assert_refused(code, err, None, "Method 'shapeless-fit': fit_state() must map names to numeric arrays", fragment,
                   stores_allowed=True)
    assert "extract.py" not in err


@pytest.mark.parametrize("part", ["key", "fit", "transform", "state", "check_rows", "output_dim", "state_bytes",
                                  "least_budget"])
def test_a_postprocessor_part_that_raises_is_one_line(part, cli, shared_data):
    # the run's plan asks for its state and fit's need once it says its output's dimension
    broken = type("Broken", (Arrayed,), {"__module__": "my_plugin", "key": lambda self, rows, budget: {"k": 1},
                                         "output_dim": lambda self, rows: rows.dim, part: boom})
    code, _, err = evaluate(cli, shared_data, plugin("post", postprocessor=lambda self: broken()))
    assert_refused(code, err, None, f"Post-processor Broken (my_plugin) failed in {part}(): RuntimeError: server "
                                    "said no at ", line_of(boom), stores_allowed=True)


class Passes(Stage):
    Options = RerankOptions
    track = "re-ranked"

    def apply(self, candidates, context):
        return candidates


@pytest.mark.parametrize("part", ["__init__", "apply", "fingerprint", "provenance", "stored_bytes", "check",
                                  "least_budget"])
def test_a_stage_part_that_raises_is_one_line(part, cli, shared_data):
    register_stage("wobbly", type("Wobbly", (Passes,), {"__module__": "my_plugin", part: boom}))
    code, _, err = evaluate(cli, shared_data, plugin("plain"), "--rerank", "wobbly", "--rerank-k", 5)
    where = "its constructor Wobbly" if part == "__init__" else part
    assert_refused(code, err, None, f"Stage 'wobbly' (my_plugin) failed in {where}(): RuntimeError: server said no at ",
                   line_of(boom), stores_allowed=True)


class Refuses(RerankOptions):
    __module__ = "my_plugin"

    @field_validator("k")
    @classmethod
    def _k(cls, k):
        raise RuntimeError("server said no")  # beyond ValueError: pydantic does not turn it into its own error


def test_a_stage_options_validator_that_raises_is_one_line(cli, shared_data):
    register_stage("picky", type("Picky", (Passes,), {"__module__": "my_plugin", "Options": Refuses}))
    code, _, err = evaluate(cli, shared_data, plugin("plain"), "--rerank", "picky", "--rerank-k", 5)
    # before: a traceback through vprbench (the spec validates a stage's options before anything runs)
    assert_refused(code, err, None, "Stage 'picky' (my_plugin) failed in its options Refuses(): RuntimeError: server "
                                    "said no at ", f"test_plugin_parts.py:{Refuses._k.__func__.__code__.co_firstlineno + 3}")


NFC, NFD = unicodedata.normalize("NFC", "café"), unicodedata.normalize("NFD", "café")


def test_a_name_has_one_unicode_form(cli, shared_data):
    register_method(NFC, Returns)
    # before: registered as a second method 'café', shown alike
    with pytest.raises(ValueError, match=r"Method names are written in Unicode NFC \(composed\), got "
                       + re.escape(f"{NFD!r} (b'cafe\\xcc\\x81')")):
        register_method(NFD, Returns)
    with pytest.raises(ValueError, match=r"Stage names are written in Unicode NFC"):
        register_stage(NFD, Passes)
    assert [n for n in registry.available_methods() if n.startswith("caf")] == [NFC]
    code, out, err = evaluate(cli, shared_data, NFD, "--json", "--quiet")  # typed decomposed: the same method
    assert code == 0, err  # before: Unknown method 'café'
    import json

    assert json.loads(out)["method"] == NFC


def test_a_plan_finds_a_name_typed_decomposed():
    from vprbench.sweep.plan import build_plan

    register_method(NFC, Returns)
    # before: "unknown method 'café'. Did you mean: café?", where the command line took it
    plan = build_plan({"methods": [NFD], "datasets": ["corridor"]}, "plan.toml")
    assert [cell.spec.method for cell in plan.cells] == [NFC]


def test_a_postprocessor_load_state_that_raises_is_one_line(cli, shared_data):
    broken = type("Broken", (Arrayed,), {"__module__": "my_plugin", "key": lambda self, rows, budget: {"k": 1},
                                         "state": lambda self: {"mean": np.zeros(3)}, "load_state": boom})
    method = plugin("loads", postprocessor=lambda self: broken())
    assert evaluate(cli, shared_data, method)[0] == 0  # fitted, its state saved
    # the second run loads that state: before, a traceback through vprbench
    code, _, err = evaluate(cli, shared_data, method)
    assert code == 1 and err.startswith("error: ") and err.count("\n") == 1, err
    assert ("error: Post-processor Broken (my_plugin) failed in load_state(): RuntimeError: server said no at " in err
            and err.endswith(line_of(boom) + "\n")), err
    assert len(read_results()) == 1  # the first run's only


def raises(cls, *_):
    raise RuntimeError("server said no")


@pytest.mark.parametrize("hook", ["cached_identities", "implied_options", "unused_options"])
def test_a_method_hook_that_raises_is_one_line(hook, cli, shared_data):
    code, _, err = evaluate(cli, shared_data, plugin("hooked", __module__="my_plugin", **{hook: classmethod(raises)}))
    # before: a traceback through vprbench (the spec calls the hook before the method exists)
    assert_refused(code, err, None, f"Method 'hooked' (my_plugin) failed in {hook}(): RuntimeError: server said no at ",
                   line_of(raises))


@pytest.mark.parametrize("hook", ["file_identities", "query_window"])
def test_a_stage_hook_that_raises_is_one_line(hook, cli, shared_data):
    register_stage("hooked", type("Hooked", (Passes,), {"__module__": "my_plugin", hook: classmethod(raises)}))
    code, _, err = evaluate(cli, shared_data, plugin("plain"), "--rerank", "hooked", "--rerank-k", 5)
    assert_refused(code, err, None, f"Stage 'hooked' (my_plugin) failed in {hook}(): RuntimeError: server said no at ",
                   line_of(raises), stores_allowed=True)


def test_describe_with_a_use_dataset_that_raises_is_one_line(cli, shared_data, tmp_path):
    images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    code, _, err = cli("describe", "--method", plugin("aimed", __module__="my_plugin", use_dataset=boom), *images,
                       "--dataset", "corridor", "--out", tmp_path / "d.npy")
    # before: a traceback through vprbench
    assert_refused(code, err, None, "Method 'aimed' (my_plugin) failed in use_dataset(): RuntimeError: server said "
                                    "no at ", line_of(boom))


def leaves(self):
    if type(self).broken:
        import sys

        sys.exit("bye")


def fails(self):
    if type(self).broken:
        raise RuntimeError("server said no")
    return None


def unknown(self):
    return fails(self) or {}


@pytest.mark.parametrize("part, attributes, error", [
    ("postprocessor", {"postprocessor": leaves}, "SystemExit: bye"),
    ("postprocessor", {"postprocessor": fails}, "RuntimeError: server said no"),
    ("fingerprint", {"fingerprint": unknown}, "RuntimeError: server said no"),
], ids=["postprocessor-exits", "postprocessor-raises", "fingerprint-raises"])
def test_a_sweep_cell_whose_method_cannot_be_made_is_not_served_its_record(part, attributes, error, cli, shared_data,
                                                                            tmp_path):
    method = plugin("broken", __module__="my_plugin", broken=False, **attributes)
    plan = tmp_path / "plan.toml"
    plan.write_text(f'k = [1]\n\n[[methods]]\nname = "{method}"\n\n[[datasets]]\nname = "corridor"\n')
    assert cli("run", plan, "--data-dir", shared_data)[0] == 0  # a record of the method as it was
    registry.method_entry(method).factory.broken = True
    code, out, err = cli("run", plan, "--data-dir", shared_data)
    # before: served that record ("plan: 1 skipped", exit 0) with no check of the method's identity now (an
    # exit ended the sweep before that); now the cell fails, in one line naming the method and the part
    text = " ".join(out.split())
    assert code == 1 and "Traceback" not in out + err and "plan: 1 failed" in text, (code, out, err)
    assert f"Method 'broken' (my_plugin) failed in {part}(): {error} at " in text, text
    assert len(read_results()) == 1  # the first run's only


def test_a_one_module_plugin_is_named_by_its_own_line_not_a_library_beside_it(tmp_path, monkeypatch):
    from vprbench.loader import plugin_part

    # installed as one module, a plugin lies in site-packages beside the libraries it calls: the
    # line was the library's, where the error surfaced, not the plugin's call
    (tmp_path / "lib_beside").mkdir()
    (tmp_path / "lib_beside" / "__init__.py").write_text("def check(x):\n    raise ValueError('bad shape')\n")
    (tmp_path / "one_module_plugin.py").write_text(
        "import lib_beside\n\nclass Plug:\n    name = 'plug'\n\n    def describe(self, images):\n"
        "        return lib_beside.check(images)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import one_module_plugin

    with pytest.raises(VPRBenchError, match=r"Method 'plug' \(one_module_plugin\) failed in describe\(\): ValueError: "
                                            rf"bad shape at {tmp_path / 'one_module_plugin.py'}:7; fix"):
        with plugin_part(one_module_plugin.Plug(), "describe"):
            one_module_plugin.Plug().describe([])


def test_evaluate_with_a_use_dataset_that_raises_and_the_patch_reranker_is_one_line(cli, shared_data):
    # the patch re-ranker calls use_dataset on its own AnyLoc (vprbench's code), never on the plugin's method,
    # whose use_dataset runs (and fails) before any stage
    code, _, err = evaluate(cli, shared_data, plugin("aimed", __module__="my_plugin", use_dataset=boom), "--rerank",
                            "patch-mnn", "--rerank-k", 5, "--rerank-option", "weights=random", "--rerank-option",
                            "backbone=dinov2_vits14", "--rerank-option", "resize=28x28")
    assert_refused(code, err, None, "Method 'aimed' (my_plugin) failed in use_dataset(): RuntimeError: server said "
                                    "no at ", line_of(boom))


def test_provenance_of_a_method_whose_postprocessor_raises_is_one_line():
    from vprbench.evaluation.provenance import method_provenance

    method = registry.create_method(plugin("crashes", __module__="my_plugin", postprocessor=boom))
    # before: the RuntimeError itself, through vprbench (method_provenance is called as a record is made)
    with pytest.raises(VPRBenchError, match=r"^Method 'crashes' \(my_plugin\) failed in postprocessor\(\): RuntimeError: "
                                            r"server said no at .*" + re.escape(line_of(boom)) + "$"):
        method_provenance(method)


class Patches(Returns):
    """A plugin exposing patch features (as AnyLoc does), which `vocabulary fit` reads."""

    backbone, layer, facet, clusters = "fake", 0, "token", 2

    def __init__(self, clusters=None, device="cpu"):
        pass

    def iter_patch_features(self, paths, resize=None):
        yield from ()
        boom()


def test_a_vocabulary_fit_on_patch_features_that_raise_is_one_line(cli, shared_data):
    register_method("patchy", type("Patchy", (Patches,), {"__module__": "my_plugin"}))
    code, _, err = cli("vocabulary", "fit", "--dataset", "corridor", "--method", "patchy", "--data-dir", shared_data)
    # before: a traceback through vprbench (the fit reads the features as it goes)
    assert_refused(code, err, None, "Method 'patchy' (my_plugin) failed in iter_patch_features(): RuntimeError: server "
                                    "said no at ", line_of(boom))
