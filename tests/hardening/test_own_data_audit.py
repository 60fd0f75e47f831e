"""A folder of one's own made hostile: positions, empty folders and links each refused in one line,
and a good run after the refusal unaffected."""
from __future__ import annotations

import os
import shutil

import pytest

from hostile_files import assert_refused

ROWS = [("database/d0.jpg", 0), ("database/d1.jpg", 10), ("database/d2.jpg", 20), ("queries/q0.jpg", 1), ("queries/q1.jpg", 11)]


@pytest.fixture
def own(shared_data, tmp_path):
    """<tmp>/own: three Corridor map images, two queries, positions in metres."""
    root = tmp_path / "own"
    for (name, _), source in zip(ROWS, ["ref/0000000.jpg", "ref/0000001.jpg", "ref/0000002.jpg", "query/0000000.jpg",
                                           "query/0000001.jpg"]):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(shared_data / "corridor" / source, root / name)
    write_positions(root)
    return root


def write_positions(root, change=None):
    rows = [(name, (change or {}).get(name, x)) for name, x in ROWS]
    (root / "positions.csv").write_text("image,x,y\n" + "".join(f"{name},{x},0\n" for name, x in rows))


def evaluate(cli, root):
    return cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)


def good_run_after(cli, root):
    code, _, err = evaluate(cli, root)
    assert code == 0, err


def test_positions_too_large_for_distances_are_refused(own, cli):
    """1e308 is finite but its distances overflow: a traceback at search time (verify said OK)."""
    write_positions(own, {"database/d1.jpg": 1e308, "queries/q0.jpg": -1e308})
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, str(own / "positions.csv"), "positions beyond +-1e+12 in 2 row(s)",
                   "database/d1.jpg")
    assert cli("datasets", "verify", own)[0] == 1
    write_positions(own)
    good_run_after(cli, own)


def test_utm_names_too_large_are_refused(own, cli):
    (own / "positions.csv").unlink()
    for i, (name, _) in enumerate(ROWS):
        (own / name).rename(own / name.split("/")[0] / f"@{1e300 if i == 1 else 500000 + i}@4000000@31@U@.jpg")
    code, out, err = cli("datasets", "verify", own)
    assert code == 1 and "Cannot read UTM coordinates from the file name '@1e+300@" in out, out + err
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "Cannot read UTM coordinates from the file name '@1e+300@")


def test_no_query_with_a_positive_is_refused(own, cli):
    """Every method scored Recall@K = 0 with exit 0: positions in the wrong unit or a radius too small."""
    write_positions(own, {"queries/q0.jpg": 1000, "queries/q1.jpg": 2000})
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "no query in", "has a database image within 25 metres",
                   str(own / "dataset.toml"))
    write_positions(own)
    good_run_after(cli, own)


@pytest.mark.parametrize("folder", ["database", "queries"])
def test_the_empty_folder_is_named(own, folder, cli):
    for image in (own / folder).iterdir():
        image.unlink()
    code, _, err = evaluate(cli, own)
    other = "queries" if folder == "database" else "database"
    assert_refused(code, err, None, f"no images in {own / folder}; put jpg")
    assert str(own / other) not in err


@pytest.mark.parametrize("link", ["dangling", "loop"])
def test_a_dead_link_named_like_an_image_is_refused(own, link, cli):
    """Skipped unseen before: the image the user put there silently left out of the benchmark."""
    path = own / "database" / "d3.jpg"
    os.symlink(own / "nowhere.jpg" if link == "dangling" else path, path)
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, f"Image {path} is a symbolic link to a missing file")
    path.unlink()
    good_run_after(cli, own)


def test_verify_counts_an_image_that_does_not_decode_apart(own, cli):
    """A truncated image is named, and not counted among the images decoded."""
    data = (own / "queries/q1.jpg").read_bytes()
    (own / "queries/q1.jpg").write_bytes(data[: len(data) // 3])
    code, out, err = cli("datasets", "verify", own)
    assert code == 1 and "q1.jpg" in out, out + err
    assert "4 of 5 images decoded" in out, out


def test_the_default_k_beyond_a_small_map_says_which_k_to_give(own, cli):
    """Three map images and the default --k 1 5 10 20: the message names the dataset and a --k that runs."""
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", own)
    assert_refused(code, err, None, "K = 20 exceeds the 3 database images of own: give --k with values up to 3, "
                   "e.g. --k 1.")


@pytest.mark.parametrize("given", ["absolute", "relative"])
def test_a_row_for_an_absent_image_is_warned_of_once(own, given):
    """The folder is read for the run's identity and again for the run: the same warning was printed twice
    (and still was for a folder given as ./own, read the second time by its absolute path)."""
    import subprocess
    import sys

    with (own / "positions.csv").open("a") as positions:
        positions.write("database/ghost.jpg,5,0\n")
    folder = str(own) if given == "absolute" else "./own"
    done = subprocess.run([sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--resize", "32", "32",
                           "--dataset", folder, "--k", "1"], capture_output=True, text=True, timeout=120,
                          cwd=own.parent)
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("lists 1 image(s) that are not in") == 1, done.stderr


def test_positions_separated_by_semicolons_are_named_so(own, cli):
    """A spreadsheet's export in ';' (as many locales write CSV): the error listed one strange column only."""
    (own / "positions.csv").write_text("image;x;y\n" + "".join(f"{name};{x};0\n" for name, x in ROWS))
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "positions.csv needs a column 'image'", "(one column: the file is separated by ';'; "
                   "save it separated by commas)")
    write_positions(own)
    good_run_after(cli, own)


def test_rows_naming_bare_file_names_say_which_path_to_write(own, cli):
    """Rows '0001.jpg' for database/0001.jpg: 'no position ... add a row for each', with the rows right there."""
    (own / "positions.csv").write_text("image,x,y\n" + "".join(f"{name.split('/')[1]},{x},0\n" for name, x in ROWS))
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "has no position for 5 image(s)", "rows name images by their path in ",
                   "write 'database/d0.jpg', not 'd0.jpg'")
    write_positions(own)
    good_run_after(cli, own)


def test_positions_typed_with_a_space_after_each_comma_are_read(own, cli):
    """'image, x, y' by hand: was "needs position columns x,y ...; it has ['image', ' x', ' y']"."""
    import json

    info = json.loads(cli("datasets", "info", own, "--json")[1])
    (own / "positions.csv").write_text("image, x, y\n" + "".join(f"{name}, {x}, 0\n" for name, x in ROWS))
    code, out, err = cli("datasets", "info", own, "--json")
    assert code == 0, err
    assert json.loads(out)["protocol"]["hash"] == info["protocol"]["hash"]  # the same positions, the same dataset
    good_run_after(cli, own)


def test_a_row_for_a_file_there_that_is_not_read_as_an_image_says_so(own, cli, recwarn):
    """A .gif (or an image in a subfolder) with its row: was warned of as "not in database or queries"."""
    from PIL import Image

    Image.open(own / "database" / "d2.jpg").save(own / "database" / "d3.gif")
    (own / "database" / "sub").mkdir()
    shutil.copy(own / "database" / "d2.jpg", own / "database" / "sub" / "d4.jpg")
    with open(own / "positions.csv", "a") as rows:
        rows.write("database/d3.gif,30,0\ndatabase/sub/d4.jpg,40,0\nqueries/gone.jpg,5,0\n")
    code, _, err = evaluate(cli, own)
    assert code == 0, err
    said = " ".join(str(w.message) for w in recwarn)
    assert "lists 2 file(s) that are not read as images, e.g. ['database/d3.gif', 'database/sub/d4.jpg']" in said, said
    assert "lists 1 image(s) that are not in " in said and "['queries/gone.jpg']" in said, said


@pytest.mark.parametrize("content", [b"", "image,x,y\ndatabase/caf\xe9.jpg,1,0\n".encode("cp1252")], ids=["empty", "cp1252"])
def test_positions_that_are_no_utf8_csv_say_how_to_save_them(content, own, cli):
    """Was "Cannot read F: 'utf-8' codec can't decode byte 0xe9 in position 27" with nothing to do."""
    (own / "positions.csv").write_bytes(content)
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, f"Cannot read {own / 'positions.csv'}: ", ". Save it as UTF-8 text, a header row "
                                    "first (e.g. image,x,y).")
