"""Where data is looked for and downloaded: nothing is downloaded or created where the user
did not ask. The default data root is filled on first use (here from a local HTTP server
holding the real Corridor files: pooch, sha256 checks and all, without the internet)."""
from __future__ import annotations

import dataclasses
import functools
import http.server
import json
import shlex
import subprocess
import sys
import threading
from pathlib import Path

import pooch
import pytest

from vprbench.datasets import manifest as manifests
from vprbench.datasets.download import read_registry

from hostile_files import assert_refused

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def no_network(monkeypatch):
    """Records any download attempt (and fails it, as offline)."""
    attempts = []

    def offline(self, name, *args, **kwargs):
        attempts.append(name)
        raise ConnectionError("offline")

    monkeypatch.setattr(pooch.Pooch, "fetch", offline)
    return attempts


def tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def test_mistyped_data_dir_names_where_it_looked_and_creates_nothing(tmp_path, no_network, cli):
    (tmp_path / "shared").mkdir()
    typo = tmp_path / "shraed"
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", typo)
    assert_refused(code, err, None, f"Dataset 'corridor' is not in the data root {typo}: looked for {typo / 'corridor'}",
                   f"closest existing path: {tmp_path} (which holds shared)",
                   f"add --download to evaluate or run 'vprbench datasets download corridor --data-dir {typo}'")
    assert tree(tmp_path) == ["shared"] and no_network == []


def test_datasets_commands_refuse_a_mistyped_data_root(tmp_path, no_network, cli, monkeypatch):
    """Was: 'datasets list --data-dir TYPO' listed every dataset as not on disk, exit 0; 'download' and
    'import' made the typo's whole tree of folders."""
    (tmp_path / "shared").mkdir()
    typo = tmp_path / "shraed"
    code, _, err = cli("datasets", "list", "--data-dir", typo)
    assert_refused(code, err, None, f"The data root {typo} (--data-dir) does not exist (closest existing path: "
                                    f"{tmp_path} (which holds shared)): check the path")
    monkeypatch.setenv("VPRBENCH_DATA", str(typo))
    code, _, err = cli("datasets", "list")
    assert_refused(code, err, None, f"The data root {typo} ($VPRBENCH_DATA) does not exist")
    monkeypatch.delenv("VPRBENCH_DATA")
    deep = typo / "data"
    for command in (("datasets", "download", "corridor"), ("datasets", "import", "corridor", tmp_path / "shared"),
                    ("evaluate", "--method", "hog", "--dataset", "corridor", "--download")):
        code, _, err = cli(*command, "--data-dir", deep)
        assert_refused(code, err, None, f"--data-dir {deep}: the folder {typo} does not exist: create it first")
    monkeypatch.setenv("VPRBENCH_DATA", str(deep))  # named as given: was '--data-dir' for evaluate --download
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--download")
    assert_refused(code, err, None, f"$VPRBENCH_DATA {deep}: the folder {typo} does not exist: create it first")
    assert tree(tmp_path) == ["shared"] and no_network == []


def test_data_root_that_is_the_dataset_folder_says_use_the_folder_above(shared_data, no_network, cli):
    before = tree(shared_data / "corridor")
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data / "corridor")
    assert_refused(code, err, None, f"The data root {shared_data / 'corridor'} is the 'corridor' dataset folder itself",
                   f"use the folder above, --data-dir {shared_data}.")
    assert tree(shared_data / "corridor") == before and no_network == []


def test_a_data_root_that_is_a_file_is_named_as_one(tmp_path, no_network, cli):
    """Was: "closest existing path: <the file>" and advice to download into it."""
    file = tmp_path / "notes.txt"
    file.write_text("x")
    for command in (("evaluate", "--method", "hog", "--dataset", "corridor"), ("datasets", "info", "corridor"),
                    ("evaluate", "--method", "hog", "--dataset", "corridor", "--download"),
                    ("datasets", "download", "corridor"), ("reproduce", "anyloc", "--table", "6", "--dry-run")):
        code, _, err = cli(*command, "--data-dir", file)
        assert_refused(code, err, None, f"The data root {file} is a file, not a folder: give --data-dir the folder "
                                        "that holds the datasets (or will hold them, with --download).")
    assert no_network == [] and tree(tmp_path) == ["notes.txt"]


def test_missing_own_folder_and_undownloadable_dataset(tmp_path, no_network, cli):
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", tmp_path / "mydta" / "x")
    assert_refused(code, err, None, f"Dataset folder {tmp_path / 'mydta' / 'x'} does not exist (closest existing folder: {tmp_path})")
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "hawkins", "--data-dir", tmp_path)
    assert_refused(code, err, None, f"looked for {tmp_path / 'hawkins_long_corridor'}", "hawkins_long_corridor.tar.gz",
                   "vprbench datasets import hawkins PATH")
    assert no_network == [] and tree(tmp_path) == []


def test_datasets_info_never_downloads(tmp_path, no_network, monkeypatch, cli):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user-cache"))
    code, _, err = cli("datasets", "info", "corridor")
    assert_refused(code, err, None, "Run 'vprbench datasets download corridor' (evaluate fetches it by itself")
    assert no_network == [] and tree(tmp_path) == []


@pytest.fixture
def corridor_server(shared_data, monkeypatch):
    """Corridor's manifest pointing at a local HTTP server of the real files."""
    handler = functools.partial(QuietHandler, directory=str(shared_data / "corridor"))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    real = manifests.dataset_manifests()
    local = {**real["corridor"].download, "base_url": f"http://127.0.0.1:{server.server_port}/"}
    served = {**real, "corridor": dataclasses.replace(real["corridor"], download=local)}
    monkeypatch.setattr(manifests, "dataset_manifests", lambda: served)
    yield server
    server.shutdown()


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the real files, except those in `damaged` (path -> 'wrong' bytes, or 'cut' halfway
    with the connection closed); every request is counted in `served`."""
    damaged: dict[str, str] = {}
    served: list[str] = []

    def log_message(self, *args):
        pass

    def do_GET(self):
        name = self.path.lstrip("/")
        QuietHandler.served.append(name)
        if name not in self.damaged:
            return super().do_GET()
        body = Path(self.directory, name).read_bytes()
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(b"not the image" if self.damaged[name] == "wrong" else body[: len(body) // 2])
        self.close_connection = True


@pytest.mark.parametrize("damage", ["wrong", "cut"])
def test_damaged_download_is_refused_naming_the_file_and_resumes(corridor_server, tmp_path, monkeypatch, cli, damage):
    """A file that fails its sha256 or stops halfway: refused naming it (query/ and ref/ share
    names), nothing at the dataset's place; the rerun fetches only what is missing."""
    import logging
    monkeypatch.setattr(pooch.get_logger(), "level", logging.WARNING)
    monkeypatch.setattr(QuietHandler, "damaged", {"query/0000005.jpg": damage})
    monkeypatch.setattr(QuietHandler, "served", [])
    target = tmp_path / "d"
    code, _, err = cli("datasets", "download", "corridor", "--data-dir", target)
    assert_refused(code, err, None, "Downloading 'corridor'", "failed at query/0000005.jpg: ",
                   f"Files fetched so far stay in {target / 'corridor.partial'}; rerun to resume.")
    assert ".." not in err.replace(str(tmp_path), "")
    assert not (target / "corridor").exists() and not (target / "corridor.partial" / "query" / "0000005.jpg").exists()
    first = len(QuietHandler.served)
    monkeypatch.setattr(QuietHandler, "damaged", {})
    code, _, err = cli("datasets", "download", "corridor", "--data-dir", target)
    assert code == 0, err
    files = len(read_registry("corridor.sha256"))
    assert len(QuietHandler.served) - first == files - (first - 1)  # the damaged one fetched again, no other
    # the dataset, and the lock downloads into this data root take turns by (locks stay, as every lock does)
    assert tree(target) == [".corridor.download.lock", "corridor",
                            *(f"corridor/{name}" for name in tree(target / "corridor"))]
    assert len(list((target / "corridor" / "query").glob("*.jpg"))) == 111


def test_default_data_root_is_filled_on_first_use(corridor_server, tmp_path, monkeypatch, shared_data, cli):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user-cache"))
    code, out, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--json")
    assert code == 0, err
    fetched = json.loads(out)
    root = manifests.default_data_root() / "corridor"
    assert root == tmp_path / "user-cache" / "vprbench" / "data" / "corridor"
    assert len(list((root / "ref").glob("*.jpg"))) == len(list((root / "query").glob("*.jpg"))) == 111
    assert fetched["counts"]["positive_pairs"] == 549
    code, out, _ = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir",
                       shared_data, "--json")
    assert json.loads(out)["recall"] == fetched["recall"]  # the same data as ../shared/data


def test_explicit_data_dir_is_downloaded_into_only_when_asked(corridor_server, tmp_path, cli):
    target = tmp_path / "mine"
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", target)
    assert code == 1 and not target.exists()
    code, _, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--data-dir", target,
                       "--download")
    assert code == 0, err
    assert tree(target / "corridor")[:3] == ["ReadMe.txt", "ground_truth_new.npy", "query"]


def readme_main_job() -> list[list[str]]:
    """The README's first set-up command after the install: its steps, each as words."""
    setup = (ROOT / "README.md").read_text().split("## Set up", 1)[1].split("## Use", 1)[0]
    line = next(line for line in setup.splitlines() if "vprbench evaluate" in line)
    steps = [shlex.split(step) for step in line.split(" && ")]
    return steps[next(i for i, step in enumerate(steps) if "install" in step) + 1:]


def test_readme_main_job_on_a_fresh_machine_downloads_and_evaluates(corridor_server, tmp_path, monkeypatch, cli):
    """A fresh machine has no ../shared: the README's command was refused there ('the folder ../shared does not
    exist') before any download; its steps, as written, now fetch Corridor beside the repo and evaluate it."""
    import logging

    monkeypatch.setattr(pooch.get_logger(), "level", logging.WARNING)
    repo = tmp_path / "repo"
    repo.mkdir()
    monkeypatch.chdir(repo)
    for step in readme_main_job():
        if step[0] == "mkdir":
            subprocess.run(step, check=True)
            continue
        assert step[0] == ".venv/bin/vprbench", step
        code, out, err = cli(*step[1:], "--cache-dir", tmp_path / "cache")
        assert code == 0, err
        assert "hog on corridor" in out
    assert len(list((tmp_path / "shared" / "data" / "corridor" / "query").glob("*.jpg"))) == 111


def test_readme_main_job_runs_here_as_a_real_process(shared_data, tmp_path):
    """The README's main job, as written there, on this machine: the data beside the repo, nothing downloaded."""
    *_, job = readme_main_job()
    words = [word.replace("../shared/data", str(shared_data)) for word in job[1:]]
    before = tree(shared_data)
    done = subprocess.run([str(Path(sys.executable).parent / "vprbench"), *words, "--cache-dir", str(tmp_path / "cache")],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "hog on corridor" in done.stdout and "111 database, 111 queries" in done.stdout
    assert tree(shared_data) == before
