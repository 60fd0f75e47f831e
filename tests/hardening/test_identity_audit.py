"""One run, one identity: what cannot change a run's numbers (a default written out) leaves its
spec and store keys alone; what can (a vocabulary folder's images, the bytes of a dataset copy)
keeps a stored result from being served for it."""
from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.methods import create_method
from vprbench.spec import resolve_spec
from vprbench.store import method_fingerprint


@pytest.mark.parametrize("method, shorter, written", [
    ("hog", {"resize": [64, 64]}, {"resize": [64, 64], "cell": 16, "bins": 9.0}),
    ("sad", {}, {"resize": "32x64", "patch": 8}),  # sad's own defaults, a tuple among them
])
def test_a_default_written_out_is_the_same_run_and_store(method, shorter, written):
    """`--method sad -o patch=8` was a run (and a descriptor store) of its own, computed again."""
    spec, same = resolve_spec(method, "corridor", options=shorter), resolve_spec(method, "corridor", options=written)
    assert (same.key, same.row_key, same.given, same.label()) == (spec.key, spec.row_key, spec.given, spec.label())
    assert method_fingerprint(create_method(method, **written)) == method_fingerprint(create_method(method, **shorter))
    other = resolve_spec(method, "corridor", options={**shorter, "patch" if method == "sad" else "cell": 4})
    assert other.key != spec.key


def test_a_list_written_as_text_is_that_list():
    """`-o bin_sizes=4,6,8,10` (text from the command line) is dense-vlad's default list, and '4,6,8' the
    list [4, 6, 8] written in a plan: one run each, not two."""
    def spec(**options):
        return resolve_spec("dense-vlad", "corridor", options=options)

    assert spec(bin_sizes="4,6,8,10").key == spec().key and spec(bin_sizes="4,6,8,10").label() == "dense-vlad"
    assert spec(bin_sizes="4, 6,8").key == spec(bin_sizes=[4, 6, 8]).key != spec().key
    assert spec(bin_sizes="4,6,8").given == {"bin_sizes": [4, 6, 8]}


def test_a_search_default_written_out_is_the_same_run():
    exact_default = resolve_spec("hog", "corridor", search={"index": "hnsw"})
    written = resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {"hnsw_m": 32, "seed": 0,
                                                                                  "ef_construction": 40}})
    assert written.key == exact_default.key and written.search.options == {}
    assert resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {"hnsw_m": 16}}).key != written.key
    # the shortlist's default depends on the database: written out, it stays
    assert resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {"shortlist": 100}}).key != written.key


def test_a_vocabulary_folder_is_known_by_its_images_not_its_path(shared_data, tmp_path):
    """A folder vocabulary was named by its path: images changed in it, a sweep served the old result."""
    first, moved = tmp_path / "words", tmp_path / "elsewhere" / "words"
    first.mkdir()
    for i in range(3):
        shutil.copyfile(shared_data / "corridor" / "ref" / f"{i:07d}.jpg", first / f"{i:07d}.jpg")
    shutil.copytree(first, moved)

    def row(folder):
        return resolve_spec("dense-vlad", "corridor", options={"vocabulary": str(folder)}, cache_dir=tmp_path).row_key

    before = row(first)
    assert row(moved) == before  # the same images elsewhere: the same row
    shutil.copyfile(shared_data / "corridor" / "ref" / "0000050.jpg", first / "0000001.jpg")
    edited = row(first)
    assert edited != before
    (first / ".DS_Store").write_bytes(b"x")  # a hidden file is none of its images
    assert row(first) == edited


def _edit_image(root):
    path = root / "query" / "0000005.jpg"
    data = path.read_bytes()
    path.unlink()  # a symlink into the shared data: replaced, never written through
    import cv2

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    cv2.imwrite(str(path), 255 - image)


def _edit_ground_truth(root):
    path = root / "ground_truth_new.npy"
    truth = np.load(path, allow_pickle=True)
    path.unlink()
    truth[0, 1] = [0]
    np.save(path, truth, allow_pickle=True)


@pytest.mark.parametrize("edit", [_edit_image, _edit_ground_truth])
def test_a_sweep_does_not_serve_a_result_computed_on_other_data(corridor_copy, shared_data, tmp_path, capsys,
                                                                 monkeypatch, edit):
    """A benchmark's spec names its protocol, not the bytes of the copy: `vprbench run` skipped a
    cell as complete whose record was computed on another copy's images or ground truth."""
    monkeypatch.setenv("COLUMNS", "200")
    plan = tmp_path / "plan.toml"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')
    cache = tmp_path / "cache"

    def run(data_root) -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", "1", "--quiet", "--data-dir", data_root, "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)

    [original] = run(shared_data)
    edit(corridor_copy)
    records = run(corridor_copy.parent)
    assert len(records) == 2, "the cell was skipped: a result of other data was served"
    assert records[-1]["dataset_fingerprint"] != original["dataset_fingerprint"]
    assert len(run(corridor_copy.parent)) == 2  # the copy's own result is found again
    assert len(run(shared_data)) == 2  # and the original's


def test_a_file_a_plugin_preset_names_is_known_by_its_bytes(tmp_path, scratch_methods):
    """A preset's file (and a file given equal to it) was named by its path: edited in place, the
    run kept its key and a sweep served the result of the old bytes."""
    from vprbench import register_method
    from vprbench.methods.base import Method

    class Toy(Method):
        def __init__(self, weights: str = "", device: str = "cpu"):
            self.weights = weights

        def describe(self, images):
            return np.ones((len(images), 4), np.float32)

    weights = tmp_path / "w.npy"
    np.save(weights, np.ones(4))
    register_method("toy-identity", Toy, defaults={"weights": str(weights)})
    before = [resolve_spec("toy-identity", "corridor", options=o).key for o in ({}, {"weights": str(weights)})]
    np.save(weights, np.zeros(4))
    after = [resolve_spec("toy-identity", "corridor", options=o).key for o in ({}, {"weights": str(weights)})]
    assert before[0] == before[1] and after[0] == after[1] and after[0] != before[0]


def test_reproduce_still_sees_the_vocabulary_a_default_aggregation_needs(tmp_path):
    """A default left out of the spec (aggregation = "vlad" written out) must still count as set."""
    from vprbench.sweep.plan import Cell
    from vprbench.sweep.needs import vocabulary_for

    options = {"backbone": "dino_vits8", "layer": 9, "facet": "key", "clusters": 128, "vocabulary": "aerial"}
    for given in (options, {**options, "aggregation": "vlad"}):
        spec = resolve_spec("anyloc", "nardo-air", options=given)
        assert "aggregation" not in spec.options
        assert vocabulary_for(Cell(spec), tmp_path)[0] == "vocabulary 'aerial' for dino_vits8 layer 9 key c128"


def test_a_method_created_in_python_keys_its_store_as_the_command_line_does():
    """`create_method("hog", resize="64x64")` keyed its store by the text '64x64', `--resize 64 64`
    by [64, 64]: the same descriptors were computed twice, in two stores."""
    from vprbench.hashing import canonical_hash

    keys = {canonical_hash(method_fingerprint(create_method("hog", resize=written)))
            for written in ("64x64", [64, 64], (64.0, 64), "64")}
    assert len(keys) == 1


def test_a_reproduce_dry_run_does_not_call_complete_a_cell_of_other_data(corridor_copy, shared_data, tmp_path, capsys):
    """The dry run judged a cell complete by its spec alone: one computed on another copy read complete
    while the run itself would compute it again."""
    from vprbench.cli.reproduce import dry_run_listing
    from vprbench.run_settings import RunSettings
    from vprbench.sweep.plan import Cell
    from vprbench.sweep.reproduce import TableCell
    from vprbench.evaluation import evaluate, save_result
    from rich.console import Console

    cache = tmp_path / "cache"
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=[1], data_dir=shared_data)
    save_result(evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=cache)), cache)
    _edit_image(corridor_copy)

    def status(data_root) -> str:
        table = dry_run_listing({"title": "t"}, [TableCell("hog", "corridor", [Cell(spec)])], {spec.key: []},
                                RunSettings(data_dir=data_root, cache_dir=cache), "1 cell")
        console = Console(width=200, record=True)
        console.print(table)
        return console.export_text()

    assert "complete" in status(shared_data)
    assert "complete" not in status(corridor_copy.parent) and "would run" in status(corridor_copy.parent)


def test_a_sweep_hashes_the_data_before_a_claim_not_under_its_lock(shared_data, tmp_path, monkeypatch):
    """The claim's lock is held for moments (120 s timeout): a first look at a large copy hashed it
    there, so other processes found the cell "busy" meanwhile."""
    import vprbench.sweep.claims as claims_module
    from vprbench.run_settings import RunSettings
    from vprbench.sweep.plan import Cell
    from vprbench.sweep.runner import StoredRecords, run_cells

    held, hashed_under_lock = [], []
    real_lock, real_fingerprint = claims_module._lock, StoredRecords.fingerprint

    class Spy:
        def __init__(self, path):
            self.inner = real_lock(path)

        def __enter__(self):
            held.append(1)
            return self.inner.__enter__()

        def __exit__(self, *exc):
            held.pop()
            return self.inner.__exit__(*exc)

    def fingerprint(self, spec):
        hashed_under_lock.append(bool(held) and spec.dataset.model_dump_json() not in self.fingerprints)
        return real_fingerprint(self, spec)

    monkeypatch.setattr(claims_module, "_lock", Spy)
    monkeypatch.setattr(StoredRecords, "fingerprint", fingerprint)
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=[1], data_dir=shared_data)
    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path / "cache")
    for _ in range(2):  # computed, then found complete
        run_cells([Cell(spec)], settings)
    assert hashed_under_lock and not any(hashed_under_lock)


@pytest.mark.parametrize("method, options, idle", [
    ("anyloc-gem-dinov2", {"clusters": 4}, "clusters=4 is not used here (only VLAD uses it, the aggregation is gem)"),
    ("anyloc-gem-dinov2", {"vocabulary": "urban"}, "vocabulary='urban' is not used here (only VLAD uses it"),
    ("anyloc-vlad-dinov2", {"gem_p": 4}, "gem_p=4 is not used here (only GeM uses it, the aggregation is vlad)"),
])
def test_an_option_the_aggregation_ignores_is_refused_not_named_in_the_row(method, options, idle):
    """Was: accepted, computed without it, and named in the row ('anyloc-gem-dinov2 [clusters=4]', a second
    row of the same numbers)."""
    from vprbench.errors import VPRBenchError

    for make in (lambda: resolve_spec(method, "corridor", options=options), lambda: create_method(method, **options)):
        with pytest.raises(VPRBenchError, match=re.escape(f"Method {method!r}: option {idle}")):
            make()
    assert resolve_spec("anyloc-gem-dinov2", "corridor", options={"clusters": 32}).label() == "anyloc-gem-dinov2"
    gem = resolve_spec("anyloc-vlad-dinov2", "corridor", options={"aggregation": "gem", "gem_p": 4})
    assert gem.given == {"aggregation": "gem", "gem_p": 4}


def test_every_part_of_what_a_run_computes_is_in_its_keys():
    base = resolve_spec("hog", "corridor", ks=[1, 5])
    # a float16 store and an approximate index change the numbers: another run and another row
    for other in (resolve_spec("hog", "corridor", ks=[1, 5], store_dtype="float16"),
                  resolve_spec("hog", "corridor", ks=[1, 5], search={"index": "hnsw"})):
        assert other.key != base.key and other.row_key != base.row_key
    # other K values: another run (its record holds other recalls), the same leaderboard row
    more = resolve_spec("hog", "corridor", ks=[1, 5, 10])
    assert more.key != base.key and more.row_key == base.row_key
    # another protocol under the same name (own folders: positions or radius edited): another run, the same row
    edited = base.model_copy(update={"dataset": base.dataset.model_copy(update={"protocol_hash": "0" * 16})})
    assert edited.dataset.protocol == base.dataset.protocol
    assert edited.key != base.key and edited.row_key == base.row_key


def test_a_folders_identity_skips_hidden_files_below_it_only(tmp_path):
    """Hidden means hidden inside the folder (a .git/ beside the images); a folder that itself lies
    under a hidden one (~/.cache/words) still has its files counted."""
    from vprbench.content_identity import folder_identity

    words = tmp_path / ".cache" / "words"
    (words / ".git").mkdir(parents=True)
    (words / "a.jpg").write_bytes(b"a")
    (words / "b.jpg").write_bytes(b"b")
    before = folder_identity(str(words))
    (words / ".git" / "index").write_bytes(b"changed")
    assert folder_identity(str(words)) == before
    (words / "b.jpg").write_bytes(b"B")
    assert folder_identity(str(words)) != before


def test_a_folders_identity_does_not_depend_on_the_order_files_are_listed(tmp_path, monkeypatch):
    """Directory listings come in the file system's order (by hash, by creation): the files are hashed by name."""
    from pathlib import Path

    from vprbench.content_identity import folder_identity

    words = tmp_path / "words"
    words.mkdir()
    for i in range(12):
        (words / f"{i:03d}.jpg").write_bytes(bytes([i]))
    listed = folder_identity(str(words))
    rglob = Path.rglob
    monkeypatch.setattr(Path, "rglob", lambda self, pattern: reversed(sorted(rglob(self, pattern))))
    assert folder_identity(str(words)) == listed
    monkeypatch.setattr(Path, "rglob", lambda self, pattern: iter(sorted(rglob(self, pattern))))
    assert folder_identity(str(words)) == listed
