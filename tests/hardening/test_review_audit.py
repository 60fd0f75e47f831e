"""Review of the day's identity, cache and leaderboard changes: each test names what went wrong."""
from __future__ import annotations

import pytest

from vprbench import Method, register_method
from vprbench.methods import create_method
from vprbench.spec import resolve_spec


pytestmark = pytest.mark.usefixtures("scratch_methods")  # what a test registers is its own


class Sized(Method):
    """Like netvlad-vgg16: resize None is the release's own size, 'native' the full image."""

    def __init__(self, resize=None, device: str = "cpu"):
        self.got = resize

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}

    def describe(self, images):
        raise AssertionError("not run here")


def test_a_value_given_for_an_option_whose_default_is_none_is_kept():
    """resize=native was dropped as 'the default' (canonical(None) is 'native'): netvlad-vgg16 then ran at
    480x640 and was served the default run's result."""
    register_method("sized", Sized)
    native = resolve_spec("sized", "corridor", options={"resize": "native"})
    assert native.given == {"resize": "native"}
    assert native.key != resolve_spec("sized", "corridor").key
    assert create_method("sized", resize="native").got == "native"
    assert create_method("sized").got is None


def test_two_words_naming_files_of_one_content_are_two_runs(tmp_path, monkeypatch):
    """Empty files 'key' and 'value' in the working directory made facet=key and the preset's facet=value
    one run key (each word replaced by the same sha256): one served the other's stored result."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "key").write_bytes(b"")
    (tmp_path / "value").write_bytes(b"")
    key = resolve_spec("anyloc-vlad-dinov2", "corridor", options={"facet": "key"})
    assert key.key != resolve_spec("anyloc-vlad-dinov2", "corridor").key
    # a file written as a path (or with a suffix) is still known by its bytes alone, wherever it lies
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "c.pt").write_bytes(b"centres")
    (tmp_path / "c.pt").write_bytes(b"centres")
    by_path = resolve_spec("anyloc", "corridor", options={"vocabulary": str(tmp_path / "w" / "c.pt")})
    assert by_path.key == resolve_spec("anyloc", "corridor", options={"vocabulary": "c.pt"}).key
    assert by_path.files["vocabulary"].startswith("sha256:")


class Weighted(Method):
    """A plugin whose factory's own default names a weights file."""

    def __init__(self, weights: str = "", device: str = "cpu"):
        self.weights = weights

    def describe(self, images):
        raise AssertionError("not run here")


def test_a_file_written_out_equal_to_the_factory_default_is_still_known_by_its_bytes(tmp_path):
    """weights=<the factory's default file> was dropped as a default: the file left the run's identity, so
    after it was edited in place a sweep served the result of its old bytes."""
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"old")

    def weighted(weights: str = str(weights), device: str = "cpu"):
        return Weighted(weights, device)

    register_method("weighted", weighted)
    before = resolve_spec("weighted", "corridor", options={"weights": str(weights)})
    weights.write_bytes(b"new bytes")
    after = resolve_spec("weighted", "corridor", options={"weights": str(weights)})
    assert before.files["weights"].startswith("sha256:") and after.key != before.key


@pytest.mark.parametrize("arguments", [
    ("describe", "--method", "dense-vlad", "-o", "vocabulary=~nosuchuser-vprbench/v.npy"),
    ("evaluate", "--method", "anyloc", "-o", "vocabulary=~nosuchuser-vprbench/v.pt", "--dataset", "corridor"),
    ("evaluate", "--method", "hog", "--dataset", "~nosuchuser-vprbench/data"),
])
def test_a_path_in_the_home_of_an_unknown_user_is_one_line(arguments, cli, shared_data, tmp_path):
    """pathlib raises RuntimeError on '~name' of a user it cannot find: a traceback from the option
    identity, the vocabulary parser or the dataset loader."""
    images = [shared_data / "corridor" / "ref" / "0000000.jpg"] if arguments[0] == "describe" else []
    # a data root only where a dataset is looked up by name (one no route uses is refused first)
    where = ["--out", tmp_path / "o.npy"] if arguments[0] == "describe" else \
        ["--data-dir", shared_data] if "corridor" in arguments else []
    code, _, err = cli(*arguments, *where, "--cache-dir", tmp_path / "cache", *images)
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines()[-1].endswith("give the path in full, or ~/... for your own home folder.")


def test_the_paper_table_after_a_run_shows_no_result_of_another_copy(corridor_copy, shared_data, tmp_path):
    """The run and its dry run judge a record by the data at hand (StoredRecords); the table printed after
    the run still took the newest record of the spec, computed on another copy's images."""
    import shutil

    from rich.console import Console

    from vprbench.cli.reproduce import paper_table
    from vprbench.evaluation import evaluate, save_result
    from vprbench.run_settings import RunSettings
    from vprbench.sweep.plan import Cell
    from vprbench.sweep.reproduce import TableCell, table_spec

    cache = tmp_path / "cache"
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=[1, 5], data_dir=shared_data)
    save_result(evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=cache)), cache)
    edited = corridor_copy / "query" / "0000005.jpg"
    edited.unlink()  # a symlink into the shared data: replaced by another image, never written through
    shutil.copyfile(shared_data / "corridor" / "query" / "0000006.jpg", edited)

    def row(data_root) -> str:
        console = Console(width=200, record=True, markup=False)
        console.print(paper_table(table_spec("anyloc", "6"), [TableCell("hog", "baidu-mall", [Cell(spec)])],
                                  RunSettings(data_dir=data_root, cache_dir=cache)))
        return next(line for line in console.export_text().splitlines() if "│ hog" in line)

    assert "not measured" not in row(shared_data).split("│")[2]
    assert row(corridor_copy.parent).split("│")[2].strip() == "- / not measured"
