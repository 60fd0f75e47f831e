"""A method plugin that changes what vprbench hands it (the batch's list, the database's list, the options'
lists): its rows still land on their own images, and the preset stays what was registered."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hostile_files import assert_refused
from test_plugin_audit import Returns, describe, plugin, unit_rows
from vprbench import create_method, register_method
from vprbench.evaluation.results import read_results
from vprbench.methods import registry


pytestmark = pytest.mark.usefixtures("scratch_methods")  # what a test registers is its own


class Pops(Returns):
    """describe takes the batch's last image off its list and describes the others."""

    def describe(self, images):
        images.pop()
        return unit_rows(images)


def test_a_describe_that_pops_its_list_is_refused_not_shifted_onto_other_images(cli, tmp_path, images):
    # was: its rows written one place early, then 'rows are missing; it cannot be marked complete', naming no plugin
    code, _, err = describe(cli, tmp_path, plugin("pops", base=Pops), images)
    assert_refused(code, err, None, "Method 'pops' returned shape (1, 3) for 2 images; expected (2, dim).")


@pytest.mark.parametrize("shape, fragment", [
    (lambda rows: torch.empty(rows.shape, device="meta"), "returned Tensor (Cannot copy out of meta tensor"),
    (lambda rows: torch.from_numpy(rows).to_sparse(), "returned Tensor (can't convert Sparse layout tensor"),
], ids=["meta-tensor", "sparse-tensor"])
def test_a_tensor_without_rows_to_read_is_refused_in_one_line(shape, fragment, cli, tmp_path, images):
    # was a NotImplementedError / TypeError traceback from vprbench's conversion
    code, _, err = describe(cli, tmp_path, plugin("tensor", shape), images)
    assert_refused(code, err, None, f"Method 'tensor' {fragment}", "expected a (2, dim) array of real numbers")


@pytest.mark.parametrize("hidden", [True, False], ids=["masked-entry", "nothing-masked"])
def test_masked_entries_are_missing_values_not_silently_unmasked(hidden, cli, tmp_path, images):
    def masked(rows):
        mask = np.zeros(rows.shape, bool)
        mask[-1, 0] = hidden  # one value of each batch's last row
        return np.ma.masked_array(rows, mask)

    code, _, err = describe(cli, tmp_path, plugin("masks", masked), images)
    if not hidden:  # a mask hiding nothing loses nothing
        assert code == 0, err
        return
    # was: accepted, the masked value used as if it were real
    assert_refused(code, err, None, "Method 'masks' returned a masked array with masked (missing) entries, "
                                    "first in row 1 of 2: return plain rows")


class Reverses(Returns):
    """fit sorts its database list its own way (here: reversed), as a plugin may before sampling."""

    needs_fit = True

    def fit(self, database):
        database.reverse()


def test_a_fit_that_reorders_its_list_leaves_the_database_in_order(cli, shared_data):
    # was: 'Image .../0000110.jpg changed while reverses fitted on the database', an image nobody changed
    code, out, err = cli("evaluate", "--method", plugin("reverses", base=Reverses), "--dataset", "corridor",
                         "--data-dir", shared_data, "--k", 1)
    assert code == 0, err
    assert [r["method"] for r in read_results()] == ["reverses"]


class Appends(Returns):
    """Its factory and hooks append to the lists they are given (as one normalising its options in place)."""

    def __init__(self, sizes=(1, 2), device: str = "cpu"):
        sizes.append(0)

    @classmethod
    def implied_options(cls, options):
        options["sizes"].append(1)
        return {}

    @classmethod
    def unused_options(cls, options):
        options["sizes"].append(2)
        return {}

    @classmethod
    def cached_identities(cls, options, dataset, cache_dir=None):
        options["sizes"].append(3)
        return {}


def test_a_plugin_changing_its_options_leaves_the_preset_and_the_spec_as_they_were(shared_data):
    from vprbench.spec import resolve_spec

    register_method("appends", Appends, defaults={"sizes": [1, 2]})
    first, second = create_method("appends"), create_method("appends")
    # was [1, 2, 0] then [1, 2, 0, 0]: each method made in one process (a sweep's cells) had another preset
    assert first.settings == second.settings == {"sizes": [1, 2]}
    assert registry.method_entry("appends").defaults == {"sizes": [1, 2]}
    given = create_method("appends", sizes=[5])
    assert given.options == given.settings == {"sizes": [5]}
    spec = resolve_spec("appends", "corridor", options={"sizes": [5]}, data_dir=shared_data)
    registry.method_entry("appends").cached_identities(spec.options, "corridor")  # as an evaluation asks it
    assert spec.options == {"sizes": [5]} and registry.method_entry("appends").defaults == {"sizes": [1, 2]}



# ---------------------------------------------------------------- what is registered
@pytest.mark.parametrize("name", ["a\nb", "a\tb", "a\u200bb", "-o"], ids=["line-break", "tab", "zero-width", "dash"])
def test_a_name_that_would_split_a_row_or_read_as_an_option_is_refused(name, scratch_stages):
    # was taken: 'a\nb' printed the leaderboard's row as two, '-o' could not be given to --method
    from vprbench.stages import Stage, register_stage
    from vprbench.stages import registry as stage_registry

    for register, target in ((register_method, Returns), (register_stage, Stage)):
        with pytest.raises(ValueError, match="no whitespace or control characters and do not start with '-'"):
            register(name, target)
    assert name not in registry.available_methods() and name not in stage_registry.available_stages()


@pytest.mark.parametrize("defaults, fragment", [
    ({"x": float("nan")}, "Out of range float values"),
    ({"x": [1, float("inf")]}, "Out of range float values"),
    ({"x": object()}, "is not plain data"),
    ({1: 2}, "an option's name is text, not 1"),
], ids=["nan", "inf-in-list", "object", "number-key"])
def test_defaults_that_are_not_plain_data_are_refused_when_registered(defaults, fragment):
    # was taken, then a JSON traceback from every command using the method
    with pytest.raises(ValueError, match="in its defaults: register plain data") as refused:
        register_method("preset", Returns, defaults=defaults)
    assert fragment in str(refused.value) and "preset" not in registry.available_methods()


# ---------------------------------------------------------------- a describe that fails
class FailsSecond(Returns):
    """Its second batch raises (a file it cannot read, a server that is down)."""

    calls = 0

    def describe(self, images):
        type(self).calls += 1
        if type(self).calls == 2:
            raise RuntimeError("server said no")
        return unit_rows(images)


def test_a_describe_that_raises_names_the_images_it_was_given(cli, tmp_path, images):
    # was 'failed in describe(): RuntimeError: server said no at ...', which of 5 images left unsaid
    code, _, err = describe(cli, tmp_path, plugin("fails", base=FailsSecond), images)
    assert_refused(code, err, None, f"Method 'fails' (abc) failed in describe() of image {images[2]} (and 1 more in "
                   "its batch): RuntimeError: server said no at ", stores_allowed=True)
    assert not (tmp_path / "d.npy").exists()  # no half-written output; the store's finished rows are resumed


# ---------------------------------------------------------------- what a hook returns
@pytest.mark.parametrize("hook, returned, what", [
    ("implied_options", None, "value"),      # was AttributeError: 'NoneType' object has no attribute 'items'
    ("unused_options", [1], "value"),        # was AttributeError: 'list' object has no attribute 'items'
    ("implied_options", {3: "a"}, "value"),
    ("cached_identities", [1], "text"),      # was a TypeError at registry.py's line, named as the plugin's
    ("cached_identities", {"sizes": 3}, "text"),  # was a pydantic traceback when the spec was made
])
def test_a_hook_returning_no_dict_of_options_is_one_line(hook, returned, what, cli, shared_data):
    register_method("hooked", type("Hooked", (Returns,), {hook: classmethod(lambda cls, *_: returned)}))
    code, _, err = cli("evaluate", "--method", "hooked", "--dataset", "corridor", "--data-dir", shared_data, "--k", 1)
    assert_refused(code, err, None, f"Method 'hooked' (abc): its {hook}() returned {returned!r}; it "
                   f"returns a dict of option name -> {what}. Fix the plugin.")
