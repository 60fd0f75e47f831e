"""Image folders and positions files made hostile in ways a copy, an editor or a camera leaves them:
a link looping beside the images, an image Pillow reads with a warning, a positions file with a
repeated column or a malformed row. Each is one line naming the file, and a later good run is unaffected."""
from __future__ import annotations

import json
import re
import warnings

import numpy as np
import pytest
from PIL import Image

from vprbench.datasets.layouts.npy import read_npy
from vprbench.datasets.layouts.release import pose_rows, top_k_csv
from vprbench.errors import VPRBenchError
from vprbench.images import list_images, load_image

from hostile_files import assert_refused

ROWS = [("database/d0.jpg", 0), ("database/d1.jpg", 10), ("queries/q0.jpg", 1)]


@pytest.fixture
def own(tmp_path):
    """<tmp>/own: two small map images and one query, positions in metres."""
    root = tmp_path / "own"
    for shade, (name, _) in enumerate(ROWS):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (32, 32), (40 * shade, 90, 90)).save(root / name)
    write_positions(root)
    return root


def write_positions(root, header="image,x,y", extra=""):
    rows = "".join(f"{name},{x},0\n" for name, x in ROWS)
    (root / "positions.csv").write_text(f"{header}\n{rows}{extra}")


def test_a_link_looping_beside_the_images_is_ignored(own, cli):
    """A link that leads back to itself (a copy tool's leftover), not named as an image, is ignored as
    other files are; it ended the run with 'Too many levels of symbolic links'."""
    (own / "database" / "loop").symlink_to("loop")
    code, out, err = cli("datasets", "info", own, "--json")
    assert code == 0 and "Traceback" not in err and "symbolic links" not in err, err
    assert json.loads(out)["database"] == 2, out


def corrupt_exif_jpeg(path):
    Image.new("RGB", (16, 8), (90, 90, 90)).save(path, "JPEG", exif=b"Exif\x00\x00II*\x00\xff\xff\xff\x7f")
    return path


def test_pillows_warnings_name_the_image(tmp_path):
    """Pillow warns of a damaged EXIF block without naming the file: a run of thousands of images said
    'warning: Corrupt EXIF data' and no more."""
    path = corrupt_exif_jpeg(tmp_path / "photo.jpg")
    with pytest.warns(UserWarning) as said:
        assert load_image(path).size == (16, 8)
    assert [str(w.message) for w in said] == [
        f"Image {path}: Pillow warns 'Corrupt EXIF data.  Expecting to read 2 bytes but only got 0.'; it is read as "
        "Pillow reads it (replace the file if it is damaged)."]


def test_a_palette_with_transparency_reads_without_a_warning(tmp_path):
    """RGB drops a palette's transparency, as the authors' loaders do: Pillow's advice to convert to
    RGBA, naming no file, is no advice for a benchmark's user."""
    path = tmp_path / "palette.png"
    image = Image.frombytes("P", (8, 8), bytes(range(64)))
    image.putpalette(bytes(range(256)) * 3)
    image.save(path, transparency=bytes([0, 128] + [255] * 254))
    with Image.open(path) as saved:
        assert isinstance(saved.info["transparency"], bytes)  # the form Pillow warns of
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_image(path).mode == "RGB"


def test_a_warning_in_a_run_names_the_image(own, cli):
    image = corrupt_exif_jpeg(own / "queries" / "q0.jpg")
    with pytest.warns(UserWarning, match=re.escape(f"Image {image}: Pillow warns 'Corrupt EXIF data.")):
        code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", own, "--k", 1)
    assert code == 0, err


def evaluate(cli, root):
    return cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)


def test_a_repeated_position_column_is_refused(own, cli):
    """'image,x,x,y': pandas renamed the second x to x.1 and the first was used, unseen."""
    write_positions(own, header="image,x,y,x")
    (own / "positions.csv").write_text((own / "positions.csv").read_text().replace(",0\n", ",0,500\n"))
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, f"{own / 'positions.csv'} names the column(s) ['x'] more than once")
    write_positions(own)
    assert evaluate(cli, own)[0] == 0


def test_a_row_of_more_values_than_columns_says_so_in_one_line(own, cli):
    write_positions(own, extra="queries/q1.jpg,1,0,7\n")
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "Expected 3 fields in line 5, saw 4; give each row one value for each column")
    assert "\\n" not in err, err  # pandas' message ends in a line break, written out by the one-line error


def test_a_row_with_no_image_name_is_said_as_such(own, cli):
    """A spreadsheet's trailing ',,' row was warned of as an image named 'nan' not in the folders."""
    write_positions(own, extra=",,\n")
    with pytest.warns(UserWarning, match="has 1 row\\(s\\) with no image name; they are left out") as said:
        code, _, err = evaluate(cli, own)
    assert code == 0, err
    assert not [w for w in said if "'nan'" in str(w.message)]


def test_a_linked_subfolder_of_a_split_is_read_and_a_link_back_up_is_not(tmp_path):
    """The utm-names layout reads a split's subfolders; one linked in from another disk was skipped
    unseen (a count warning only), though linked image folders are read as set up."""
    split, elsewhere = tmp_path / "images" / "test" / "database", tmp_path / "other-disk"
    tiny = Image.new("RGB", (8, 8))
    for path in (split / "a" / "@1@2@.jpg", elsewhere / "@3@4@.jpg", tmp_path / "images" / "test" / "queries" / "q.jpg"):
        path.parent.mkdir(parents=True, exist_ok=True)
        tiny.save(path)
    (split / "linked").symlink_to(elsewhere)
    (split / "up").symlink_to("..")  # leads back to images/test: would add the queries and loop
    (split / "a" / "loop").symlink_to("loop")
    assert list_images(split, recursive=True, natural=True) == [split / "a" / "@1@2@.jpg", split / "linked" / "@3@4@.jpg"]


@pytest.mark.parametrize("where", ["positive", "query index"])
def test_a_ground_truth_index_too_large_for_a_float_is_one_line(where, corridor_copy, shared_data, cli):
    """A pickled Python int of 400 digits in a real VPR-Bench row file: math.isfinite overflowed, a traceback."""
    path = corridor_copy / "ground_truth_new.npy"
    rows = read_npy(shared_data / "corridor" / "ground_truth_new.npy", "ground truth", "rows")
    rows[5, 1 if where == "positive" else 0] = [10**400] if where == "positive" else 10**400
    path.unlink()
    np.save(path, rows, allow_pickle=True)
    code, _, err = cli("datasets", "info", "corridor", "--data-dir", corridor_copy.parent)
    assert_refused(code, err, None, f"Cannot read ground truth {path}: a whole number of 1329 bits is not an image "
                                    "index (it is beyond the 64-bit integer range)")
    assert "0" * 100 not in err  # not its 400 digits


def test_a_pose_too_large_for_a_float_is_one_line(tmp_path):
    path = tmp_path / "pose_topic_list.npy"
    poses = np.zeros((2, 2), dtype=object)
    poses[1, 0] = 10**400
    np.save(path, poses, allow_pickle=True)
    with pytest.raises(VPRBenchError, match=f"Cannot read poses {re.escape(str(path))}: int too large"):
        pose_rows(path, {"database_rows": [0, 1], "query_rows": [1, 2]}, 1, 1)


@pytest.mark.parametrize("sign", ["", "-"])
def test_a_position_of_hundreds_of_digits_is_refused_as_too_large(sign, own, cli):
    """pandas reads a whole number of 401 digits as a Python int and overflows turning it into a float,
    even when told to coerce: a traceback (1e400, text, became infinity and was refused)."""
    write_positions(own, extra="")
    text = (own / "positions.csv").read_text().replace("database/d1.jpg,10,0", f"database/d1.jpg,{sign}1{'0' * 400},0")
    (own / "positions.csv").write_text(text)
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "has positions beyond +-1e+12 in 1 row(s), e.g. for ['database/d1.jpg']")


def test_a_top_k_index_of_hundreds_of_digits_is_one_line(tmp_path):
    path = tmp_path / "gt_matches.csv"
    path.write_text("top_1_ref_ind,top_2_ref_ind\n0,1\n1" + "0" * 400 + ",2\n")
    with pytest.raises(VPRBenchError, match=f"Cannot read ground truth {re.escape(str(path))}: a whole number of "
                       r"1329 bits is not an image index \(it is beyond the 64-bit integer range\)\. Expected"):
        top_k_csv(path, {"columns": ["top_1_ref_ind", "top_2_ref_ind"]}, 2)


def test_hidden_names_are_no_images(tmp_path):
    """macOS's ._x.jpg metadata files (and hidden folders) were listed as images: a benchmark copied from a Mac
    was then refused by its image count without naming them."""
    from vprbench.images import list_images

    Image.new("RGB", (4, 4)).save(tmp_path / "a.jpg")
    (tmp_path / "._a.jpg").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    (tmp_path / ".thumbs").mkdir()
    Image.new("RGB", (4, 4)).save(tmp_path / ".thumbs" / "b.jpg")
    assert list_images(tmp_path) == [tmp_path / "a.jpg"]
    assert list_images(tmp_path, recursive=True) == [tmp_path / "a.jpg"]


def test_an_unreadable_subfolder_of_a_split_is_named_not_skipped(own, cli, monkeypatch):
    """The check for images left in a split's subfolders skipped one it could not read without a word (rglob),
    where list_images names an unreadable folder. Tests run as root: the folder is made unreadable by hand."""
    import os

    locked = own / "database" / "old"
    locked.mkdir()
    scandir = os.scandir

    def refusing(path="."):
        if os.fspath(path) == str(locked):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return scandir(path)

    monkeypatch.setattr(os, "scandir", refusing)
    code, _, err = cli("datasets", "info", own)
    assert_refused(code, err, None, f"Cannot use {locked}: Permission denied")


def test_a_fractional_frame_is_refused_naming_its_row(own, cli):
    """A frame is an index along a route: 'frame' 12.5 was taken as a position between frames."""
    (own / "dataset.toml").write_text("radius = 2\n")
    (own / "positions.csv").write_text("image,frame\ndatabase/d0.jpg,-1\ndatabase/d1.jpg,12.5\nqueries/q0.jpg,0\n")
    code, _, err = cli("datasets", "info", own)
    assert_refused(code, err, None, f"{own / 'positions.csv'} has frame numbers that are not whole in 1 row(s), "
                                    "e.g. for ['database/d1.jpg']; give each image's frame index")
    (own / "positions.csv").write_text("image,frame\ndatabase/d0.jpg,-1\ndatabase/d1.jpg,12.0\nqueries/q0.jpg,0\n")
    assert cli("datasets", "info", own)[0] == 0  # whole numbers written as 12.0, and a negative frame, are taken


def test_an_own_folders_table_is_titled_with_its_radius_as_its_board_column(own, cli):
    """'vprbench evaluate' titled it 'hog [resize=32x32] on own:own', where the board's column reads 'own (own, ±2 frames)'."""
    from vprbench.cli.evaluate import results_table
    from vprbench.evaluation.results import read_results
    from vprbench.leaderboard.cells import build_board

    (own / "dataset.toml").write_text("radius = 2\n")
    (own / "positions.csv").write_text("image,frame\ndatabase/d0.jpg,0\ndatabase/d1.jpg,10\nqueries/q0.jpg,1\n")
    code, _, err = evaluate(cli, own)
    assert code == 0, err
    [record] = read_results()
    [column] = build_board([record]).columns
    assert column.title == "own (own, ±2 frames)"
    assert results_table(record).title == f"hog [resize=32x32] on {column.title}"


def test_a_float_image_in_0_to_255_is_warned_of_once_naming_it(tmp_path):
    """Float images are read as values in [0, 1]: one written in 0..255 read almost white, unsaid."""
    levels = np.linspace(0, 255, 64, dtype=np.float32).reshape(8, 8)
    Image.fromarray(levels, "F").save(tmp_path / "bright.tif")
    Image.fromarray(levels / 255, "F").save(tmp_path / "unit.tif")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        for _ in range(2):  # read again (another method, a resumed run): said once
            assert (np.asarray(load_image(tmp_path / "bright.tif")) == 255).mean() > 0.9
        load_image(tmp_path / "unit.tif")
    assert [str(w.message) for w in said] == [
        f"Image {tmp_path / 'bright.tif'}: a float image with values up to 255 is read as values in [0, 1] (1 is "
        "white, above it clipped), so it reads almost white: save it as 8- or 16-bit integers, or as floats scaled "
        "to [0, 1]."]
