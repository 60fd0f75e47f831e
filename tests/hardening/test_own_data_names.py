"""positions.csv rows matched to a folder's files by name: one spelling per path, either Unicode
form, case named when it is what differs; and a folder changed after its run was planned."""
from __future__ import annotations

import os
import shutil
import unicodedata

import pytest

from hostile_files import assert_refused

NFC, NFD = unicodedata.normalize("NFC", "café.jpg"), unicodedata.normalize("NFD", "café.jpg")


@pytest.fixture
def own(shared_data, tmp_path):
    """<tmp>/own: three Corridor map images (d0..d2), two queries, positions in metres."""
    root = tmp_path / "own"
    (root / "database").mkdir(parents=True)
    (root / "queries").mkdir()
    for i in range(3):
        shutil.copy(shared_data / "corridor" / "ref" / f"000000{i}.jpg", root / "database" / f"d{i}.jpg")
    for i in range(2):
        shutil.copy(shared_data / "corridor" / "query" / f"000000{i}.jpg", root / "queries" / f"q{i}.jpg")
    return root


def positions(root, rows):
    (root / "positions.csv").write_text("image,x,y\n" + "".join(f"{name},{x},0\n" for name, x in rows))


ROWS = [("database/d0.jpg", 0), ("database/d1.jpg", 10), ("database/d2.jpg", 20), ("queries/q0.jpg", 1),
        ("queries/q1.jpg", 11)]


def evaluate(cli, root):
    return cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)


def test_a_row_matches_a_file_named_in_the_other_unicode_form(own, cli):
    """A file named in NFD (as macOS writes it) and its row typed in NFC: 'no position for database/café.jpg',
    naming a row that reads exactly like the file."""
    os.rename(own / "database" / "d0.jpg", own / "database" / NFD)
    positions(own, [(f"database/{NFC}", 0)] + ROWS[1:])
    code, out, err = evaluate(cli, own)
    assert code == 0, err
    from vprbench.datasets import load_dataset

    dataset = load_dataset(str(own))
    assert [p.name for p in dataset.database] == [NFD, "d1.jpg", "d2.jpg"]  # the file keeps its name
    assert dataset.ground_truth.database_positions[:, 0].tolist() == [0, 10, 20]


def test_two_files_named_alike_in_two_unicode_forms_are_refused(own, cli):
    """They printed alike and each took the row spelled as it is: which is which cannot be seen."""
    shutil.copy(own / "database" / "d1.jpg", own / "database" / NFC)
    shutil.copy(own / "database" / "d2.jpg", own / "database" / NFD)
    positions(own, ROWS + [(f"database/{NFC}", 30), (f"database/{NFD}", 40)])
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "'database/cafe\\u0301.jpg' and 'database/caf\\xe9.jpg' are one name in two "
                   "Unicode forms", "rename one of the two files")


def test_a_row_spelled_through_dotdot_is_a_repeat(own, cli):
    """'queries/../database/d0.jpg' is database/d0.jpg: it was warned of as 'not in the folder' and left out,
    so which of two positions the image took depended on the spelling."""
    positions(own, ROWS + [("queries/../database/d0.jpg", 500)])
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "lists 1 image(s) more than once, e.g. ['database/d0.jpg']")


def test_a_row_differing_only_in_case_is_named(own, cli):
    os.rename(own / "database" / "d0.jpg", own / "database" / "D0.JPG")
    positions(own, ROWS)
    code, _, err = evaluate(cli, own)
    assert_refused(code, err, None, "has no position for 1 image(s), e.g. ['database/D0.JPG']; names must match in "
                   "case: the row 'database/d0.jpg' is not the file 'database/D0.JPG'; add a row for each.")


def test_an_image_replaced_after_the_run_was_planned_says_to_run_again(own, shared_data):
    """The message told a user of `evaluate --dataset ./folder` to 'build the spec again', which they never built."""
    from types import SimpleNamespace

    from vprbench.errors import VPRBenchError
    from vprbench.evaluation.pipeline import load_data
    from vprbench.run_settings import RunSettings
    from vprbench.spec import resolve_dataset

    positions(own, ROWS)
    planned = resolve_dataset(str(own))
    shutil.copy(shared_data / "corridor" / "ref" / "0000050.jpg", own / "database" / "d1.jpg")
    with pytest.raises(VPRBenchError) as refused:
        load_data(SimpleNamespace(dataset=planned), RunSettings())
    message = str(refused.value)
    assert f"Dataset {planned.path} now has protocol hash" in message and planned.protocol_hash in message
    assert "changed after the run was planned; run it again" in message


def test_a_folder_named_in_bytes_that_are_not_utf8_is_evaluated(own, cli, tmp_path):
    """A folder named in other bytes than UTF-8 (a Latin-1 'é' on Linux) arrives as '\\udce9': the image-hash
    memo (sqlite, text only) could not hold its images' paths: UnicodeEncodeError, a traceback."""
    folder = own.rename(tmp_path / os.fsdecode(b"caf\xe9"))
    positions(folder, ROWS)
    for _ in range(2):  # the second run reads its stores: its images hashed again, not remembered
        code, out, err = evaluate(cli, folder)
        assert code == 0 and "Traceback" not in err, err
