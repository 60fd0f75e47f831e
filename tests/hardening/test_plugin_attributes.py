"""The attributes vprbench reads off a plugin's method (needs_fit, compare, batch_size, device, cache_dir) and
sets on it (name, batch_size): a property that raises, or a value of another type, is one line naming the
method, the attribute and what to do, through `vprbench describe`/`evaluate` and the Python API, with nothing
stored; before, a traceback from wherever vprbench first read it (or 'yes' read as True)."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import textwrap

import pytest

from hostile_files import assert_refused
from vprbench import VPRBenchError, create_method, register_method
from vprbench.evaluation.pipeline import evaluate
from vprbench.evaluation.results import read_results
from vprbench.paths import cache_root
from vprbench.spec import RunSettings, spec_for

PLUGIN = '''\
import numpy as np
from vprbench import Method


def raises(self):
    raise RuntimeError("server said no")


class Plugin(Method):
    {body}

    def provenance(self):
        return {{"weights": {{"source": "none"}}}}

    def describe(self, images):
        return np.tile(np.float32([1, 0, 0]), (len(images), 1))
'''
RAISES_AT = 6  # the line of `raise` in PLUGIN
#: a module name per plugin: Python keeps a module imported once
NUMBERS = itertools.count()


pytestmark = pytest.mark.usefixtures("scratch_methods")  # what a test registers is its own


def plugin_file(folder, module: str, body: str):
    """A plugin module `module`.py in `folder`, its class Plugin holding `body`."""
    path = folder / f"{module}.py"
    path.write_text(PLUGIN.format(body=textwrap.indent(body, "    ").strip()))
    return path


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """plugin(body) -> (name, file, module): the plugin registered by its import path, as an entry point does."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def make(body: str):
        module = f"attr_plugin_{next(NUMBERS)}"
        path = plugin_file(tmp_path, module, body)
        register_method(module.replace("_", "-"), f"{module}:Plugin")
        return module.replace("_", "-"), path, module

    return make


def run(cli, command: str, name: str, shared_data, tmp_path, *extra):
    if command == "describe":
        images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
        return cli("describe", "--method", name, *images, "--out", tmp_path / "d.npy", *extra)
    return cli("evaluate", "--method", name, "--dataset", "corridor", "--data-dir", shared_data, "--k", 1, *extra)


RAISING = ["needs_fit", "compare", "batch_size", "device", "cache_dir"]
WRONG = [
    ("needs_fit", "'yes'", "True or False"),  # was read as True: a fit asked for
    ("needs_fit", "None", "True or False"),  # was read as False
    ("device", "5", "a device name such as 'cpu' or 'cuda'"),  # was recorded as device "5"
    ("cache_dir", "5", "a folder (text or a path), or None"),
]


@pytest.mark.parametrize("command", ["describe", "evaluate"])
@pytest.mark.parametrize("attribute", RAISING)
def test_a_property_that_raises_is_one_line(attribute, command, plugin, cli, shared_data, tmp_path):
    name, path, module = plugin(f"{attribute} = property(raises)")
    code, _, err = run(cli, command, name, shared_data, tmp_path)
    assert_refused(code, err, None, f"error: Method {name!r} ({module}) failed reading its attribute {attribute}: "
                                    f"RuntimeError: server said no at {path}:{RAISES_AT}; fix the plugin, or report it "
                                    "to its authors.")


@pytest.mark.parametrize("command", ["describe", "evaluate"])
@pytest.mark.parametrize("attribute, value, expected", WRONG)
def test_an_attribute_of_another_type_is_one_line(attribute, value, expected, command, plugin, cli, shared_data, tmp_path):
    name, _, module = plugin(f"{attribute} = {value}")
    code, _, err = run(cli, command, name, shared_data, tmp_path)
    assert_refused(code, err, None, f"error: Method {name!r} ({module}) has {attribute} {value}; it must be "
                                    f"{expected}", "(fix the plugin).")


def test_needs_fit_set_by_use_dataset_is_checked_before_anything_is_described(plugin, cli, shared_data, tmp_path):
    # before: the run went through and its record said needs_fit true
    name, _, module = plugin("def use_dataset(self, name):\n    self.needs_fit = 'yes'")
    code, _, err = run(cli, "evaluate", name, shared_data, tmp_path)
    assert_refused(code, err, None, f"error: Method {name!r} ({module}) has needs_fit 'yes'; it must be True or "
                                    "False (fix the plugin).")


@pytest.mark.parametrize("body, extra, attribute", [
    ("name = property(lambda self: 'mine')", (), "name"),
    ("batch_size = property(lambda self: 4)", ("--batch-size", 2), "batch_size"),
])
def test_an_attribute_vprbench_sets_that_cannot_be_set_is_one_line(body, extra, attribute, plugin, cli, shared_data,
                                                                  tmp_path):
    name, _, module = plugin(body)  # before: AttributeError: property ... has no setter, from vprbench's code
    code, _, err = run(cli, "evaluate", name, shared_data, tmp_path, *extra)
    assert_refused(code, err, None, f"error: Method {name!r} ({module}) does not let vprbench set its {attribute} "
                                    "(AttributeError: ", f"drop the plugin's own {attribute} (or give it a setter)")


def test_an_installed_plugin_file_is_refused_in_one_line(shared_data, tmp_path):
    """Through the entry point of a plugin installed beside vprbench, in a command of its own."""
    site = tmp_path / "site"
    (site / "attr_installed-0.dist-info").mkdir(parents=True)
    path = plugin_file(site, "attr_installed", "needs_fit = property(raises)")
    (path.parent / "attr_installed.py").write_text(path.read_text() + "\n\ndef register():\n    from vprbench import "
                                                   "register_method\n    register_method('attrs', Plugin)\n")
    (site / "attr_installed-0.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: attr-installed\nVersion: 0\n")
    (site / "attr_installed-0.dist-info" / "entry_points.txt").write_text(
        "[vprbench.methods]\nattrs = attr_installed:register\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "vprbench.cli.main", "evaluate", "--method", "attrs", "--dataset",
                           "corridor", "--data-dir", str(shared_data), "--json"], env=env, capture_output=True, text=True)
    assert done.returncode == 1 and done.stdout == "" and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"error: Method 'attrs' (attr_installed) failed reading its attribute needs_fit: RuntimeError: server said no "
        f"at {path}:{RAISES_AT}; fix the plugin, or report it to its authors."]
    assert not list(cache_root().rglob("*.h5")) and not read_results()


# ---------------------------------------------------------------- the Python API
@pytest.mark.parametrize("body, fragment", [
    ("needs_fit = property(raises)", "failed reading its attribute needs_fit: RuntimeError: server said no"),
    ("needs_fit = 'yes'", "has needs_fit 'yes'; it must be True or False"),
    ("device = property(raises)", "failed reading its attribute device: RuntimeError: server said no"),
])
def test_create_method_refuses_the_attribute(body, fragment, plugin):
    name, _, module = plugin(body)
    with pytest.raises(VPRBenchError, match=f"Method {name!r} \\({module}\\) {fragment}") as refused:
        create_method(name)
    assert isinstance(refused.value.__cause__, RuntimeError) == ("raises" in body)  # its chain kept for a debugger


@pytest.mark.parametrize("attribute, value, expected", [
    ("compare", 5, "one of cosine, mean-absolute-difference"),
    ("batch_size", 0, "a whole number >= 1"),
    ("batch_size", -3, "a whole number >= 1"),
    ("batch_size", 2.5, "a whole number >= 1"),
    ("batch_size", "8", "a whole number >= 1"),
    ("needs_fit", "yes", "True or False"),
])
def test_a_method_built_without_create_method_is_checked_as_one_built_with_it(attribute, value, expected, plugin):
    name, _, module = plugin("pass")
    method = create_method(name)
    setattr(method, attribute, value)  # as a plugin's own code may leave it after creation
    with pytest.raises(VPRBenchError, match=f"Method {name!r} \\({module}\\) has {attribute} {value!r}; "
                                            f"it must be {expected}"):
        spec_for(method, "corridor")  # before: taken, for the run to fail (or not) later


def test_python_evaluate_refuses_needs_fit_set_by_use_dataset_storing_nothing(plugin, shared_data, tmp_path):
    name, _, module = plugin("def use_dataset(self, name):\n    self.needs_fit = 'yes'")
    spec = spec_for(create_method(name), "corridor")
    with pytest.raises(VPRBenchError, match=f"Method {name!r} \\({module}\\) has needs_fit 'yes'; it must be "
                                            "True or False \\(fix the plugin\\)."):
        evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=tmp_path / "cache"))
    assert not list((tmp_path / "cache").rglob("*.h5")) and not read_results(tmp_path / "cache")
