"""Kills and full disks on the commands that write outside the descriptor stores: the published
leaderboard and saved vocabularies (bundle imports, the dataset registry and result records are
covered in test_concurrent_imports.py, test_disk_errors.py and tests/bundles)."""
from __future__ import annotations

import hashlib
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from vprbench.aggregation.vocabulary import Vocabulary, load_vocabulary
from vprbench.bundles.export import bundle_bytes
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate, read_results, save_result
from vprbench import fsutil
from vprbench.fsutil import atomic_write
from vprbench.spec import RunSettings, resolve_spec


@pytest.fixture(scope="module")
def hog_run(shared_data, tmp_path_factory) -> tuple[Path, dict]:
    """(cache, record): a cache holding one real hog run on Corridor (32 x 32: seconds), and its record."""
    cache = tmp_path_factory.mktemp("one-run")
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, data_dir=shared_data, cache_dir=cache)
    record = evaluate(spec, RunSettings(cache_dir=cache, data_dir=shared_data, workers=0))
    save_result(record, cache)
    return cache, record


@pytest.fixture
def one_run(hog_run) -> Path:
    return hog_run[0]


def tree(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


#: `vprbench ARGS...` killed (SIGKILL) just after the first step that puts the new section in place
KILLED_PUBLISHING = """
import os, pathlib, signal, sys
from vprbench.cli.main import main
from vprbench.leaderboard import staging

def killed_after(step):
    def run(*args):
        step(*args)
        os.kill(os.getpid(), signal.SIGKILL)
    return run

pathlib.Path.rename = killed_after(pathlib.Path.rename)
staging.exchange = killed_after(staging.exchange)
sys.exit(main(sys.argv[1:]))
"""


def test_a_publish_killed_while_swapping_leaves_one_whole_site(one_run, shared_data, tmp_path, cli):
    """Was: the old section was renamed away, then the new one renamed in: kill -9 between the two
    left docs/ with no leaderboard/ at all (the old site only in a hidden .leaderboard-old-* folder).
    And the section was mode 0700 (mkdtemp's), unreadable to a web server running as another user."""
    from vprbench.fsutil import exchange

    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    if not exchange(tmp_path / "a", tmp_path / "b"):
        pytest.skip("this system cannot swap two folders in one step (renameat2 RENAME_EXCHANGE): publish renames twice")
    docs = tmp_path / "docs"
    args = ["leaderboard", "publish", "--to", docs, "--cache-dir", one_run]  # no mosaics: quicker
    code, _, err = cli(*args)
    assert code == 0, err
    section = docs / "leaderboard"
    mask = os.umask(0)
    os.umask(mask)
    assert section.stat().st_mode & 0o777 == 0o777 & ~mask
    (section / "previous-site").write_text("the site before this publish\n")
    before = tree(section)
    done = subprocess.run([sys.executable, "-c", KILLED_PUBLISHING, *map(str, args)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == -9, done.stderr
    assert section.is_dir()
    after = tree(section)
    new = {name: digest for name, digest in before.items() if name != "previous-site"}
    assert after in (before, new)  # the old site whole or the new one whole, never neither nor a mix
    assert section.stat().st_mode & 0o777 == 0o777 & ~mask
    code, _, err = cli(*args)  # and the next publish runs as ever
    assert code == 0, err
    assert tree(section) == new


def test_saving_a_vocabulary_removes_only_its_own_leftovers(tmp_path):
    """Was: saving to `vocabulary fit --output FOLDER/v.pt` removed every '.*.tmp' file an hour old in
    FOLDER, another program's (an editor's swap file in one's home folder) as well as its own."""
    others, mine = tmp_path / ".editor-swap.tmp", tmp_path / ".v.pt.abc123.tmp"
    for path in (others, mine):
        path.write_bytes(b"x")
        os.utime(path, (time.time() - 7200, time.time() - 7200))
    centres = torch.arange(4 * 8, dtype=torch.float32).reshape(4, 8)
    Vocabulary(centres, {}).save(tmp_path / "v.pt")
    assert others.read_bytes() == b"x" and not mine.exists()  # a killed save of v.pt: its own, gone
    assert torch.equal(load_vocabulary(tmp_path / "v.pt").centres, centres)


def test_a_vocabulary_that_does_not_fit_on_the_disk_is_one_line(tmp_path):
    """A write that fails (a file-size limit here; a full disk fails the same way: checked on a
    64 KiB tmpfs). Was: torch.save's own writer raised RuntimeError '[enforce fail at
    inline_container.cc:672] . unexpected pos 1024 vs 918', shown as a traceback by `vocabulary import`."""
    source = Vocabulary(torch.ones(8, 384), {}).save(tmp_path / "v384.pt")
    cache = tmp_path / "cache"

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (8_000, 8_000))  # the file is 14 KB

    done = subprocess.run([sys.executable, "-m", "vprbench", "vocabulary", "import", source, "--source", "mine",
                           "--backbone", "dinov2_vits14@random", "--layer", "0", "--cache-dir", cache],
                          capture_output=True, text=True, timeout=120, preexec_fn=limited)
    folder = cache / "vocabularies" / "dinov2_vits14@random-l0-value-c8" / "mine"
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith(f"error: Cannot use {folder / 'vocabulary.pt'}: File too large; ")
    assert len(done.stderr.strip().splitlines()) == 1
    assert [p.name for p in folder.iterdir()] == [".vocabulary.pt.lock"]  # nothing half-written to load; its lock


@pytest.mark.parametrize("stop", [KeyboardInterrupt(), OSError(28, "No space left on device")], ids=["kill", "full-disk"])
def test_a_record_stored_is_one_that_can_be_exported(hog_run, tmp_path, monkeypatch, stop):
    """Stopped while the row's method card was written (the record already written before it). Was:
    the record stood without its card, so `results export` refused it for good ('Run ...: Cannot use
    .../methods/<row key>.json: No such file or directory'; a kill -9 there left the same), and a
    full disk there said 'The result was not stored.' of a record that was."""
    _, record = hog_run
    cache = tmp_path / "cache"

    def card_fails(path, data):
        if path.parent.name == "methods":
            raise stop
        return atomic_write(path, data)

    monkeypatch.setattr(fsutil, "atomic_write", card_fails)  # the card is written through fsutil.write_once
    with pytest.raises((KeyboardInterrupt, VPRBenchError)) as stopped:
        save_result(record, cache)
    if isinstance(stopped.value, VPRBenchError):
        assert str(stopped.value).endswith("No space left on device; free some space, or use a folder on another disk "
                                           "(finished descriptors are kept). The result was not stored.")
    assert read_results(cache) == []  # nothing a reader would take for a stored run
    monkeypatch.undo()
    save_result(record, cache)  # the rerun stores it whole
    (stored,) = read_results(cache)
    assert stored["run_id"] == record["run_id"] and len(bundle_bytes([stored])) > 1000


def test_a_publish_onto_a_full_disk_keeps_the_site_and_says_what_to_do(one_run, tmp_path, cli, monkeypatch):
    """A full disk part-way through the pages (the same on a 2 MiB tmpfs, at four levels of filling).
    Was: '... (No space left on device); the previous .../leaderboard is unchanged.', and no word of
    what to do."""
    from vprbench.leaderboard import site

    docs = tmp_path / "docs"
    args = ["leaderboard", "publish", "--to", docs, "--cache-dir", one_run]
    assert cli(*args)[0] == 0
    before = tree(docs / "leaderboard")
    write, pages = site._write, []

    def fills_up(path, text):
        pages.append(path)
        if len(pages) == 2:
            raise OSError(28, "No space left on device")
        return write(path, text)

    monkeypatch.setattr(site, "_write", fills_up)
    code, out, err = cli(*args)
    assert (code, out) == (1, "") and err == (
        f"error: Cannot write the leaderboard to {docs} (No space left on device); the previous {docs / 'leaderboard'} "
        "is unchanged: free some space, then publish again, or publish to a folder on another disk.\n")
    assert tree(docs / "leaderboard") == before
    # no half-written section
    assert sorted(p.name for p in docs.iterdir()) == [".leaderboard.lock", ".leaderboard.read-at", "leaderboard"]



#: stores the record of the run in cache argv[1] into cache argv[2], killed (SIGKILL) just before the file
#: argv[3] of its results folder (the row's method card, or LAYOUT) is renamed in place
KILLED_WRITE = """
import os, signal, sys
from vprbench.evaluation import read_results, save_result
replace = os.replace
def killed(source, target):
    if os.path.relpath(target, os.path.join(sys.argv[2], "results")).startswith(sys.argv[3]):
        os.kill(os.getpid(), signal.SIGKILL)
    replace(source, target)
os.replace = killed
save_result(read_results(sys.argv[1])[0], sys.argv[2])
"""


@pytest.mark.parametrize("killed_in", ["methods", "LAYOUT"])
def test_a_stored_record_removes_what_killed_writers_of_files_written_once_left(hog_run, tmp_path, killed_in):
    """Was: a run killed while writing its row's method card (or the results folder's LAYOUT) left
    `.<name>.*.tmp` there for good: that file, once written, is never written again, so nothing looked."""
    cache, record = hog_run
    for _ in range(2):
        killed = subprocess.run([sys.executable, "-c", KILLED_WRITE, str(cache), str(tmp_path), killed_in],
                                capture_output=True, text=True, timeout=60)
        assert killed.returncode == -9, killed.stderr
    left = sorted(p for p in (tmp_path / "results").rglob(".*.tmp"))
    assert len(left) == 2 and all(p.relative_to(tmp_path / "results").as_posix().startswith(killed_in)
                                  or p.name.startswith(f".{killed_in}.") for p in left)
    os.utime(left[0], (time.time() - 7200, time.time() - 7200))  # untouched for two hours: a dead writer's
    save_result(record, tmp_path)
    other = record["run_id"][:-1] + ("1" if record["run_id"].endswith("0") else "0")  # another run of the same row
    save_result({**record, "run_id": other}, tmp_path)  # its card and LAYOUT written already: not again
    assert sorted((tmp_path / "results").rglob(".*.tmp")) == [left[1]]  # a young one may be a live writer's
    assert len(read_results(tmp_path)) == 2
