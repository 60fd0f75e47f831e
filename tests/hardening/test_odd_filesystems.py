"""Folders on odd filesystems: names that are no UTF-8 text (bytes of another encoding, as a Latin-1
system or an old archive writes them), and names the folder lists in any order."""
from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

from hostile_files import assert_refused
from own_folders import corridor_folder


def test_images_under_a_folder_named_in_another_encoding_are_hashed_and_remembered(shared_data, tmp_path):
    """A folder b'caf\\xe9' (Latin-1): was UnicodeEncodeError from the image-hash memo (a traceback)."""
    from vprbench.datasets.identity import content_hashes

    folder = Path(os.fsdecode(os.path.join(os.fsencode(tmp_path), b"caf\xe9")))
    folder.mkdir()
    image = folder / "0.jpg"
    shutil.copy(shared_data / "corridor" / "ref" / "0000000.jpg", image)
    expected = [hashlib.sha256(image.read_bytes()).hexdigest()]
    assert content_hashes([image], tmp_path / "cache") == expected
    image.unlink()  # remembered by its stamp: a second look-up reads no byte of the (now copied) file
    shutil.copy(shared_data / "corridor" / "ref" / "0000001.jpg", image)
    assert content_hashes([image], tmp_path / "cache") != expected, "a new file's stamp was taken for the old one"


def test_an_own_folder_under_a_folder_named_in_another_encoding_runs(shared_data, tmp_path, cli):
    root = corridor_folder(shared_data, Path(os.fsdecode(os.path.join(os.fsencode(tmp_path), b"d\xe9", b"own"))))
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)
    assert code == 0, err


def test_an_image_named_in_another_encoding_is_one_line(shared_data, tmp_path, cli):
    """Its name cannot be a row of positions.csv (UTF-8) nor a name in a store: was a traceback from the memo
    with UTM names, and 'add a row for each' with positions.csv."""
    root = corridor_folder(shared_data, tmp_path / "own")
    shutil.copy(shared_data / "corridor" / "ref" / "0000003.jpg",
                os.path.join(os.fsencode(root / "database"), b"caf\xe9\n\x1b[2J.jpg"))
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)
    assert_refused(code, err, None, r"b'caf\xe9\n\x1b[2J.jpg'", "not UTF-8", "rename it")
    code, out, err = cli("datasets", "verify", root)
    assert code == 1 and r"b'caf\xe9\n\x1b[2J.jpg'" in out + err and "\x1b" not in out + err, out + err


def test_names_alike_in_natural_order_are_listed_in_one_order(tmp_path, monkeypatch):
    """'a1.jpg' and 'a01.jpg' (or one name in two subfolders) sort alike by name: their order was the order
    the filesystem lists them in (hash order on ext4, newest first on tmpfs), and the ground truth with it."""
    from vprbench.images import list_images

    for name in ("a1.jpg", "a01.jpg", "x/b.jpg", "y/b.jpg"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    orders = []
    for reverse in (False, True):
        iterdir, rglob = Path.iterdir, Path.rglob
        monkeypatch.setattr(Path, "iterdir", lambda self: iter(sorted(iterdir(self), reverse=reverse)))
        monkeypatch.setattr(Path, "rglob", lambda self, pattern: iter(sorted(rglob(self, pattern), reverse=reverse)))
        orders.append([(list_images(tmp_path, natural=True)), list_images(tmp_path, recursive=True, natural=True)])
        monkeypatch.undo()
    assert orders[0] == orders[1]


def test_verify_names_a_file_holding_a_newline_in_one_line(shared_data, tmp_path, cli):
    """A damaged image named 'a\\nb.jpg': its problem was printed over two lines (the second unmarked)."""
    root = corridor_folder(shared_data, tmp_path / "own")
    name = "\x1b[2Ja\nb.jpg"
    (root / "database" / name).write_bytes((shared_data / "corridor" / "ref" / "0000003.jpg").read_bytes()[:3000])
    with open(root / "positions.csv", "a") as positions:
        positions.write(f'"database/{name}",30,0\n')
    code, out, err = cli("datasets", "verify", root)
    problem = [line for line in out.splitlines() if "truncated" in line]
    assert code == 1 and len(problem) == 1 and problem[0].startswith("  error: ") and "\x1b" not in out, out + err
    assert problem[0].endswith("Replace or remove the corrupt file."), out


def test_a_published_download_names_a_dataset_folder_with_blanks_by_its_last_name(shared_data, tmp_path, cli):
    """'/home/ann lee/my photos/own' was published as 'ann lee/my photos/own' (a path's names ended at a blank)."""
    import json

    root = corridor_folder(shared_data, tmp_path / "ann lee" / "my photos" / "own")
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 32, 32, "--dataset", root, "--k", 1)
    assert code == 0, err
    code, _, err = cli("leaderboard", "publish", "--to", tmp_path / "docs")
    assert code == 0, err
    (download,) = [p for p in (tmp_path / "docs" / "leaderboard" / "downloads").glob("own-*.json")]
    (record,) = json.loads(download.read_text())  # the dataset's one run
    assert record["dataset_root"] == record["spec"]["dataset"]["path"] == "own", record["dataset_root"]
    assert "ann lee" not in download.read_text() and "photos" not in download.read_text()


def test_a_folder_an_option_names_holding_a_name_in_another_encoding_is_identified(tmp_path):
    """dense-vlad's `--vocabulary ./words` with a stray 'notes-\\xe9.txt' beside the images: was a
    UnicodeEncodeError traceback while the run's identity was made. Named by its bytes: one key per name."""
    from vprbench.content_identity import folder_identity

    words = tmp_path / "words"
    words.mkdir()
    (words / "a.jpg").write_bytes(b"a")
    stray = os.path.join(os.fsencode(words), b"notes-\xe9.txt")
    with open(stray, "wb") as f:
        f.write(b"x")
    first = folder_identity(str(words), tmp_path / "cache")
    os.rename(stray, os.path.join(os.fsencode(words), b"notes-\xe8.txt"))
    assert first.startswith("folder:") and folder_identity(str(words), tmp_path / "cache") != first


#: reproduce's page written under a file-size limit (a full disk fails the same way), the leaderboard's publish
#: left out; prints the error's type
LIMITED_PAGE = """
import resource, signal, sys
from pathlib import Path
from types import SimpleNamespace
from vprbench import leaderboard
from vprbench.cli.reproduce import publish
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails (EFBIG) instead of killing the process
resource.setrlimit(resource.RLIMIT_FSIZE, (4_000, 4_000))
leaderboard.publish = lambda *args: None
try:
    publish(SimpleNamespace(publish=Path(sys.argv[1]), paper="anyloc", table="2"), {"title": "T"}, "x" * 10_000, None)
except Exception as error:
    print(type(error).__name__)
"""


def test_a_reproduce_page_that_cannot_be_written_whole_leaves_the_one_before(tmp_path):
    """Was: written in place, a full disk left half the new table where the whole old one was."""
    import subprocess
    import sys

    page = tmp_path / "anyloc-table-2.md"
    page.write_text("the table before\n")
    done = subprocess.run([sys.executable, "-c", LIMITED_PAGE, str(tmp_path)], capture_output=True, text=True,
                          timeout=120)
    assert done.stdout.strip().splitlines()[-1] == "CacheError", done.stderr  # (the table is printed above it)
    assert page.read_text() == "the table before\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [page.name]


def test_waiting_for_a_lock_in_a_folder_named_with_escapes_is_one_literal_line(tmp_path, capsys):
    """A cache folder named 'c\\x1b[2J\\nd' (a user's, or a script's typo): 'waiting for descriptor store ...' cleared
    the screen and broke in two lines."""
    import subprocess
    import sys

    from vprbench.fsutil import LockTimeout, lock

    folder = tmp_path / "c\x1b[2J\nd"
    folder.mkdir()
    hold = ("import sys; from filelock import FileLock; held = FileLock(sys.argv[1]); held.acquire(); "
            "print('held', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(folder / ".lock")], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        try:
            with lock(folder / ".lock", 0, what=f"descriptor store {folder}"):
                pass
        except LockTimeout:
            pass
        err = capsys.readouterr().err
        assert err.startswith("waiting for descriptor store ") and err.count("\n") == 1 and "\x1b" not in err, err
        assert "c\\x1b[2J\\nd" in err
    finally:
        holder.kill()
        holder.wait()


def test_describe_names_an_image_named_in_another_encoding(shared_data, tmp_path, cli):
    """`describe caf\\xe9.jpg` (a path given as bytes of another encoding): was a UnicodeEncodeError traceback
    when its store was created (stores keep names as UTF-8), after the images before it were described."""
    image = os.path.join(os.fsencode(tmp_path), b"caf\xe9.jpg")
    shutil.copy(shared_data / "corridor" / "ref" / "0000003.jpg", image)
    out = tmp_path / "d.npy"
    code, _, err = cli("describe", "--method", "hog", "--resize", 32, 32, shared_data / "corridor" / "ref" / "0000001.jpg",
                       os.fsdecode(image), "--out", out)
    assert_refused(code, err, None, r"b'caf\xe9.jpg'", "not UTF-8", "rename it")
    assert not out.exists()
