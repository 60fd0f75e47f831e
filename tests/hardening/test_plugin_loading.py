"""Installed method plugins as they load: one that fails (raises, exits, lacks a dependency, fails
partway, says nothing) is a warning and skipped whole, and a method it would have given names it;
none takes a core method's name."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from hostile_files import assert_refused
from vprbench import Method, register_method
from vprbench.methods import registry
from vprbench.registration import run_plugins


class Returns(Method):
    """A plugin's method (never run here)."""

    def __init__(self, device: str = "cpu"):
        pass

    def describe(self, images):
        raise AssertionError("not described here")


def test_a_plugin_cannot_take_a_core_method_name(scratch_methods):
    class Hijack(Returns):
        pass

    def hijack():  # an installed plugin's entry point, registering HOG's name (its rows all ties: R@1 2.7 as HOG)
        register_method("hog", Hijack, description="not HOG")

    scratch_methods.fresh()
    with pytest.raises(ValueError, match=r"Method name 'hog' is taken \(registered by vprbench\); register yours "
                                         "under another name"):
        register_method("hog", Hijack)  # the Python API, before the registry was ever read: the core's name first
    scratch_methods.fresh(SimpleNamespace(name="hijack", value="x:hijack", load=lambda: hijack))
    with pytest.warns(UserWarning, match=r"Method plugin 'hijack' \(x:hijack\) failed to load: Method name 'hog' is "
                                         r"taken \(registered by vprbench\)"):
        entry = registry.method_entry("hog")
    assert entry.source == "vprbench" and entry.target == "vprbench.methods.hog:HOG"
    register_method("thumb", Returns)
    with pytest.raises(ValueError, match="Method name 'thumb' is taken"):  # a second plugin's, or a second factory
        register_method("thumb", Hijack)
    register_method("thumb", Returns)  # the same registration again is no clash
    assert registry.method_entry("thumb").target is Returns


def test_a_plugin_that_exits_while_loading_is_skipped(scratch_methods, cli):
    def exits():  # e.g. a module that calls sys.exit when a dependency is missing: every command ended with it
        raise SystemExit("please install superlib")

    scratch_methods.fresh(SimpleNamespace(name="exits", value="x:exits", load=lambda: exits))
    with pytest.warns(UserWarning, match=r"Method plugin 'exits' \(x:exits\) failed to load: please install superlib"):
        code, out, err = cli("methods", "list", "--json")
    assert code == 0 and "hog" in out, err


def test_a_method_of_a_plugin_that_failed_to_import_is_not_just_unknown(scratch_methods, cli, tmp_path):
    """The plugin's methods were 'Unknown method' alone, as if never installed; the error names the plugin
    that failed to load, why, and what to do."""
    def broken():
        import nonexistent_dependency_of_the_plugin  # noqa: F401

    scratch_methods.fresh(SimpleNamespace(name="mine", value="my_pkg:register", load=lambda: broken))
    with pytest.warns(UserWarning, match="Method plugin 'mine'"):
        code, _, err = cli("evaluate", "--method", "thumbnail", "--dataset", "corridor", "--k", "1")
    assert_refused(code, err, None, "Unknown method 'thumbnail'. Run 'vprbench methods list' to see all methods. It may "
                   "come from a plugin that failed to load: 'mine' (my_pkg:register): No module named "
                   "'nonexistent_dependency_of_the_plugin'. To use its methods, install what it needs or fix it (or "
                   "uninstall the plugin).")
    plan = tmp_path / "plan.toml"  # a plan names it in its list of problems alike
    plan.write_text('k = [1]\n[[methods]]\nname = "thumbnail"\n[[datasets]]\nname = "corridor"\n')
    code, _, err = cli("run", plan)
    assert code == 1 and "plan.toml:3: unknown method 'thumbnail'" in err, err
    assert "It may come from a plugin that failed to load: 'mine' (my_pkg:register)" in err, err


class Silent:
    """An entry point whose register() raises an exception without a message."""

    name, value = "quiet", "pkg:register"

    def load(self):
        def register():
            raise RuntimeError()
        return register


def test_a_plugin_failing_without_a_message_is_named_by_its_error_type():
    with pytest.warns(UserWarning, match=r"plugin 'quiet' \(pkg:register\) failed to load: RuntimeError$"):
        assert run_plugins("Method", [Silent()], {}) == ["'quiet' (pkg:register): RuntimeError"]


def test_a_plugin_failing_partway_is_skipped_whole(scratch_methods, scratch_stages):
    """What its register() registered before it failed is taken out again, in every registry (a method
    plugin may register stages too: was, its stages stayed); the core's and other plugins' stay."""
    from vprbench.stages import register_stage
    from vprbench.stages import registry as stages

    scratch_stages.fresh(SimpleNamespace(name="other", value="o:register",
                                         load=lambda: lambda: register_stage("other-stage", "o:Stage")))

    def partway():  # the stage registry is first read here: its core and plugin stages load meanwhile
        register_method("first", Returns)
        register_stage("its-stage", "pkg:Stage")
        raise RuntimeError("the second method's import failed")

    scratch_methods.fresh(SimpleNamespace(name="partway", value="pkg:register", load=lambda: partway))
    with pytest.warns(UserWarning, match="failed to load: the second method's import failed"):
        methods = registry.available_methods()
    assert "first" not in methods and "hog" in methods
    found = stages.available_stages()
    assert "its-stage" not in found and {"other-stage", "aqe", "sift-ransac"} <= set(found)
