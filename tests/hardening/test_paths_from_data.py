"""Paths read from data stay inside the dataset: a ground-truth .mat naming an absolute path,
a '..' that climbs out or a symlink leading out, a positions CSV naming files elsewhere, a
manifest's list files outside the folder and a dataset name that is not a plain file name are
refused with one line naming the file and the entry. Each test first shows the attack is real:
the path named really leads to a readable image outside the dataset folder."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.io import loadmat

from vprbench import VPRBenchError
from vprbench.datasets import load_dataset
from vprbench.datasets.layouts.own_data import is_safe_name, own_manifest, safe_name
from vprbench.datasets.protocol import Protocol, apply_protocol

from hostile_files import assert_refused, oxford_copy, tiny_images


@pytest.fixture
def secret(tmp_path) -> Path:
    """An image outside every dataset folder, which no dataset may make vprbench read."""
    tiny_images(tmp_path / "private", ["holiday.png"])
    return tmp_path / "private" / "holiday.png"


def mat_names(mat: Path) -> list[str]:
    """The query names in an oxdatapart.mat, as scipy reads them (what the reader sees)."""
    cell = loadmat(mat)["dbStruct"].ravel()
    return [str(np.ravel(v)[0]) for v in np.ravel(cell[2])]


@pytest.mark.parametrize("route", ["absolute", "dot-dot", "symlink-file", "symlink-folder"])
def test_mat_image_names_leading_out_are_refused(route, tmp_path, secret, cli):
    data = tmp_path / "data"
    images = data / "Oxford_Robotcar" / "oxDataPart"
    if route == "absolute":
        entry = str(secret)
    elif route == "dot-dot":
        entry = "../../../private/holiday.png"
    elif route == "symlink-file":
        entry = "view.png"
    else:
        entry = "album/holiday.png"
    root = oxford_copy(data, ["a.png"], [entry])
    if route == "symlink-file":
        (images / "view.png").symlink_to(secret)
    elif route == "symlink-folder":
        (images / "album").symlink_to(secret.parent, target_is_directory=True)
    # the attack is real: the name in the file leads to the outside image, which is readable
    assert mat_names(root / "oxdatapart.mat") == [entry]
    target = (images / entry).resolve()
    assert target == secret.resolve() and target.is_file() and not target.is_relative_to(root.resolve())

    code, _, err = cli("datasets", "info", "oxford", "--data-dir", data)
    assert_refused(code, err, None, f"{root / 'oxdatapart.mat'} names {entry!r}, which lies outside {images}")
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "oxford", "--data-dir", data)
    assert_refused(code, err, None, f"names {entry!r}, which lies outside")


@pytest.mark.filterwarnings("ignore:Dataset .oxford.")  # two images, not the release's 213
def test_mat_names_inside_the_folder_still_read(tmp_path):
    """Names with '..' that stay inside, and a symlinked image folder, are fine."""
    data = tmp_path / "data"
    root = oxford_copy(data, ["sub/../a.png"], ["./b.png"])  # each image named once: a query is not in the database
    (root / "oxDataPart" / "sub").mkdir()
    dataset = load_dataset("oxford", data)
    assert [p.name for p in dataset.database] == ["a.png"] and [p.name for p in dataset.queries] == ["b.png"]
    moved = tmp_path / "disk2" / "oxDataPart"  # the whole image folder on another disk, linked in
    moved.parent.mkdir()
    (root / "oxDataPart").rename(moved)
    (root / "oxDataPart").symlink_to(moved, target_is_directory=True)
    assert len(load_dataset("oxford", data).database) == 1


@pytest.mark.parametrize("entry", ["../private/holiday.png", "ABSOLUTE"])
def test_positions_csv_rows_outside_the_folder_are_refused(entry, tmp_path, secret, cli):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["0.jpg"])
    tiny_images(root / "queries", ["0.jpg"])
    entry = str(secret) if entry == "ABSOLUTE" else entry
    assert (root / entry).resolve() == secret.resolve() and secret.is_file()  # the row names a real file outside
    (root / "positions.csv").write_text(f"image,x,y\ndatabase/0.jpg,0,0\nqueries/0.jpg,1,0\n{entry},5,5\n")
    code, _, err = cli("datasets", "info", root)
    assert_refused(code, err, None, f"{root / 'positions.csv'} names 1 image(s) outside {root}, e.g. [{entry!r}]")


def test_manifest_list_files_outside_the_folder_are_refused(tmp_path, make_protocol_dataset):
    dataset, outside = make_protocol_dataset
    relative = "../elsewhere/names.txt"
    assert (dataset.root / relative).resolve() == outside.resolve() and outside.is_file()  # real, readable
    protocol = Protocol(dataset="mine", name="subset", select_queries={"names": relative}, base={"unit": "metres"})
    with pytest.raises(VPRBenchError, match=r"selects its queries from \['../elsewhere/names.txt'\], which are not all "
                                            r"paths inside the dataset folder"):
        apply_protocol(dataset, protocol)
    inside = dataclasses.replace(protocol, select_queries={"names": "names.txt"})
    (dataset.root / "names.txt").write_text("q0.jpg\n")
    assert len(apply_protocol(dataset, inside).queries) == 1  # the same list inside the folder is read


@pytest.mark.parametrize("role", ["names", "index"])
def test_a_query_subset_npy_claiming_more_than_it_holds_is_refused_unread(role, tmp_path, make_protocol_dataset):
    """Was: the 64 TiB its header claims allocated first (a MemoryError: "out of memory, lower --batch-size")."""
    dataset, _ = make_protocol_dataset
    (dataset.root / "names.txt").write_text("q0.jpg\n")
    huge = dataset.root / "huge.npy"
    with open(huge, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "<i8", "fortran_order": False, "shape": (2**43,)})
        handle.write(bytes(64))
    spec = {"names": "huge.npy"} if role == "names" else {"names": "names.txt", "index": "huge.npy"}
    protocol = Protocol(dataset="mine", name="subset", select_queries=spec, base={"unit": "metres"})
    with pytest.raises(VPRBenchError, match=rf"Cannot read query subset \w+ {huge}: it is truncated"):
        apply_protocol(dataset, protocol)


@pytest.fixture
def make_protocol_dataset(tmp_path):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["0.jpg"])
    tiny_images(root / "queries", ["q0.jpg", "q1.jpg"])
    (root / "positions.csv").write_text("image,x,y\ndatabase/0.jpg,0,0\nqueries/q0.jpg,0,0\nqueries/q1.jpg,9,9\n")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "names.txt").write_text("q0.jpg\n")
    return load_dataset(str(root)), tmp_path / "elsewhere" / "names.txt"


@pytest.mark.parametrize("name", ["../../escaped", "a/b", "..", "x<script>", "lab\x1b[2Jcorridor", "tab\tname",
                                  "-rf", " padded", "ünïcode"])
def test_unsafe_dataset_names_are_refused(name, tmp_path, cli):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["@0@0@.jpg"])
    tiny_images(root / "queries", ["@5@0@.jpg"])
    (root / "dataset.toml").write_text(f"name = {json.dumps(name)}\n", encoding="utf-8")
    if "/" in name or name == "..":  # the attack is real: as a file name, it lands in another folder
        results = tmp_path / "cache" / "results"
        assert (results / name).resolve().parent != results.resolve()
    code, _, err = cli("datasets", "info", root)
    if "\x1b" in name:
        assert_refused(code, err, None, f"{root / 'dataset.toml'}: name holds the control character")
        assert "\x1b" not in err
    else:
        assert_refused(code, err, None, f"{root / 'dataset.toml'}: name {name!r} is not a safe dataset name")


def test_control_characters_in_titles_are_refused_and_markup_is_kept(tmp_path, cli):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["@0@0@.jpg"])
    tiny_images(root / "queries", ["@5@0@.jpg"])
    (root / "dataset.toml").write_text('title = "Lab \\u001b]0;owned\\u0007 corridor"\n')
    code, _, err = cli("datasets", "info", root)
    assert_refused(code, err, None, f"{root / 'dataset.toml'}: title holds the control character '\\x1b'")
    (root / "dataset.toml").write_text('name = "lab-corridor_2.v1+x"\ntitle = "Lab <b>corridor</b>\\tfloor 2"\n')
    assert own_manifest(root).name == "lab-corridor_2.v1+x"


def test_a_dataset_toml_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Was: "dataset.toml is not valid TOML: Invalid statement (at line 1, column 1)", of a file that looked right."""
    root = tmp_path / "mine"
    (root / "dataset.toml").parent.mkdir()
    (root / "dataset.toml").write_text('\ufeffname = "lab"\nradius = 3\n', encoding="utf-8")
    assert (own_manifest(root).name, own_manifest(root).radius) == ("lab", 3)


def test_default_names_from_folder_names_are_made_safe(tmp_path):
    assert safe_name("Lab photos <2024>") == "Lab-photos-2024-" and is_safe_name(safe_name("Lab photos <2024>"))
    assert safe_name("..hidden") == "hidden" and safe_name("日本") == "own-data" and safe_name("a..b") == "a.b"
    root = tmp_path / "my data (v2)"
    tiny_images(root / "database", ["@0@0@.jpg"])
    tiny_images(root / "queries", ["@5@0@.jpg"])
    assert load_dataset(str(root)).name == "my-data-v2-"
