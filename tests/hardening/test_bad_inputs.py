"""Bad input of every other kind: method options, images, own-data files, vocabularies and
names with markup. Each bad input gets one clear message naming what is at fault, exit 1,
no traceback and nothing stored; inputs that are odd but valid work as they should."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from vprbench import Method, VPRBenchError, create_method, register_method
from vprbench.images import load_rgb
from vprbench.methods import registry
from vprbench.methods.checks import whole, wholes

from hostile_files import assert_refused, tiny_images

# ---------------------------------------------------------------- method options (checked at creation)
HOG, DENSE, ANYLOC = ["--method", "hog"], ["--method", "dense-vlad"], ["--method", "anyloc", "--backbone", "dinov2_vits14"]
OPTIONS = [
    # hog: OpenCV answers these with SIGFPE (cell 0), SIGSEGV (bins < 4) or an assertion at the first image
    (HOG + ["-o", "cell=0"], "option cell takes a whole number >= 1"),
    (HOG + ["-o", "cell=-8"], "option cell takes a whole number >= 1"),
    (HOG + ["-o", "cell=2.5"], "option cell takes a whole number"),
    (HOG + ["-o", "cell=abc"], "got 'abc'"),
    (HOG + ["-o", "bins=0"], "option bins takes a whole number >= 4"),
    (HOG + ["-o", "bins=3"], "option bins takes a whole number >= 4"),
    (HOG + ["-o", "bins=true"], "option bins takes a whole number >= 4 (orientation bins); got True"),
    (HOG + ["-o", "block=12", "-o", "cell=5"], "option block (12) must be a multiple of cell (5)"),
    (HOG + ["-o", "block_stride=0"], "option block_stride takes a whole number >= 1"),
    (HOG + ["--resize", "60", "64"], "exceed it by a multiple of block_stride (8)"),
    (HOG + ["--resize", "0", "0"], "resize must be positive"),
    (HOG + ["-o", "resize=native"], "option resize takes the size HOG is computed at"),
    # dense-vlad
    (DENSE + ["-o", "bin_sizes=4,x"], "option bin_sizes takes one or more whole numbers >= 1"),
    (DENSE + ["-o", "bin_sizes=0"], "option bin_sizes takes one or more whole numbers >= 1"),
    (DENSE + ["-o", "bin_sizes=4,,6"], "option bin_sizes takes one or more whole numbers"),
    (DENSE + ["-o", "step=0"], "option step takes a whole number >= 1"),
    (DENSE + ["-o", "max_side=-1"], "option max_side takes a whole number >= 40"),
    (DENSE + ["--clusters", "1"], "option clusters takes a whole number >= 2"),
    (DENSE + ["-o", "sample=10"], "option sample takes a whole number >= 128"),
    (DENSE + ["-o", "seed=-1"], "option seed takes a whole number >= 0"),
    # anyloc: all checked before any weights or vocabulary is looked for
    (ANYLOC + ["--aggregation", "gem", "-o", "gem_p=abc"], "option gem_p takes a finite number > 0 (GeM's power, e.g. 3); got 'abc'"),
    (ANYLOC + ["--aggregation", "gem", "-o", "gem_p=nan"], "option gem_p takes a finite number > 0"),
    (ANYLOC + ["--aggregation", "gem", "-o", "gem_p=inf"], "option gem_p takes a finite number > 0"),
    (ANYLOC + ["--aggregation", "gem", "-o", "gem_p=0"], "option gem_p takes a finite number > 0"),
    (ANYLOC + ["--aggregation", "gem", "-o", "gem_p=-2"], "option gem_p takes a finite number > 0"),
    (ANYLOC + ["--layer", "12"], "option layer takes a whole number from 0 to 11 (0-based block of dinov2_vits14); got 12"),
    (ANYLOC + ["--layer", "-1"], "option layer takes a whole number from 0 to 11"),
    (ANYLOC + ["--clusters", "0"], "option clusters takes a whole number >= 1"),
    (ANYLOC + ["-o", "stride=0"], "option stride takes a whole number from 1 to 14"),
    (ANYLOC + ["-o", "stride=15"], "option stride takes a whole number from 1 to 14"),
    (ANYLOC + ["--pca-dim", "0"], "option pca_dim takes a whole number >= 1"),
    (ANYLOC + ["--pca-dim", "-4"], "option pca_dim takes a whole number >= 1"),
    (ANYLOC + ["--facet", "values"], "option facet takes one of query, key, value, token; got 'values'"),
    (ANYLOC + ["--aggregation", "netvlad"], "option aggregation takes one of vlad"),
    (ANYLOC + ["-o", "precision=fp64"], "option precision takes one of fp32, fp16, bf16"),
    (ANYLOC + ["--resize", "0", "10"], "resize must be positive"),
    (ANYLOC + ["-o", "layer_for=dinov2_vitg14:abc"], "option layer_for takes a whole number from 0 to 39"),
    (ANYLOC + ["-o", "vocabulary="], "option vocabulary takes a non-empty text"),
    (["--method", "anyloc", "--backbone", "dinov2_vitz14"], "Unknown backbone 'dinov2_vitz14'"),
    # every method: device and batch size in the registry, before a plugin loads weights
    (ANYLOC + ["--device", "gpu0"], "option device takes a torch device such as cpu, cuda or cuda:1; got 'gpu0'"),
    (["--method", "cosplace", "--device", "cuda"], "no CUDA GPU is available"),
    (HOG + ["--batch-size", "0"], "hog: option batch_size takes a whole number >= 1 (images per batch); got 0"),
    (HOG + ["--batch-size", "-3"], "hog: option batch_size takes a whole number >= 1"),
    (DENSE + ["--batch-size", "0"], "dense-vlad: option batch_size takes a whole number >= 1"),
    (ANYLOC + ["--batch-size", "0"], "anyloc: option batch_size takes a whole number >= 1"),
    (["--method", "cosplace", "--batch-size", "0"], "cosplace: option batch_size takes a whole number >= 1"),
    (HOG + ["-o", "batch_size=abc"], "hog: option batch_size takes a whole number >= 1 (images per batch); got 'abc'"),
    # baselines: checked before the weights are looked for
    (["--method", "netvlad", "-o", "resize=0"], "Option resize must be positive"),
    (["--method", "cosplace", "--resize", "-1", "3"], "Option resize must be positive"),
    (["--method", "mixvpr", "-o", "dim=abc"], "Option dim must be an integer, got 'abc'"),
    (["--method", "netvlad", "-o", "backbone=resnet7"], "unknown backbone 'resnet7'"),
    # approximate search: checked when the run is specified (a 'nan' was once a traceback after every image was described)
    (HOG + ["--index", "ivf-pq", "--index-option", "nlist=nan"], "--index ivf-pq option nlist takes a whole number >= 1; got 'nan'"),
    (HOG + ["--index", "ivf-pq", "--index-option", "nprobe=0"], "--index ivf-pq option nprobe takes a whole number >= 1; got 0"),
    (HOG + ["--index", "hnsw", "--index-option", "ef_search=x"], "--index hnsw option ef_search takes a whole number >= 1"),
    (HOG + ["--index", "hnsw", "--index-option", "seed=-1"], "--index hnsw option seed takes a whole number >= 0; got -1"),
    # a database too small for the index: refused before any descriptor is computed (was: after describing it)
    (HOG + ["--index", "ivf-pq"], "index='ivf-pq' needs at least 9,984 database rows to train its coarse quantizer"),
    (HOG + ["--index", "hnsw", "--index-option", "shortlist=5000"], "A shortlist of 5000 exceeds the"),
    # was: no word of what to do ("Exact search takes no index options; got nprobe.")
    (HOG + ["--index-option", "nprobe=8"], "Exact search takes no index options; got nprobe: drop them, or choose an "
                                           "approximate index (--index ivf-pq or hnsw"),
]


@pytest.mark.parametrize("args, message", OPTIONS, ids=[" ".join(a[1:]) for a, _ in OPTIONS])
def test_bad_method_option_is_refused_at_creation(args, message, shared_data, cli, tmp_path):
    code, _, err = cli("evaluate", *args, "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, message)
    assert not (tmp_path / "torch-home").exists(), "no weights were looked for"


def test_option_forms_from_the_command_line_mean_the_same_value():
    assert whole("m", "x", "8") == whole("m", "x", 8) == whole("m", "x", 8.0) == 8
    assert wholes("m", "x", "4, 6,8") == wholes("m", "x", [4, 6, 8]) == wholes("m", "x", (4, 6, 8)) == (4, 6, 8)
    assert create_method("dense-vlad", bin_sizes=4).bin_sizes == (4,)  # `-o bin_sizes=4` arrives as an int
    assert create_method("hog", cell="8", block=16).fingerprint()["cell"] == 8


def test_settings_are_the_preset_merged_with_the_users_options():
    hog = create_method("hog", cell=8, batch_size=4, device=None)
    assert hog.settings == {"cell": 8} and hog.options == {"cell": 8}  # batch size: a run setting, in no identity
    assert hog.batch_size == 4 and hog.fingerprint()["cell"] == 8  # hog's own parameters are not overwritten
    gem = create_method("anyloc-gem-dinov2", backbone="dinov2_vits14", layer=3)
    assert gem.settings == {"backbone": "dinov2_vits14", "layer_for": "dinov2_vitg14:31", "facet": "value",
                            "aggregation": "gem", "layer": 3}
    assert gem.options == {"backbone": "dinov2_vits14", "layer": 3}


class Plain(Method):
    """A plugin whose factory takes no batch_size."""

    def __init__(self, size: int = 4):
        self.size = size

    def describe(self, images):
        return np.ones((len(images), 2), np.float32) / np.sqrt(2)


class Broken(Plain):
    batch_size = 0


def test_registry_gives_every_method_a_checked_batch_size(scratch_methods):
    register_method("plain", Plain)
    register_method("broken", Broken)
    assert "batch_size" in registry.method_entry("plain").options()
    assert create_method("plain", batch_size="3").batch_size == 3
    assert create_method("plain").batch_size == 16  # the class default
    with pytest.raises(VPRBenchError, match="plain: option batch_size takes a whole number >= 1"):
        create_method("plain", batch_size=0)
    with pytest.raises(VPRBenchError, match=r"Method 'broken' \(.*\) has batch_size 0; it must be a whole number >= 1"):
        create_method("broken")
    assert create_method("broken", batch_size=2).batch_size == 2


def test_vocabulary_of_the_wrong_dimension_is_refused_before_the_model_loads(shared_data, cli, tmp_path):
    centres = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "indoor" / "c_centers.pt"
    code, _, err = cli("evaluate", "--method", "anyloc-vlad-dinov2", "--backbone", "dinov2_vits14", "--layer", 3,
                       "--vocabulary", centres, "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, f"Vocabulary {centres} has 1536-dimensional centres but the features are 384-dimensional")
    assert not (tmp_path / "torch-home").exists(), "no weights were looked for"
    # the right backbone takes it (no weights needed to build the method)
    assert create_method("anyloc-vlad-dinov2", vocabulary=str(centres)).centres.shape == (32, 1536)


# ---------------------------------------------------------------- images: high bit depth scaled, not clipped
GRADIENT = np.linspace(0, 65535, 96 * 128).reshape(96, 128).astype(np.uint16)


@pytest.mark.parametrize("kind", ["png-16-bit-grey", "tiff-16-bit-big-endian", "tiff-float", "png-16-bit-rgb"])
def test_high_bit_depth_images_are_scaled(kind, tmp_path):
    import cv2

    expected = np.rint(GRADIENT * (255 / 65535)).astype(np.uint8)
    path = tmp_path / (kind + (".png" if "png" in kind else ".tif"))
    if kind == "png-16-bit-grey":
        Image.fromarray(GRADIENT).save(path)
    elif kind == "tiff-16-bit-big-endian":
        Image.fromarray(GRADIENT.astype(">u2")).save(path)
    elif kind == "tiff-float":
        Image.fromarray(GRADIENT.astype(np.float32) / 65535, "F").save(path)
    else:
        cv2.imwrite(str(path), np.stack([GRADIENT] * 3, axis=-1))
        expected = GRADIENT >> 8  # Pillow keeps the high bytes of 48-bit PNGs
    with Image.open(path) as image:
        assert image.mode in ("I;16", "I;16B", "I", "F", "RGB"), image.mode
    rgb = load_rgb(path)
    assert rgb.dtype == np.uint8 and rgb.shape == (96, 128, 3)
    np.testing.assert_array_equal(rgb[..., 0], expected)
    assert (rgb == 255).mean() < 0.01  # clipping made 99.6 % of these pixels white


def test_a_16_bit_copy_gives_the_same_descriptor(shared_data, tmp_path):
    original = shared_data / "corridor" / "ref" / "0000010.jpg"
    grey = np.asarray(Image.open(original).convert("L"))
    Image.fromarray(grey.astype(np.uint16) * 257).save(tmp_path / "deep.png")
    Image.fromarray(grey).save(tmp_path / "flat.png")
    hog = create_method("hog", resize=(64, 64))
    np.testing.assert_array_equal(hog.describe([tmp_path / "deep.png"]), hog.describe([tmp_path / "flat.png"]))


# ---------------------------------------------------------------- own data
@pytest.fixture
def own(tmp_path):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["000.jpg", "001.jpg", "002.jpg"])
    tiny_images(root / "queries", ["q0.jpg"])
    return root


IMAGES = ["database/000.jpg", "database/001.jpg", "database/002.jpg", "queries/q0.jpg"]


@pytest.mark.parametrize("repeat", ["database/001.jpg", "./database/001.jpg"])
def test_repeated_image_row_is_refused(own, repeat, cli):
    pd.DataFrame({"image": IMAGES + [repeat], "x": [0, 10, 20, 0, 99], "y": 0}).to_csv(own / "positions.csv", index=False)
    code, _, err = cli("datasets", "info", own)
    assert_refused(code, err, None, f"{own / 'positions.csv'} lists 1 image(s) more than once, e.g. ['database/001.jpg']")


def test_listed_but_absent_images_are_warned_about(own, cli):
    rows = IMAGES + ["database/003.jpg", "queries/gone.jpg"]
    pd.DataFrame({"image": rows, "x": [0, 10, 20, 5, 30, 40], "y": 0}).to_csv(own / "positions.csv", index=False)
    with pytest.warns(UserWarning, match=r"lists 2 image\(s\) that are not in .*database or .*queries, "
                                         r"e.g. \['database/003.jpg', 'queries/gone.jpg'\]; they are left out"):
        code, out, _ = cli("datasets", "info", own, "--json")
    assert code == 0 and json.loads(out)["database"] == 3


def test_frames_report_their_radius_in_frames(own, cli):
    pd.DataFrame({"image": IMAGES, "frame": [0, 1, 2, 1]}).to_csv(own / "positions.csv", index=False)
    (own / "dataset.toml").write_text("radius = 1\n")
    code, out, err = cli("datasets", "info", own, "--json")
    info = json.loads(out)
    assert code == 0, err
    assert (info["unit"], info["radius"], info["radius_unit"], info["positive_pairs"]) == ("frames", 1, "frames", 3)


@pytest.mark.parametrize("toml, message", [
    ('radius = "ten"', "radius must be a number of metres or frames, 0 or more; got 'ten'"),
    ("radius = -1", "got -1"),
    ("radius = true", "got True"),
    ("name = 5", "name must be a non-empty string; got 5"),
    ('name = ""', "name must be a non-empty string"),
    ("title = [1]", "title must be a string; got [1]"),
    ("radius = 1\nradius = 2", "is not valid TOML: Cannot overwrite a value (at line 2, column 11)"),
    ("colour = 'red'", "unknown key(s) ['colour']"),
])
def test_bad_dataset_toml_is_named(own, toml, message, cli):
    pd.DataFrame({"image": IMAGES, "x": [0, 10, 20, 0], "y": 0}).to_csv(own / "positions.csv", index=False)
    (own / "dataset.toml").write_text(toml + "\n")
    code, _, err = cli("datasets", "info", own)
    assert_refused(code, err, None, str(own / "dataset.toml"), message)


# ---------------------------------------------------------------- names keep their brackets (markup off)
def test_names_with_brackets_print_whole(shared_data, cli, monkeypatch, scratch_methods):
    code, _, err = cli("evaluate", "--method", "hog[x]", "--dataset", "corridor", "--data-dir", shared_data)
    assert_refused(code, err, None, "Unknown method 'hog[x]'")

    assert cli("evaluate", "--method", "hog", "-o", "bins=4", "--resize", 64, 64, "--dataset", "corridor",
               "--data-dir", shared_data)[0] == 0
    code, out, _ = cli("leaderboard")
    assert code == 0 and "hog [bins=4 resize=64x64]" in out

    register_method("colorhist[bins=4]", Plain, description="colour histogram [bold]4 bins[/bold]")
    monkeypatch.setenv("COLUMNS", "250")  # one table row per method
    code, out, _ = cli("methods", "list")
    assert "colorhist[bins=4]" in out and "[bold]4 bins[/bold]" in out


def test_own_dataset_title_with_markup_prints_whole(own, cli):
    pd.DataFrame({"image": IMAGES, "x": [0, 10, 20, 0], "y": 0}).to_csv(own / "positions.csv", index=False)
    (own / "dataset.toml").write_text('title = "Lab [red]corridor[/red]"\n')
    code, out, _ = cli("datasets", "info", own)
    assert code == 0 and "Lab [red]corridor[/red]" in out


# ---------------------------------------------------------------- seeds and K of the other commands
def test_negative_seeds_and_k_are_one_line(shared_data, cli, tmp_path):
    """A negative seed was a numpy traceback in compare, publish and vocabulary fit; --k 0 compared 'R@0'."""
    for args, said in ((["compare", "hog", "dense-vlad", "--dataset", "corridor", "--seed", "-1"], "--seed takes a whole number >= 0"),
                       (["compare", "hog", "dense-vlad", "--dataset", "corridor", "--k", "0"], "--k takes a whole number >= 1"),
                       (["publish", "--to", tmp_path / "docs", "--seed", "-1"], "--seed takes a whole number >= 0")):
        code, _, err = cli("leaderboard", *args)
        assert_refused(code, err, None, said)
        assert err.count("takes a whole number") == 1  # the option at fault alone (was: both, '--k 1' never given)
    assert not (tmp_path / "docs").exists()
    code, _, err = cli("vocabulary", "fit", "--dataset", "corridor", "--method", "anyloc", "--backbone", "dinov2_vits14",
                       "--weights", "random", "--layer", 1, "--clusters", 2, "--resize", 28, 28, "--seed", -1,
                       "--data-dir", shared_data)
    assert_refused(code, err, None, "The vocabulary's seed (--seed) must be a whole number >= 0, got -1")
