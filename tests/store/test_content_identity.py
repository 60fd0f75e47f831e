"""A store holds descriptors of exactly the bytes its key names: an image that changes while it
is read, or between runs (even keeping its size and restoring its mtime), never ends in, or is
served from, a store keyed by the original bytes."""
from __future__ import annotations

import os
import shutil

import pytest

import vprbench.loader as loader
from vprbench.cli.main import main
from vprbench.evaluation import read_results

HOG = ["--method", "hog", "--resize", "32", "32", "--dataset", "corridor", "--k", "1", "5"]


@pytest.fixture
def corridor_copy(shared_data, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(shared_data / "corridor", root / "corridor")
    return root


def evaluate(capsys, data, cache) -> tuple[int, str, str]:
    code = main(["evaluate", *HOG, "--data-dir", str(data), "--cache-dir", str(cache), "--json"])
    out, err = capsys.readouterr()
    return code, out, err


def recall(cache) -> dict:
    return read_results(cache)[-1]["recall"]


def rewrite_during_the_run(patch, victim, replacement, when=None):
    """Right after image `when` (default: `victim` itself) is decoded, another program (a sync
    tool) rewrites `victim`."""
    from vprbench.methods.hog import HOG as Hog

    decode = Hog.load

    def load(self, path):
        item = decode(self, path)
        if path == (when or victim):
            victim.write_bytes(replacement)
        return item

    patch.setattr(Hog, "load", load)


def test_an_image_changed_while_read_never_completes_a_store(corridor_copy, tmp_path, capsys, monkeypatch):
    clean_cache = tmp_path / "clean"
    assert evaluate(capsys, corridor_copy, clean_cache)[0] == 0
    clean = recall(clean_cache)
    queries = sorted((corridor_copy / "corridor" / "query").glob("*.jpg"))
    victim, other = queries[7], queries[90]
    original_bytes = victim.read_bytes()

    # the attack is real: unchecked, the run completes a store whose key says "the original images"
    with monkeypatch.context() as patch:
        unchecked = loader._Images.__init__
        patch.setattr(loader._Images, "__init__", lambda self, method, paths, digests=None: unchecked(self, method, paths))
        rewrite_during_the_run(patch, victim, other.read_bytes(), when=queries[2])
        assert evaluate(capsys, corridor_copy, tmp_path / "attacked")[0] == 0
    victim.write_bytes(original_bytes)  # a byte-identical copy of the dataset again
    code, out, _ = evaluate(capsys, corridor_copy, tmp_path / "attacked")
    served = read_results(tmp_path / "attacked")[-1]
    assert served["descriptors_computed"] == {"database": 0, "queries": 0}, "served from the poisoned store"
    poisoned_rows = served["top_predictions"][7] != read_results(clean_cache)[-1]["top_predictions"][7]
    assert poisoned_rows or served["recall"] != clean, "the changed image really changed what the store holds"

    # checked: an image changed since its identity was taken stops the run, naming it; no store
    # completes; a later run is right
    with monkeypatch.context() as patch:
        rewrite_during_the_run(patch, victim, other.read_bytes(), when=queries[2])
        code, _, err = evaluate(capsys, corridor_copy, tmp_path / "checked")
    assert code == 1 and f"Image {victim} changed since its identity was taken" in err and "Traceback" not in err, err
    assert not list((tmp_path / "checked" / "stores").rglob("queries.h5")), "no complete store"
    victim.write_bytes(original_bytes)
    assert evaluate(capsys, corridor_copy, tmp_path / "checked")[0] == 0
    assert recall(tmp_path / "checked") == clean

    # rewritten right after it was decoded: the row describes the very bytes decoded, which are
    # the ones the key names, so the store is right (and the next run sees the new bytes)
    with monkeypatch.context() as patch:
        rewrite_during_the_run(patch, victim, other.read_bytes())
        assert evaluate(capsys, corridor_copy, tmp_path / "after")[0] == 0
    after = read_results(tmp_path / "after")[-1]
    assert after["recall"] == clean and after["top_predictions"] == read_results(clean_cache)[-1]["top_predictions"]
    assert read_results(tmp_path / "after")[-1]["descriptors_computed"]["queries"] > 0
    victim.write_bytes(original_bytes)


def test_a_method_reading_files_itself_is_checked_around_its_load(corridor_copy, tmp_path, capsys, monkeypatch):
    """A plugin whose `load` opens files without vprbench.images: each image is hashed just before
    and just after that load, so a change while it reads is still caught."""
    import numpy as np
    from PIL import Image

    from vprbench.methods.hog import HOG as Hog

    queries = sorted((corridor_copy / "corridor" / "query").glob("*.jpg"))
    victim, other = queries[7], queries[90]
    original_bytes, replacement = victim.read_bytes(), other.read_bytes()

    def own_reader(self, path):
        with Image.open(path) as image:  # not vprbench.images.load_image
            pixels = np.ascontiguousarray(np.asarray(image.convert("RGB").resize(self.size))[:, :, ::-1])
        if path == victim and victim.read_bytes() == original_bytes:
            victim.write_bytes(replacement)  # changed while this load reads it
        return pixels

    monkeypatch.setattr(Hog, "load", own_reader)
    code, _, err = evaluate(capsys, corridor_copy, tmp_path / "cache")
    assert code == 1 and f"Image {victim} changed " in err and "Traceback" not in err, err
    assert not list((tmp_path / "cache" / "stores").rglob("queries.h5")), "no complete store"
    victim.write_bytes(original_bytes)


def test_a_same_size_edit_with_its_mtime_restored_is_seen(corridor_copy, tmp_path, capsys):
    cache = tmp_path / "cache"
    assert evaluate(capsys, corridor_copy, cache)[0] == 0
    image = corridor_copy / "corridor" / "query" / "0000003.jpg"
    stat = image.stat()
    data = image.read_bytes()
    # another frame, padded after its end marker to the same size (decoders stop at the marker)
    other = next(p for p in sorted((corridor_copy / "corridor" / "ref").glob("*.jpg"))[60:] if p.stat().st_size < len(data))
    replacement = other.read_bytes().ljust(len(data), b"\0")
    assert replacement != data and len(replacement) == len(data)
    image.write_bytes(replacement)  # same size, other bytes
    os.utime(image, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # the mtime set back
    assert image.stat().st_size == stat.st_size and image.stat().st_mtime_ns == stat.st_mtime_ns
    assert evaluate(capsys, corridor_copy, cache)[0] == 0
    first, again = read_results(cache)
    assert again["descriptors_computed"]["queries"] == 111, "not served from the store of the old bytes"
    assert again["dataset_fingerprint"] != first["dataset_fingerprint"]
