"""Untrusted files never run code: a hostile pickle (or any other content) in every kind of
file vprbench reads is refused with a message naming the file, exit 1, and the payload,
which would create a marker file, never runs.

Files read, and how each is protected (the audit):
- ground truth and poses .npy (VPR-Bench rows, positive lists, pose tables): datasets/layouts/npy.py,
  an unpickler that knows only numpy's array/dtype/scalar reconstruction;
- vocabularies (.pt, the authors' c_centers.pt) and weights: torch.load(weights_only=True) in
  vprbench/weights.py; vocabulary .npy: the same npy.py reader;
- .mat (scipy.io.loadmat), .camera (text), CSV (pandas), TOML (tomllib), datasets.json (json),
  HDF5 stores (h5py): parsers that build plain data, never objects; images: Pillow restricted
  to the image formats vprbench lists (no PostScript via Ghostscript).
"""
from __future__ import annotations

import glob
import os
import pickle
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.io import savemat

from vprbench.datasets import load_dataset
from vprbench.datasets.layouts.npy import read_npy
from vprbench.evaluation.results import results_dir
from vprbench.paths import cache_root

from hostile_files import Payload, assert_refused, gadget_pickles, npy_with_pickle, rows_with_payload, tiny_images

GADGETS = list(gadget_pickles(Path("marker")))  # their names


def test_gadgets_are_real(marker):
    """Each pickle of the corpus does run its payload when unpickled without restriction."""
    for name, data in gadget_pickles(marker).items():
        pickle.loads(data)
        assert marker.exists(), name
        marker.unlink()
    np.save(marker.parent / "rows.npy", rows_with_payload(marker), allow_pickle=True)
    np.load(marker.parent / "rows.npy", allow_pickle=True)
    assert marker.exists()


def test_real_ground_truth_files_load_exactly_as_numpy_loads_them(shared_data):
    """Every .npy in ../shared/data (object-array row files, numeric lists, image-name lists): same values."""
    files = sorted(glob.glob(str(shared_data / "**" / "*.npy"), recursive=True))
    assert len(files) == 27  # corridor, 12 VPR-Bench lists, 14 VLAD-BuFF files
    for path in files:
        ours, numpy_s = read_npy(path, "ground truth", "rows"), np.load(path, allow_pickle=True)
        assert ours.shape == numpy_s.shape and ours.dtype == numpy_s.dtype, path
        for a, b in zip(ours.ravel(), numpy_s.ravel()):
            assert np.array_equal(np.asarray(a), np.asarray(b)), path
    corridor = load_dataset("corridor", shared_data)
    rows = np.load(shared_data / "corridor" / "ground_truth_new.npy", allow_pickle=True)
    assert [p.tolist() for p in corridor.positives] == [sorted(r[1]) for r in rows]
    assert sum(len(p) for p in corridor.positives) == 549


# ---------------------------------------------------------------- .npy ground truth and poses
def vpr_bench_gt(tmp_path, shared_data, request):
    corridor = request.getfixturevalue("corridor_copy")
    return corridor / "ground_truth_new.npy", ["evaluate", "--method", "hog", "--resize", 64, 64, "--dataset",
                                               "corridor", "--data-dir", corridor.parent]


def gardens_gt(tmp_path, shared_data, request):
    root = tmp_path / "gardens-data" / "gardens"
    tiny_images(root / "day_right", ["Image000.jpg", "Image001.jpg", "Image002.jpg"])
    tiny_images(root / "night_right", ["Image000.jpg", "Image001.jpg", "Image002.jpg"])
    return root / "gardens_gt.npy", ["datasets", "info", "gardens-point", "--data-dir", root.parent]


def hawkins_poses(tmp_path, shared_data, request):
    root = tmp_path / "hawkins-data" / "hawkins_long_corridor"
    tiny_images(root / "db_images", [f"{i}.png" for i in range(3)])
    tiny_images(root / "q_images", [f"{i}.png" for i in range(3)])
    return root / "pose_topic_list.npy", ["datasets", "info", "hawkins", "--data-dir", root.parent]


def vocabulary_npy(tmp_path, shared_data, request):
    return tmp_path / "centres.npy", ["evaluate", "--method", "anyloc", "--backbone", "dinov2_vits14", "--layer", 3,
                                      "--vocabulary", tmp_path / "centres.npy", "--dataset", "corridor",
                                      "--data-dir", shared_data]


NPY_READERS = {"vpr-bench-ground-truth": vpr_bench_gt, "positive-lists": gardens_gt, "pose-rows": hawkins_poses,
               "vocabulary-npy": vocabulary_npy}


@pytest.mark.parametrize("gadget", [*GADGETS, "payload-inside-real-rows"])
@pytest.mark.parametrize("reader", list(NPY_READERS))
def test_hostile_npy_is_refused(reader, gadget, tmp_path, shared_data, request, marker, cli):
    path, command = NPY_READERS[reader](tmp_path, shared_data, request)
    path.unlink(missing_ok=True)
    if gadget == "payload-inside-real-rows":
        np.save(path, rows_with_payload(marker), allow_pickle=True)
    else:
        npy_with_pickle(path, gadget_pickles(marker)[gadget])
    code, _, err = cli(*command)
    assert_refused(code, err, marker, f"{path}:")


@pytest.mark.parametrize("content, reason", [
    (b"not a numpy file", "not a .npy file"),
    ("truncated", "Expected rows [query_index, [positive reference indices]]"),
    ("dicts", "entry [0, 1] is a dict"),
    ("nested-lists", "entry [0, 1] is a list, not a number"),
    ("short-numbers", "it is truncated"),
])
def test_damaged_ground_truth_is_named(content, reason, corridor_copy, shared_data, cli):
    path = corridor_copy / "ground_truth_new.npy"
    path.unlink()
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "truncated":  # a real VPR-Bench row file cut short
        path.write_bytes((shared_data / "corridor" / "ground_truth_new.npy").read_bytes()[:-40])
    elif content in ("dicts", "nested-lists"):
        rows = np.empty((111, 2), dtype=object)
        for i in range(111):
            rows[i] = i, ({"positives": [i]} if content == "dicts" else [[i]])
        np.save(path, rows, allow_pickle=True)
    else:
        np.save(path, np.arange(111 * 2).reshape(111, 2))
        path.write_bytes(path.read_bytes()[:-100])
    code, _, err = cli("datasets", "info", "corridor", "--data-dir", corridor_copy.parent)
    assert_refused(code, err, None, f"Cannot read ground truth {path}", reason)


# ---------------------------------------------------------------- torch files: vocabularies and weights
def write_torch(path, form: str, marker) -> None:
    payload = Payload(os.system, f"touch {marker}")
    obj = payload if form.endswith("top-level") else {"centres": torch.zeros(2, 384), "state_dict": {"x": payload}}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(obj, path, _use_new_zipfile_serialization=form.startswith("zip"))


def vocabulary_file(tmp_path, shared_data):
    path = tmp_path / "vocabulary.pt"
    return path, ["evaluate", "--method", "anyloc", "--backbone", "dinov2_vits14", "--layer", 3, "--vocabulary", path,
                  "--dataset", "corridor", "--data-dir", shared_data]


def released_centres(tmp_path, shared_data):
    path = tmp_path / "indoor" / "c_centers.pt"
    return path, ["evaluate", "--method", "anyloc", "--backbone", "dinov2_vits14", "--layer", 3,
                  "--vocabulary", path.parent, "--dataset", "corridor", "--data-dir", shared_data]


def anyloc_weights(tmp_path, shared_data):
    path = tmp_path / "dinov2_vits14_pretrain.pth"
    return path, ["evaluate", "--method", "anyloc", "--backbone", "dinov2_vits14", "--layer", 3, "--aggregation", "gem",
                  "--weights", path, "--dataset", "corridor", "--data-dir", shared_data]


def baseline_weights(tmp_path, shared_data):
    path = tmp_path / "ResNet101_2048_cosplace.pth"
    return path, ["evaluate", "--method", "cosplace", "--weights", path, "--dataset", "corridor", "--data-dir", shared_data]


TORCH_READERS = {"vocabulary-pt": vocabulary_file, "released-c_centers": released_centres,
                 "anyloc-weights": anyloc_weights, "baseline-weights": baseline_weights}


@pytest.mark.parametrize("form", ["zip-top-level", "zip-nested", "legacy-top-level", "legacy-nested"])
@pytest.mark.parametrize("reader", list(TORCH_READERS))
def test_hostile_torch_file_is_refused(reader, form, tmp_path, shared_data, marker, cli):
    path, command = TORCH_READERS[reader](tmp_path, shared_data)
    write_torch(path, form, marker)
    code, _, err = cli(*command)
    assert_refused(code, err, marker, str(path))


# ---------------------------------------------------------------- text, MATLAB, HDF5 and image files
def hostile_bytes(marker) -> bytes:
    return gadget_pickles(marker)["reduce-system-protocol2"]


def test_hostile_csv_ground_truth(tmp_path, marker, cli):
    root = tmp_path / "d" / "test_40_midref_rot0"
    tiny_images(root / "reference_images", ["0.png", "1.png"])
    tiny_images(root / "query_images", ["0.png"])
    for name in ("reference.csv", "query.csv"):
        (root / name).write_text("")
    (root / "gt_matches.csv").write_bytes(hostile_bytes(marker))
    code, _, err = cli("datasets", "info", "nardo-air", "--data-dir", root.parent)
    assert_refused(code, err, marker, f"Cannot read ground truth {root / 'gt_matches.csv'}")


def test_hostile_camera_pose_file(tmp_path, marker, cli):
    root = tmp_path / "d" / "baidu_datasets"
    tiny_images(root / "training_images_undistort", ["a.jpg"])
    tiny_images(root / "query_images_undistort", ["b.jpg"])
    (root / "training_gt").mkdir()
    (root / "query_gt").mkdir()
    (root / "training_gt" / "a.camera").write_bytes(hostile_bytes(marker))
    (root / "query_gt" / "b.camera").write_text("0\n" * 7 + "1 2 3\n0\n")
    code, _, err = cli("datasets", "info", "baidu-mall", "--data-dir", root.parent)
    assert_refused(code, err, marker, f"Cannot read camera pose {root / 'training_gt' / 'a.camera'}")


@pytest.mark.parametrize("form", ["pickle", "object-in-struct"])
def test_hostile_mat_file(form, tmp_path, marker, cli):
    root = tmp_path / "d" / "Oxford_Robotcar"
    tiny_images(root / "oxDataPart", ["a.png"])
    if form == "pickle":
        (root / "oxdatapart.mat").write_bytes(hostile_bytes(marker))
    else:  # a MATLAB struct whose fields hold pickled bytes and text: data, never run
        savemat(root / "oxdatapart.mat", {"dbStruct": {"dbImageFns": np.frombuffer(hostile_bytes(marker), np.uint8),
                                                       "utmDb": "os.system"}})
    code, _, err = cli("datasets", "info", "oxford", "--data-dir", root.parent)
    assert_refused(code, err, marker, f"Cannot read {root / 'oxdatapart.mat'}")


@pytest.mark.parametrize("name", ["positions.csv", "dataset.toml"])
def test_hostile_own_data_files(name, tmp_path, marker, cli):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["@0@0@.jpg"])
    tiny_images(root / "queries", ["@5@0@.jpg"])
    (root / name).write_bytes(hostile_bytes(marker))
    code, _, err = cli("datasets", "info", root)
    assert_refused(code, err, marker, f"Cannot read {root / name}")


def test_hostile_dataset_registry(tmp_path, marker, cli):
    (tmp_path / "datasets.json").write_bytes(hostile_bytes(marker))
    code, _, err = cli("datasets", "list", "--data-dir", tmp_path)
    assert_refused(code, err, marker, f"Cannot read the dataset registry {tmp_path / 'datasets.json'}")


def test_pickle_named_as_an_image(corridor_copy, marker, cli):
    image = corridor_copy / "query" / "0000007.jpg"
    image.unlink()
    image.write_bytes(hostile_bytes(marker))
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", corridor_copy.parent)
    assert_refused(code, err, marker, f"Cannot read image {image}", stores_allowed=True)


EPS = b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 8 8\nshowpage\n"


@pytest.fixture
def fake_ghostscript(tmp_path, marker, monkeypatch):
    """A `gs` first on PATH that creates the marker: Pillow runs gs to decode PostScript."""
    folder = tmp_path / "bin"
    folder.mkdir()
    (folder / "gs").write_text(f"#!/bin/sh\ntouch {marker}\nexit 1\n")
    (folder / "gs").chmod(0o755)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")
    return folder


def test_postscript_named_as_an_image_never_reaches_ghostscript(fake_ghostscript, corridor_copy, marker, cli, tmp_path):
    probe = tmp_path / "probe.jpg"
    probe.write_bytes(EPS)
    # without the format restriction Pillow opens it as EPS and runs gs (in a fresh process: Pillow caches gs's path)
    subprocess.run([sys.executable, "-c", f"from PIL import Image\ntry:\n Image.open({str(probe)!r}).load()\nexcept Exception:\n pass"],
                   env=os.environ.copy(), check=True)
    assert marker.exists(), "the probe shows Pillow would run Ghostscript"
    marker.unlink()
    image = corridor_copy / "ref" / "0000003.jpg"
    image.unlink()
    image.write_bytes(EPS)
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", corridor_copy.parent)
    assert_refused(code, err, marker, f"Cannot read image {image}: it is not a JPEG, PNG")


def test_hostile_file_in_place_of_a_descriptor_store(corridor_copy, marker, cli):
    command = ["evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", corridor_copy.parent]
    assert cli(*command)[0] == 0
    shutil.rmtree(results_dir())
    store = next(cache_root().rglob("database.h5"))
    store.write_bytes(hostile_bytes(marker))
    with pytest.warns(UserWarning, match=rf"Discarding {re.escape(str(store))}: it cannot be read .* it is recomputed"):
        code, _, err = cli(*command)
    # a store that cannot be read is named and recomputed; never trusted, never run
    assert not marker.exists() and "Traceback" not in err and code == 0, err
