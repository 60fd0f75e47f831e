"""Bad inputs an earlier audit left: options a route ignored, the Python API's plain Python errors,
named pipes where a file is read (each read would hang), and a download's failure as a long line
of the network client's internals. Each is one line naming the input, exit 1 (2 for an option the
command never takes), nothing stored."""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from hostile_files import assert_refused, tiny_images

from vprbench.errors import VPRBenchError

NOT_REGULAR = "is not a regular file (a named pipe, device or socket): give a file."


#: writes an end of file into the pipe each time a reader waits on it (ENXIO while none does)
UNBLOCK = """
import errno, os, sys, time
while True:
    try:
        os.close(os.open(sys.argv[1], os.O_WRONLY | os.O_NONBLOCK))
    except OSError as error:
        if error.errno not in (errno.ENXIO, errno.ENOENT):
            raise
    time.sleep(0.05)
"""


@contextlib.contextmanager
def fifo_at(path: Path):
    """A named pipe at `path`. A read that opens it (the defect) gets an end of file at once, so the
    test fails instead of hanging; from another process, as a reader in C (HDF5, torch) may hold the GIL."""
    path.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(path)
    unblocker = subprocess.Popen([sys.executable, "-c", UNBLOCK, str(path)])
    try:
        yield path
    finally:
        unblocker.kill()
        unblocker.wait()


def own_folder(root: Path) -> Path:
    tiny_images(root / "database", ["@0@0@.jpg", "@5@0@.jpg"])
    tiny_images(root / "queries", ["@1@0@.jpg"])
    return root


# ---------------------------------------------------------------- 1. options a route does not use
def test_describe_refuses_a_data_root_when_the_images_are_paths(cli, shared_data, tmp_path):
    """Was: exit 0, --data-dir unused (only --dataset looks a dataset up)."""
    image = shared_data / "corridor" / "query" / "0000000.jpg"
    code, _, err = cli("describe", "--method", "hog", "--resize", 32, 32, "--data-dir", tmp_path / "X",
                       "--out", tmp_path / "o.npy", image)
    assert_refused(code, err, None, f"--data-dir {tmp_path / 'X'} is not used without --dataset")
    assert not (tmp_path / "o.npy").exists()


# (not 'datasets download': were it to regress, it would go to the network)
@pytest.mark.parametrize("command", [["datasets", "list"], ["datasets", "import", "corridor", "x"],
                                     ["datasets", "verify", "corridor"]])
def test_dataset_commands_refuse_a_cache_they_never_read(command, cli, tmp_path):
    """Was: exit 0 with --cache-dir FILE (a file), the option read by none of them."""
    (tmp_path / "file").write_text("")
    code, _, err = cli(*command, "--cache-dir", tmp_path / "file")
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"--cache-dir is not used by 'vprbench {' '.join(command[:2])}'" in err


@pytest.mark.parametrize("command", [["vocabulary", "import", "x.pt", "--source", "urban"], ["vocabulary", "download"]])
def test_vocabulary_commands_refuse_a_data_root_they_never_read(command, cli, tmp_path):
    code, _, err = cli(*command, "--data-dir", tmp_path)
    assert code == 2 and f"--data-dir is not used by 'vprbench vocabulary {command[1]}'" in err, err


def test_datasets_info_refuses_a_cache_for_a_named_dataset(cli, shared_data, tmp_path):
    (tmp_path / "file").write_text("")
    code, _, err = cli("datasets", "info", "corridor", "--data-dir", shared_data, "--cache-dir", tmp_path / "file")
    assert_refused(code, err, None, f"--cache-dir {tmp_path / 'file'} is not used for dataset 'corridor'")


def test_datasets_info_of_an_own_folder_uses_the_cache_given(cli, tmp_path):
    """The folder's image identities are remembered in the cache: a cache that is a file is refused
    (was: exit 0, the identities put in the default cache)."""
    folder = own_folder(tmp_path / "own")
    (tmp_path / "file").write_text("")
    code, _, err = cli("datasets", "info", folder, "--cache-dir", tmp_path / "file")
    assert_refused(code, err, None, f"The cache folder {tmp_path / 'file'} (--cache-dir) is a file")
    code, _, err = cli("datasets", "info", folder, "--cache-dir", tmp_path / "cache")
    assert code == 0, err
    assert (tmp_path / "cache").is_dir()


@pytest.mark.parametrize("command", [["datasets", "info"], ["datasets", "verify"], ["evaluate", "--method", "hog", "--dataset"]])
def test_a_data_root_is_refused_when_every_dataset_is_a_folder(command, cli, tmp_path):
    folder = own_folder(tmp_path / "own")
    code, _, err = cli(*command, folder, "--data-dir", tmp_path / "data")
    assert_refused(code, err, None, f"--data-dir {tmp_path / 'data'} is not used")


def test_run_refuses_a_data_root_when_every_dataset_of_the_plan_is_a_folder(cli, tmp_path):
    """Was: exit 0, --data-dir unused; refused before the folder is read (nothing cached)."""
    folder = own_folder(tmp_path / "own")
    plan = tmp_path / "plan.toml"
    plan.write_text(f'k = [1]\nmethods = [{{ name = "hog", options = {{ resize = [32, 32] }} }}]\n'
                    f'datasets = [{str(folder)!r}]\n')
    code, _, err = cli("run", plan, "--data-dir", tmp_path / "data", "--cache-dir", tmp_path / "cache")
    assert_refused(code, err, None, f"--data-dir {tmp_path / 'data'} is not used when every dataset of the plan "
                                    "is a folder of your own")
    assert not (tmp_path / "cache").exists() and not (tmp_path / "data").exists()


def test_leaderboard_show_takes_a_data_root_for_its_ground_truth(cli, tmp_path):
    """Was refused outside publish; every action now re-scores its cells against the ground truth there."""
    code, _, err = cli("leaderboard", "show", "--data-dir", tmp_path)
    assert_refused(code, err, None, "No results")


def test_an_empty_unused_option_is_named_so(cli):
    """Was: "--cache-dir  is not used ...", the empty value ('--cache-dir=') invisible."""
    code, _, err = cli("datasets", "info", "corridor", "--protocols", "--cache-dir=")
    assert_refused(code, err, None, "--cache-dir '' is not used with --protocols")


# ---------------------------------------------------------------- 2. the Python API
@pytest.mark.parametrize("call, fragment", [
    (lambda: __import__("vprbench.weights").weights.read_torch_file(None), "Checkpoint: give a file path"),
    (lambda: __import__("vprbench.weights").weights.weights_provenance(0), "weights_provenance takes a weights identity"),
])
def test_api_arguments_of_the_wrong_kind_are_one_line(call, fragment):
    with pytest.raises(VPRBenchError, match=fragment):
        call()


def test_a_link_loop_given_to_the_api_is_the_projects_error(tmp_path):
    from vprbench.datasets import import_dataset
    from vprbench.weights import read_torch_file

    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    for call in (lambda: import_dataset("corridor", tmp_path / "a", tmp_path / "data"),
                 lambda: read_torch_file(tmp_path / "a")):
        with pytest.raises(VPRBenchError, match="a symbolic link in this path leads back to itself"):
            call()
    assert not (tmp_path / "data").exists()


def test_a_path_holding_a_nul_given_to_the_api_is_the_projects_error():
    """Was: ValueError('embedded null byte') out of os.stat."""
    from vprbench.weights import read_torch_file

    with pytest.raises(VPRBenchError, match="Checkpoint 'w\\\\x00.pth' holds a NUL character"):
        read_torch_file("w\x00.pth")


def test_a_named_pipe_given_to_the_api_is_refused(tmp_path):
    from vprbench.weights import read_torch_file

    with fifo_at(tmp_path / "w.pth") as pipe, pytest.raises(VPRBenchError, match=re.escape(NOT_REGULAR)):
        read_torch_file(pipe)


# ---------------------------------------------------------------- 3. named pipes where a file is read
@pytest.mark.parametrize("command", [
    ["results", "verify", "{pipe}"],
    ["results", "import", "{pipe}", "--into", "{tmp}/repo"],
    ["run", "{pipe}"],
    ["vocabulary", "import", "{pipe}", "--source", "urban"],
    ["describe", "--method", "netvlad", "--weights", "{pipe}", "--out", "{tmp}/o.npy", "{image}"],
    ["describe", "--method", "hog", "--out", "{tmp}/o.npy", "{pipe}"],  # was: "Image not found"
    ["evaluate", "--method", "hog", "--resize", "32", "32", "--dataset", "corridor", "--data-dir", "{data}",
     "--rerank", "aqe", "--candidates", "{pipe}"],
])
def test_a_named_pipe_as_an_input_file_is_refused(command, cli, shared_data, tmp_path):
    with fifo_at(tmp_path / "pipe") as pipe:
        filled = [part.format(pipe=pipe, tmp=tmp_path, data=shared_data,
                              image=shared_data / "corridor" / "query" / "0000000.jpg") for part in command]
        code, _, err = cli(*filled)
    assert_refused(code, err, None, f"{pipe} {NOT_REGULAR}")
    assert not (tmp_path / "repo").exists() and not (tmp_path / "o.npy").exists()


def test_a_named_pipe_as_a_datasets_ground_truth_is_refused(cli, corridor_copy):
    (corridor_copy / "ground_truth_new.npy").unlink()
    with fifo_at(corridor_copy / "ground_truth_new.npy") as pipe:
        code, _, err = cli("datasets", "info", "corridor", "--data-dir", corridor_copy.parent)
    assert_refused(code, err, None, f"{pipe} {NOT_REGULAR}")


@pytest.mark.parametrize("name", ["dataset.toml", "positions.csv", "database/@9@0@.jpg"])
def test_a_named_pipe_in_a_folder_of_your_own_is_refused(name, cli, tmp_path):
    """Was: skipped silently (dataset.toml's settings, the positions, an image dropped)."""
    folder = own_folder(tmp_path / "own")
    with fifo_at(folder / name) as pipe:
        code, _, err = cli("datasets", "info", folder)
    assert_refused(code, err, None, f"{pipe} {NOT_REGULAR}")


# ---------------------------------------------------------------- 4. a download that fails
@pytest.fixture
def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_dataset_download_failure_is_one_short_line(cli, closed_port, tmp_path, monkeypatch):
    """Was: 'HTTPConnectionPool(host=..., port=...): Max retries exceeded with url: ... (Caused by
    NewConnectionError(...))', and an empty corridor.partial left behind."""
    import pooch

    from vprbench.datasets import manifest as manifests

    monkeypatch.setattr(pooch.get_logger(), "level", logging.WARNING)  # its notice of each file it fetches
    real = manifests.dataset_manifests()
    local = {**real["corridor"].download, "base_url": f"http://127.0.0.1:{closed_port}/corridor/"}
    monkeypatch.setattr(manifests, "dataset_manifests",
                        lambda: {**real, "corridor": dataclasses.replace(real["corridor"], download=local)})
    code, _, err = cli("datasets", "download", "corridor", "--data-dir", tmp_path / "d")
    assert_refused(code, err, None, f"Downloading 'corridor' from 127.0.0.1:{closed_port} failed at ",
                   ": Connection refused. ", f"'vprbench datasets import corridor PATH --data-dir {tmp_path / 'd'}'")
    message = err.strip().splitlines()[-1]
    assert len(message.replace(str(tmp_path), "")) < 250 and "HTTPConnectionPool" not in message, message  # short but for the path
    # nothing but the lock downloads into this data root take turns by (locks stay, as every lock does)
    assert [p.name for p in (tmp_path / "d").iterdir()] == [".corridor.download.lock"]


def test_a_weights_download_failure_says_why_in_a_few_words(closed_port, tmp_path):
    from vprbench.weight_source import WeightSource
    from vprbench.weights import resolve_weights

    url = f"http://127.0.0.1:{closed_port}/release/w.pth"
    with pytest.raises(VPRBenchError) as raised:
        resolve_weights(WeightSource("w.pth", url=url), None, "toy", cache_dir=tmp_path)
    assert f"toy: could not download w.pth from {url} (Connection refused). Offline? " in str(raised.value)
    assert "URLError" not in str(raised.value) and "urlopen" not in str(raised.value)


class _Unprintable(Exception):
    def __str__(self):
        raise RuntimeError("no text")


def _holding_itself() -> Exception:
    error = ConnectionError()
    error.args = (error,)
    return error


def _cycle() -> Exception:
    outer, inner = OSError("outer"), OSError(111, "Connection refused")
    outer.__cause__, inner.__context__ = inner, outer
    return outer


@pytest.mark.parametrize("error, reason", [
    (_Unprintable(), "_Unprintable"),  # was: the RuntimeError of its __str__, in place of the download's failure
    (_holding_itself(), "ConnectionError"),  # was: RecursionError
    (_cycle(), "Connection refused"),
    (OSError(5, "x" * 10_000), "x" * 157 + "..."),  # was: the whole text
])
def test_a_download_failure_of_any_make_is_a_few_words(error, reason):
    from vprbench.errors import network_reason

    assert network_reason(error) == reason
