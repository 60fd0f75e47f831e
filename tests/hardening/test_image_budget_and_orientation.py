"""Images are decoded within a stated budget and seen upright. A 330 KB PNG declaring
13,000 x 13,000 16-bit pixels (which Pillow alone decodes, taking gigabytes) is refused from
its header, naming its size; a photo stored sideways with an EXIF orientation tag, as phones
write them, is described upright, as a person viewing it sees it. Each test first shows the
attack is real."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from PIL import Image, ImageFile, ImageOps

from vprbench import VPRBenchError, create_method
from vprbench.images import DECODE_BUDGET_PIXELS, ORIENTATION, check_decode_budget, load_image, load_rgb

from hostile_files import assert_refused, big_png

SIDE = 13_000


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    return big_png(tmp_path_factory.mktemp("bomb") / "small-file.png", SIDE, SIDE)


def test_a_small_file_declaring_a_huge_image_is_refused_before_decoding(bomb, monkeypatch):
    # the attack is real: a valid 16-bit PNG of 169 M pixels in a few hundred KB, which Pillow's
    # own limit (a warning up to twice its 89 M) lets through to the decoder
    assert bomb.stat().st_size < 400_000
    with pytest.warns(Image.DecompressionBombWarning):  # Pillow only warns: its error is at twice its limit
        with Image.open(bomb) as image:
            assert image.size == (SIDE, SIDE) and image.mode in ("I;16", "I")  # Pillow 10.0 named it "I"
    assert SIDE * SIDE > DECODE_BUDGET_PIXELS
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda self, *a, **k: pytest.fail(f"decoded {self.size}"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and no warning: one message, vprbench's
        with pytest.raises(VPRBenchError, match=rf"Image {bomb} is 13000 x 13000 = 169,000,000 pixels, above the decode "
                                                rf"budget of 89,478,485 pixels .*Downscale it"):
            load_image(bomb)


def test_the_bomb_in_a_dataset_is_one_line(bomb, corridor_copy, cli):
    image = corridor_copy / "query" / "0000005.jpg"
    image.unlink()
    image.write_bytes(bomb.read_bytes())  # named .jpg, a PNG inside: read as what it is, within the budget
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor",
                       "--data-dir", corridor_copy.parent)
    assert_refused(code, err, None, f"Image {image} is 13000 x 13000 = 169,000,000 pixels", stores_allowed=True)


def test_an_image_beyond_twice_the_budget_is_refused_as_pillow_opens_it(tmp_path):
    path = big_png(tmp_path / "huge.png", 20_000, 20_000, bit_depth=1)
    with pytest.raises(Image.DecompressionBombError):  # Pillow's own check, at twice its limit
        Image.open(path)
    with pytest.raises(VPRBenchError, match=rf"Image {path} has 400,000,000 pixels, above the decode budget"):
        load_image(path)


def test_the_budget_admits_an_image_at_the_budget_and_bounds_other_sizes():
    check_decode_budget(9248, 6936, "a 64 MP photo")  # within
    with pytest.raises(VPRBenchError, match=r"--resize 20000 20000 is 20000 x 20000 = 400,000,000 pixels.*Pick a smaller"):
        check_decode_budget(20000, 20000, "--resize 20000 20000", "Pick a smaller size.")


def sideways_photo(path, upright: np.ndarray) -> None:
    """`upright` stored turned 90 degrees anticlockwise, with the EXIF tag (orientation 6) that
    tells viewers to turn it back clockwise, as a phone held upright writes it."""
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(np.rot90(upright, 1).copy()).save(path, exif=exif)


def test_exif_orientation_is_applied(tmp_path):
    rng = np.random.default_rng(0)
    upright = rng.integers(0, 256, (96, 64, 3), dtype=np.uint8)  # a portrait photo, 64 wide, 96 high
    sideways_photo(tmp_path / "phone.png", upright)
    Image.fromarray(upright).save(tmp_path / "upright.png")
    # the attack is real: the stored pixels are landscape and differ from what a viewer shows
    with Image.open(tmp_path / "phone.png") as stored:
        assert stored.size == (96, 64) and stored.getexif()[0x0112] == 6
        raw = np.asarray(stored.convert("RGB"))
        viewed = np.asarray(ImageOps.exif_transpose(stored).convert("RGB"))
    assert raw.shape == (64, 96, 3) and np.array_equal(viewed, upright)
    assert ORIENTATION == "exif-applied"
    assert np.array_equal(load_rgb(tmp_path / "phone.png"), upright)
    hog = create_method("hog", resize=(64, 96))  # described as it is seen: the same descriptor as the upright copy
    np.testing.assert_array_equal(hog.describe([tmp_path / "phone.png"]), hog.describe([tmp_path / "upright.png"]))


def test_a_phone_jpeg_and_a_16_bit_image_are_turned_too(tmp_path):
    upright = np.zeros((96, 64), np.uint16)
    upright[:10] = 65535  # a bright band along the top
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(np.rot90(upright, 1).copy()).save(tmp_path / "deep.png", exif=exif)
    grey = load_image(tmp_path / "deep.png", "L")
    assert grey.size == (64, 96) and np.asarray(grey)[:10].min() == 255 and np.asarray(grey)[10:].max() == 0
    rgb = np.stack([np.asarray(grey)] * 3, axis=-1)
    Image.fromarray(np.rot90(rgb, 1).copy()).save(tmp_path / "phone.jpg", exif=exif, quality=95)
    assert load_rgb(tmp_path / "phone.jpg").shape == (96, 64, 3)


@pytest.mark.parametrize("method", [["hog"], ["anyloc", "--backbone", "dinov2_vits14", "--weights", "random"]])
def test_a_resize_target_above_the_decode_budget_is_refused_before_any_work(method, capsys):
    """`--resize 60000 60000` once grew to 21 GB before the system killed it: it is refused at once."""
    from vprbench.cli.main import main

    code = main(["evaluate", "--method", *method, "--resize", "60000", "60000", "--dataset", "corridor"])
    err = capsys.readouterr().err
    assert code == 1 and "60000 x 60000 = 3,600,000,000 pixels, above the decode budget" in err and "Traceback" not in err
