"""Small holes: a stage name taken by a plugin, one broken registration ending `methods list`,
'random' weights for a method without random initialisation, a bundle packed with plain
`tar czf`, and a dataset.toml nested too deeply to parse."""
from __future__ import annotations

import io
import json
import tarfile
from types import SimpleNamespace

import pytest

import vprbench
from vprbench.methods import registry as methods
from vprbench.stages import registry as stages
from vprbench.stages.expansion import AlphaQE


# ---------------------------------------------------------------- a taken stage name
class Hijack(AlphaQE):
    """Another stage, under a built-in stage's name it would have taken (its results recorded as SeqSLAM's)."""


def test_a_plugin_cannot_take_a_stage_name(scratch_stages):
    scratch_stages.fresh()
    with pytest.raises(ValueError, match=r"Stage name 'sift-ransac' is taken \(registered by vprbench\); register "
                                         "yours under another name"):
        stages.register_stage("sift-ransac", Hijack)  # the Python API, before the registry was ever read

    def hijack():  # an installed plugin's entry point
        stages.register_stage("seqslam", Hijack)

    scratch_stages.fresh(SimpleNamespace(name="hijack", value="x:hijack", load=lambda: hijack))
    with pytest.warns(UserWarning, match=r"Stage plugin 'hijack' \(x:hijack\) failed to load: Stage name 'seqslam' "
                                         r"is taken \(registered by vprbench\)"):
        entry = stages.stage_entry("seqslam")
    assert entry.source == "vprbench" and entry.target == "vprbench.stages.sequence:SeqSLAM"
    stages.register_stage("mine", AlphaQE)
    with pytest.raises(ValueError, match=r"Stage name 'mine' is taken \(registered by vprbench\)"):  # another plugin's
        stages.register_stage("mine", Hijack)
    stages.register_stage("mine", AlphaQE)  # the same registration again is no clash
    assert stages.stage_entry("mine").target is AlphaQE


def test_a_stage_plugin_that_exits_while_loading_is_skipped(scratch_stages, cli):
    def exits():
        raise SystemExit("please install superlib")

    scratch_stages.fresh(SimpleNamespace(name="exits", value="x:exits", load=lambda: exits))
    with pytest.warns(UserWarning, match=r"Stage plugin 'exits' \(x:exits\) failed to load: please install superlib"):
        code, out, err = cli("stages", "list", "--json")
    assert code == 0 and "seqslam" in {s["name"] for s in json.loads(out)}, err


# ---------------------------------------------------------------- one broken registration in a list
@pytest.mark.usefixtures("scratch_methods", "scratch_stages")
@pytest.mark.parametrize("kind", ["methods", "stages"])
def test_a_list_marks_a_registration_that_cannot_be_loaded(cli, kind):
    register = vprbench.register_method if kind == "methods" else stages.register_stage
    listed = methods.available_methods() if kind == "methods" else stages.available_stages()
    register("broken", "nosuchmodule:thing")
    why = f"{kind[:-1].title()} 'broken' (nosuchmodule) cannot be loaded from nosuchmodule:thing: No module named " \
          "'nosuchmodule'; install what it needs or fix it (or uninstall the plugin)."
    code, out, err = cli(kind, "list", "--json")
    assert code == 0, err
    shown = {e["name"]: e for e in json.loads(out)}
    assert set(shown) == set(listed) | {"broken"}
    assert shown["broken"]["unloadable"] == why and shown["broken"]["options"] is None
    assert not [e for e in shown.values() if e["name"] != "broken" and ("unloadable" in e or e["options"] is None)]
    code, out, err = cli(kind, "list")
    assert code == 0 and "broken" in out, err
    if kind == "stages":  # the methods table imports no factory (torch): it lists names, --json loads them
        assert "UNLOADABLE: " in out and "nosuchmodule" in out and "sift-ransac" in out


@pytest.mark.parametrize("module, why", [("raises", "needs a GPU"), ("exits", "please install superlib")])
def test_a_registration_whose_module_fails_on_import_is_one_line(monkeypatch, scratch_methods, cli, shared_data,
                                                                  tmp_path, module, why):
    """A plugin module that raises or calls sys.exit when imported: a traceback, or the listing ended."""
    (tmp_path / f"{module}_plugin.py").write_text('raise RuntimeError("needs a GPU")\n' if module == "raises" else
                                                  'import sys\nsys.exit("please install superlib")\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    vprbench.register_method("broken", f"{module}_plugin:Thing")
    code, out, err = cli("methods", "list", "--json")
    assert code == 0, err
    fix = "install what it needs or fix it (or uninstall the plugin)"  # what to do: the line said only what failed
    assert {e["name"]: e for e in json.loads(out)}["broken"]["unloadable"].endswith(f"_plugin:Thing: {why}; {fix}.")
    code, out, err = cli("evaluate", "--method", "broken", "--dataset", "corridor", "--data-dir", shared_data)
    assert code == 1 and err == f"error: Method 'broken' ({module}_plugin) cannot be loaded from {module}_plugin:Thing: " \
                                f"{why}; {fix}.\n", err


# ---------------------------------------------------------------- --weights random
def test_random_weights_are_only_for_anyloc_backbones(cli, shared_data):
    code, _, err = cli("evaluate", "--method", "cosplace", "--weights", "random", "--dataset", "corridor",
                       "--data-dir", shared_data)
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("error: cosplace: weights 'random' (random initialisation) are only for AnyLoc backbones "
                          "and the stages that take them; pass a weights file in the official format instead: download "
                          "ResNet101_2048_cosplace.pth from https://"), err
    assert "does not exist" not in err


# ---------------------------------------------------------------- a bundle packed with tar czf
@pytest.fixture
def unpacked(cli, shared_data, tmp_path):
    """A real bundle (a hog run on Corridor), unpacked into a folder, as a contributor would."""
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", "corridor", "--k", 1,
                       "--data-dir", shared_data)
    assert code == 0, err
    assert cli("results", "export", "--method", "hog", "--dataset", "corridor", "--to", tmp_path / "b.tar.gz")[0] == 0
    folder = tmp_path / "bundle"
    with tarfile.open(tmp_path / "b.tar.gz") as archive:
        archive.extractall(folder, filter="data")
    return folder


@pytest.mark.parametrize("names", ["each", "dot"])
def test_a_bundle_packed_with_tar_czf_is_verified_and_imported(unpacked, cli, shared_data, tmp_path, names):
    """'tar czf b.tgz MANIFEST.json <hash> methods' and 'tar czf b.tgz -C bundle .' both write folder
    entries (the second names every member './...'); tarfile's add writes the same."""
    packed = tmp_path / "packed.tgz"
    with tarfile.open(packed, "w:gz") as archive:
        if names == "dot":
            archive.add(unpacked, arcname=".")
        for child in sorted(unpacked.iterdir()) if names == "each" else ():
            archive.add(child, arcname=child.name)
    assert any(m.isdir() for m in tarfile.open(packed).getmembers())
    code, out, err = cli("results", "verify", packed, "--data-dir", shared_data)
    assert code == 0 and ": ok, re-scored from its arrays" in out, out + err
    code, out, err = cli("results", "import", packed, "--into", tmp_path / "repository", "--data-dir", shared_data)
    assert code == 0, out + err
    assert len(list((tmp_path / "repository").glob("*/*/*.npz"))) == 1


@pytest.mark.parametrize("name, kind, refusal", [("../up", tarfile.DIRTYPE, "escapes the folder"),
                                                 ("/abs", tarfile.DIRTYPE, "escapes the folder"),
                                                 ("methods", tarfile.SYMTYPE, "is a link"),
                                                 ("dev", tarfile.CHRTYPE, "is a special file")])
def test_folder_entries_that_escape_and_links_are_still_refused(cli, shared_data, tmp_path, name, kind, refusal):
    packed = tmp_path / "packed.tgz"
    with tarfile.open(packed, "w:gz") as archive:
        info = tarfile.TarInfo(name)
        info.type, info.linkname = kind, "/etc" if kind == tarfile.SYMTYPE else ""
        archive.addfile(info)
        archive.addfile(tarfile.TarInfo("MANIFEST.json"), io.BytesIO(b""))
    code, out, err = cli("results", "verify", packed, "--data-dir", shared_data)
    assert code == 1 and refusal in out + err and "Traceback" not in out + err, out + err


def test_folder_entries_count_against_the_member_bound(cli, shared_data, tmp_path, monkeypatch):
    """Ignored, but read: a flood of empty folders is bounded like a flood of files."""
    from vprbench.bundles import archive

    monkeypatch.setattr(archive, "MAX_MEMBERS", 3)
    packed = tmp_path / "packed.tgz"
    with tarfile.open(packed, "w:gz") as archive:
        for i in range(5):
            info = tarfile.TarInfo(f"{i:016x}")
            info.type = tarfile.DIRTYPE
            archive.addfile(info)
    code, out, err = cli("results", "verify", packed, "--data-dir", shared_data)
    assert code == 1 and "packed.tgz: more than 3 members." in out + err, out + err


# ---------------------------------------------------------------- a dataset.toml nested too deeply
@pytest.mark.parametrize("value", ["[" * 5000 + "]" * 5000, "{a = " * 5000 + "}" * 5000])
def test_a_dataset_toml_nested_too_deeply_is_one_line(cli, tmp_path, value):
    own = tmp_path / "own"
    (own / "database").mkdir(parents=True)
    (own / "dataset.toml").write_text(f"title = {value}\n")
    for command in (("datasets", "verify", own), ("evaluate", "--method", "hog", "--dataset", own)):
        code, out, err = cli(*command)
        assert code == 1 and "Traceback" not in out + err, out + err
        assert f"{own / 'dataset.toml'} nests arrays or tables too deeply to be read; check its brackets." in out + err


@pytest.mark.parametrize("error", [MemoryError(), RuntimeError(
    "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to allocate "
    "9000000000000 bytes. Error code 12 (Cannot allocate memory)")])
def test_running_out_of_memory_is_one_line_saying_what_to_lower(monkeypatch, cli, shared_data, tmp_path, error):
    """Before: a traceback (an option within every bound can still need more memory than the machine has)."""
    from vprbench.methods.hog import HOG

    def describe(self, images):
        raise error

    monkeypatch.setattr(HOG, "describe", describe)
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
                       "--cache-dir", tmp_path / "cache")
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("error: Out of memory (") and "Lower --batch-size" in err and "Traceback" not in err, err


@pytest.mark.parametrize("command", [["run", "plan.toml"], ["reproduce", "anyloc", "--table", "1", "--dry-run"]])
def test_plans_under_torchrun_are_refused_saying_both_ways(monkeypatch, cli, tmp_path, command):
    """Before: each rank ran cells of its own as an independent sweep, each printing its table."""
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    code, out, err = cli(*command, "--cache-dir", tmp_path / "cache")
    assert code == 1 and out == "" and len(err.strip().splitlines()) == 1, err
    assert f"'vprbench {command[0]}' runs under torchrun as independent copies, not sharded" in err
    assert not (tmp_path / "cache").exists()
