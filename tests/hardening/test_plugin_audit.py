"""A careless or hostile method plugin, run through `vprbench describe`, `vprbench evaluate` and
the Python API: what it returns is checked before anything is stored or scored, its name cannot
take another method's, and what keys its descriptors cannot be overwritten by its own fingerprint."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hostile_files import assert_refused
from vprbench import Method, VPRBenchError, register_method
from vprbench.evaluation.provenance import method_provenance
from vprbench.evaluation.results import read_results
from vprbench.methods import registry
from vprbench.paths import cache_root


def unit_rows(images) -> np.ndarray:
    """One unit row per image, set by its file name only (no batch statistics)."""
    rows = np.stack([np.random.default_rng(int(Path(p).stem)).standard_normal(3) for p in images])
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


class Returns(Method):
    """describe returns `shape(unit rows)`: what a careless plugin hands back."""

    shape = staticmethod(lambda rows: rows)

    def __init__(self, device: str = "cpu"):
        pass

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}

    def describe(self, images):
        return type(self).shape(unit_rows(images))


def plugin(name: str, shape=None, base=Returns, **attributes) -> str:
    """Register a method whose describe returns `shape(rows)` (the registry is the test's own copy)."""
    extra = {"shape": staticmethod(shape)} if shape is not None else {}
    register_method(name, type(name.title().replace("-", ""), (base,), {**extra, **attributes}))
    return name


pytestmark = pytest.mark.usefixtures("scratch_methods")  # what a test registers is its own


def describe(cli, tmp_path, method: str, images, *options):
    return cli("describe", "--method", method, *images, "--batch-size", 2, "--out", tmp_path / "d.npy", *options)


# ---------------------------------------------------------------- what describe returns
@pytest.mark.parametrize("shape, length", [
    (lambda rows: rows * 1000, "1000"),                      # not normalised: inner products are not cosines
    (lambda rows: rows * np.float32(1e30), "1e+30"),         # products overflow: the PR curve crashed
    (lambda rows: (rows * 10).astype(np.int64), None),       # whole numbers
    (lambda rows: rows > 0, None),                           # booleans
], ids=["scaled", "huge", "integers", "booleans"])
def test_rows_compared_by_cosine_must_have_length_one(shape, length, cli, tmp_path, images):
    code, _, err = describe(cli, tmp_path, plugin("careless", shape), images)
    assert_refused(code, err, None, "Method 'careless' returned rows that are not L2-normalised",
                   f"has length {length}" if length else "has length", "vprbench.methods.l2_normalise")
    assert not (tmp_path / "d.npy").exists()


@pytest.mark.parametrize("shape, fragment", [
    (lambda rows: rows.astype(np.complex64), "ndarray of complex64 values"),  # its imaginary part was dropped
    (lambda rows: [["a"] * 3] * len(rows), "list of <U1 values"),            # was a ValueError traceback
    (lambda rows: np.array([object()] * len(rows)), "ndarray of object values"),
    (lambda rows: {"rows": rows}, "dict of object values"),
    (lambda rows: None, "returned None"),
    (lambda rows: rows.astype(np.float64) * 1e300, "non-finite descriptors (NaN, infinity, or beyond float32's range)"),
], ids=["complex", "text", "objects", "dict", "none", "beyond-float32"])
def test_what_is_no_array_of_real_numbers_is_refused(shape, fragment, cli, tmp_path, images):
    code, _, err = describe(cli, tmp_path, plugin("careless", shape), images)
    assert_refused(code, err, None, "Method 'careless' ", fragment)


def test_a_nan_row_names_its_row_and_what_to_do(cli, tmp_path, images):
    # a blank image's row divided by its length 0: was the bare "returned non-finite descriptors (...)."
    code, _, err = describe(cli, tmp_path, plugin("divides", lambda rows: np.where(np.arange(len(rows))[:, None] == 1,
                                                                                   np.nan, rows)), images)
    assert_refused(code, err, None, "Method 'divides' returned non-finite descriptors", "first in row 1 of 2: fix it "
                   "(an image with nothing to describe gets an all-zero row")


def zero_first(rows):
    return np.where(np.arange(len(rows))[:, None] == 0, 0, rows)  # an all-zero row, as for a blank image


@pytest.mark.parametrize("shape", [
    lambda rows: torch.from_numpy(rows).requires_grad_(),  # was a RuntimeError traceback ("requires grad")
    lambda rows: torch.from_numpy(rows).to(torch.bfloat16),  # numpy has no bfloat16: was a TypeError traceback
    lambda rows: torch.from_numpy(rows).double(),
    lambda rows: rows.astype(np.float64),
    lambda rows: rows.astype(np.float16),
    lambda rows: np.asfortranarray(np.repeat(rows, 2, axis=1)[:, ::2]),  # not contiguous
    lambda rows: rows.tolist(),
    zero_first,
], ids=["tensor-with-grad", "bfloat16-tensor", "float64-tensor", "float64", "float16", "strided", "list", "zero-row"])
def test_the_forms_of_the_same_rows_are_taken(shape, cli, tmp_path, images):
    code, _, err = describe(cli, tmp_path, plugin("lenient", shape), images)
    assert code == 0, err
    expected = unit_rows(images)
    if shape is zero_first:
        expected[[0, 2, 4]] = 0  # the first row of every batch of 2
    np.testing.assert_allclose(np.load(tmp_path / "d.npy"), expected, atol=1e-2)


# ---------------------------------------------------------------- what its post-processing returns
class Hooked(Returns):
    """A plugin overriding the whole-matrix `postprocess` hook with `self.post(db, q)`."""

    def postprocess(self, database, queries):
        return type(self).post(database, queries)


class Transform:
    def key(self, rows, memory_budget):
        return {"transform": "nan"}

    def fit(self, rows, memory_budget):
        return self

    def transform(self, rows):
        out = np.array(rows, dtype=np.float32)
        out[0, 0] = np.nan
        return out

    def state(self):
        return {"nothing": np.zeros(1)}

    def load_state(self, state):
        pass


@pytest.mark.parametrize("post, fragment", [
    (lambda db, q: (db, q[:-5]), "returned shape (106, 3) for 111 images"),  # was scored over 106 of 111 queries
    (lambda db, q: (db[:-5], q), "returned shape (106, 3) for 111 images"),
    (lambda db, q: (np.where(db == db[0, 0], np.nan, db), q), "non-finite descriptors"),
    (lambda db, q: (db, None), "returned None; expected a (111, dim) array"),
    # finite, but every score inf: searched, ranked as ties, recorded
    (lambda db, q: (db * 1e30, q * 1e30), "returned rows too long to compare (row 0 has length 1e+30"),
], ids=["fewer-queries", "fewer-database", "nan", "none", "overflowing"])
def test_a_postprocess_hook_cannot_change_what_is_scored(post, fragment, cli, shared_data):
    name = plugin("hooked", base=Hooked, post=staticmethod(post))
    code, _, err = cli("evaluate", "--method", name, "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, "Method 'hooked' (its postprocess) returned", fragment, stores_allowed=True)


def test_a_postprocessor_returning_nan_is_refused(cli, shared_data):
    name = plugin("transformed", postprocessor=lambda self: Transform())
    code, _, err = cli("evaluate", "--method", name, "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, "Post-processor Transform returned non-finite descriptors", stores_allowed=True)


class SplitDims(Returns):
    """Three numbers per database image, two per query: each split fine alone, not comparable."""

    def describe(self, images):
        rows = unit_rows(images)[:, :2 if "query" in str(images[0]) else 3]
        return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_splits_of_different_dimensions_name_the_method(cli, shared_data):
    name = plugin("split-dims", base=SplitDims)
    for _ in range(2):  # computed, then served from its stores: the same line
        code, _, err = cli("evaluate", "--method", name, "--dataset", "corridor", "--data-dir", shared_data)
        # was: 'Database descriptors have 3 dims, queries 2', naming neither the method nor what to do
        assert_refused(code, err, None, "Method 'split-dims' described the database in 3 and the queries in 2 "
                                        "dimensions: every image must get the same dimension", stores_allowed=True)


@pytest.mark.parametrize("value, fragment", [
    ({"car", "road"}, "set"), (object(), "object"), (float("nan"), "Out of range float"),
])
def test_an_option_that_is_not_plain_data_is_refused_when_the_method_is_created(value, fragment):
    name = plugin("takes-x", base=type("TakesX", (Returns,), {"__init__": lambda self, x=1, device="cpu": None}))
    # before: created with it; a set or an object was refused only when the run was specified, the object
    # as 'created as ... but now says ...' (its deep copy), which named no option
    with pytest.raises(VPRBenchError, match=rf"Method 'takes-x': an option is not plain data \(.*{fragment}"):
        registry.create_method(name, x=value)


# ---------------------------------------------------------------- what keys its descriptors
class Sized(Returns):
    """A plugin with a `size` option whose fingerprint() returns `self.own`."""

    def __init__(self, size: int = 3, device: str = "cpu"):
        self.size = int(size)

    def describe(self, images):
        rows = np.zeros((len(images), self.size), np.float32)
        rows[:, 0] = 1
        return rows


@pytest.mark.parametrize("own, fragment", [
    ({"settings": {"network": "x"}}, "fingerprint() uses the key(s) settings, which the store's key sets itself"),
    (None, "fingerprint() must return a dict naming what changes its descriptors, got NoneType"),
])
def test_a_fingerprint_cannot_hide_the_options_from_the_store(own, fragment, cli, tmp_path, images):
    name = plugin("sized", base=Sized, fingerprint=lambda self: own)
    code, _, err = describe(cli, tmp_path, name, images, "-o", "size=3")
    # before: accepted, and '-o size=5' was then served the 3-dimensional rows stored for size=3
    assert_refused(code, err, None, f"Method 'sized': {fragment}")


class Projects(Sized):
    """A plugin whose rows come from `projection`, which its fingerprint() names as the array itself."""

    projection = np.zeros(2000)

    def fingerprint(self) -> dict:
        return {"projection": type(self).projection}

    def describe(self, images):
        rows = np.zeros((len(images), 2), np.float32)
        rows[:, 0 if type(self).projection[1000] == 0 else 1] = 1
        return rows


def test_a_fingerprint_holding_an_array_is_refused_not_keyed_by_its_summary(cli, tmp_path, images):
    name = plugin("projects", base=Projects)
    # before: keyed by the array's text, '[0. 0. 0. ... 0. 0. 0.]' for both, so the second projection was
    # served the rows stored for the first
    code, _, err = describe(cli, tmp_path, name, images)
    assert_refused(code, err, None, "Method 'projects': fingerprint() holds a ndarray at projection, which is not "
                                    "plain data", "the sha256 of an array's bytes")


@pytest.mark.parametrize("own, fragment", [
    ({"classes": {"car", "tree", "road"}}, "holds a set at classes"),  # text ordered by each process's hash seed
    ({"net": {"loaded": object()}}, "holds a object at net.loaded"),  # text holds its address: never served again
    ({"scale": float("nan")}, "holds nan at scale; give a finite number"),  # was a traceback
])
def test_a_fingerprint_is_plain_data(own, fragment, cli, tmp_path, images):
    name = plugin("unplain", base=Sized, fingerprint=lambda self: own)
    code, _, err = describe(cli, tmp_path, name, images)
    assert_refused(code, err, None, f"Method 'unplain': fingerprint() {fragment}")


def test_a_fingerprint_key_that_is_not_text_is_refused():
    from vprbench.stages.run import stage_fingerprint
    from vprbench.store.folder import method_fingerprint

    # JSON made 1 the text "1": {1: "a", "1": "b"} keyed as {"1": "b"}, one store for two; a tuple key and
    # a stage's mixed keys were a TypeError traceback
    for own in ({1: "a", "1": "b"}, {(1, 2): 3}):
        with pytest.raises(VPRBenchError, match=r"Method 'x': fingerprint\(\) holds the key .* at its top; give"):
            method_fingerprint(SimpleNamespace(name="x", settings={}, fingerprint=lambda: own))
    with pytest.raises(VPRBenchError, match=r"Stage 's': fingerprint\(\) holds the key 1 \(int\) at net; give"):
        stage_fingerprint(SimpleNamespace(name="s", fingerprint=lambda: {"net": {1: "a", "b": 2}}))


def test_numpy_numbers_and_paths_in_a_fingerprint_key_the_store_as_plain_values(cli, tmp_path, images):
    from vprbench.store.folder import method_fingerprint

    method = SimpleNamespace(name="x", settings={}, fingerprint=lambda: {"dim": np.int64(8), "file": Path("w.pt")})
    plain = SimpleNamespace(name="x", settings={}, fingerprint=lambda: {"dim": 8, "file": "w.pt"})
    assert method_fingerprint(method) == method_fingerprint(plain)  # was {"dim": "8"}: another store for 8


def test_options_key_the_store_whatever_the_fingerprint_forgets(cli, tmp_path, images):
    name = plugin("forgets", base=Sized, fingerprint=lambda self: {})
    for size in (3, 5):
        code, _, err = describe(cli, tmp_path, name, images, "-o", f"size={size}")
        assert code == 0, err
        assert np.load(tmp_path / "d.npy").shape == (5, size)


# ---------------------------------------------------------------- what the registry is given
def test_a_registration_that_is_no_factory_is_one_clear_line(cli, tmp_path, images):
    register_method("not-callable", "os:sep")
    code, _, err = describe(cli, tmp_path, "not-callable", images)  # was: TypeError: '/' is not a callable object
    assert_refused(code, err, None, "Method 'not-callable' (os) is registered with 'os:sep', which is not a class "
                                    "or function returning a vprbench.Method; fix the plugin.")


def test_a_factory_returning_no_method_says_what_it_returned_and_what_to_do(cli, tmp_path, images):
    class Plain:  # a newcomer's class with describe, not derived from vprbench.Method
        def describe(self, images):
            return unit_rows(images)

    register_method("plain", Plain)
    code, _, err = describe(cli, tmp_path, "plain", images)  # was: "... did not return a vprbench.Method", no remedy
    assert_refused(code, err, None, "Method 'plain' (", "): its factory returned Plain, not a vprbench.Method; return "
                                    "an instance of a subclass of vprbench.Method")


def test_an_unknown_comparison_is_refused_before_anything_is_described(cli, tmp_path, images):
    # before: every image described and stored, then an error about sequence matching
    code, _, err = describe(cli, tmp_path, plugin("euclid", compare="euclidean"), images)
    assert_refused(code, err, None, "Method 'euclid' (", ") has compare 'euclidean'; it must be one of cosine, "
                                    "mean-absolute-difference (fix the plugin).")


def test_provenance_must_be_a_dict_and_is_kept_as_json():
    declared = {}
    method = type("Declares", (Returns,), {"provenance": lambda self: declared["value"]})()
    method.name, declared["value"] = "p", "official"
    with pytest.raises(VPRBenchError, match=r"Method 'p': provenance\(\) must return a dict such as .*, got str"):
        method_provenance(method)  # was: AttributeError traceback after every image was described
    marker = object()
    declared["value"] = {"weights": {"source": "none", "loaded_by": marker}}
    assert method_provenance(method)["weights"] == {"source": "none", "loaded_by": str(marker)}  # was unsaveable


def boom(*_):
    raise RuntimeError("server said no")


def leaves(*_):
    raise SystemExit(3)


@pytest.mark.parametrize("part, attributes, error", [
    ("describe", {"describe": boom}, "RuntimeError: server said no"),  # was a traceback through vprbench
    ("describe", {"describe": leaves}, "SystemExit: 3"),  # was exit 3, not a word said
    ("load", {"load": boom}, "RuntimeError: server said no"),
])
def test_a_plugin_that_raises_is_one_line_naming_it_and_its_line(part, attributes, error, cli, tmp_path, images):
    code, _, err = describe(cli, tmp_path, plugin("crashes", __module__="my_plugin", **attributes), images)
    # the image it failed on is named too (describe: the batch's first, batch size 2)
    on = f"image {images[0]} (and 1 more in its batch)" if part == "describe" else f"image {images[0]}"
    assert_refused(code, err, None, f"Method 'crashes' (my_plugin) failed in {part}() of {on}: {error} at ",
                   f"test_plugin_audit.py:{next(iter(attributes.values())).__code__.co_firstlineno + 1}; fix the "
                   "plugin, or report it to its authors.")


# ---------------------------------------------------------------- a method that fails mid-run
def test_a_method_that_fails_mid_run_resumes_with_the_rows_it_finished(cli, tmp_path, images):
    calls = []

    class Flaky(Returns):
        def describe(self, batch):
            calls.append(len(batch))
            if len(calls) == 2 and fail:
                raise VPRBenchError("the plugin's server went away")
            return unit_rows(batch)

    register_method("flaky", Flaky)
    fail = True
    code, _, err = describe(cli, tmp_path, "flaky", images)
    assert code == 1 and "the plugin's server went away" in err and not read_results()
    assert not list(cache_root().rglob("queries.h5")), "no complete store from a failed run"
    fail, calls[:] = False, []
    code, _, err = describe(cli, tmp_path, "flaky", images)
    assert code == 0, err
    assert calls == [2, 1]  # the first batch of 2 was kept, the 3 others described now
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), unit_rows(images))


# ---------------------------------------------------------------- the contract's one required member left out
def test_a_method_without_describe_is_named_not_a_line_of_vprbench(cli, tmp_path, images):
    """Was "failed in its factory ...: TypeError: Can't instantiate abstract class ... at vprbench/methods/
    registry.py:NNN": a line of vprbench's given as the plugin's."""
    class NoDescribe(Method):
        def __init__(self, device: str = "cpu"):
            pass

    register_method("no-describe", NoDescribe)
    code, _, err = describe(cli, tmp_path, "no-describe", images)
    assert_refused(code, err, None, "Method 'no-describe' (", "): NoDescribe does not define describe(), which every "
                   "vprbench.Method needs; define it")
    assert "registry.py" not in err


def test_a_stage_without_apply_is_refused_before_retrieval(scratch_stages, cli, shared_data):
    """Was "failed in apply(): NotImplementedError:  at vprbench/stages/base.py:NNN", after retrieval had run."""
    from vprbench.stages import RerankOptions, Stage
    from vprbench.stages import registry as stages

    class NoApply(Stage):
        Options = RerankOptions

    stages.register_stage("no-apply", NoApply)
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", "corridor", "--data-dir",
                       shared_data, "--k", 1, "--rerank", "no-apply", "--rerank-k", 5)
    assert_refused(code, err, None, "Stage 'no-apply' (", "): NoApply does not define apply(candidates, context), "
                   "which every stage needs; define it")
