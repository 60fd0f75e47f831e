"""Text from data prints as it is on the terminal: Rich markup and emoji codes in a name are shown,
not interpreted, and control characters (escape sequences, bells, carriage returns) are written out
as escapes, never acted on. The names come from a stored record (a method option), a dataset's own
dataset.toml and a plugin; the test first shows that Rich, as configured by default, interprets
all three kinds."""
from __future__ import annotations

import io
import json

import pytest
import torch
from rich.console import Console
from rich.table import Table

from vprbench import register_method
from vprbench.evaluation import read_results
from vprbench.spec import RunSpec

from hostile_files import tiny_images

MARKUP = "[bold red]x[/] :pile_of_poo: [link=javascript:alert(1)]y[/link]"
CONTROLS = "\x1b]0;owned\x07\x1b[2J\rz"
HOSTILE_ROW = f"hog [note={MARKUP} {CONTROLS} resize=16x16]"
#: how the terminal must show CONTROLS
SHOWN = "\\x1b]0;owned\\x07\\x1b[2J\\x0dz"


def test_the_attack_is_real_in_rich_by_default():
    table = Table()
    table.add_column("method")
    table.add_row(f"hog [note={MARKUP} {CONTROLS}]")
    out = io.StringIO()
    Console(file=out, width=300).print(table)
    printed = out.getvalue()
    assert "[bold red]" not in printed and "[link=" not in printed, "markup swallowed"
    assert ":pile_of_poo:" not in printed and "\U0001f4a9" in printed, "an emoji code turned into an emoji"
    assert "\x1b]0;owned" in printed and "\x1b[2J" in printed, "escape sequences reach the terminal"


@pytest.fixture
def hostile_run(shared_data, tmp_path, cli):
    """Two hog runs on Corridor; one record rewritten as an attacker would, with a method option
    holding markup and control characters (its keys recomputed, so the record reads as valid)."""
    cache = tmp_path / "cache"
    for size in (16, 24):
        assert cli("evaluate", "--method", "hog", "--resize", size, size, "--k", 1, 5, "--dataset", "corridor",
                   "--data-dir", shared_data, "--cache-dir", cache)[0] == 0
    record = read_results(cache)[0]
    path = next(p for p in (cache / "results").rglob(f"{record['run_id']}.json"))
    stored = json.loads(path.read_text())
    for part in (stored["spec"]["given"], stored["spec"]["options"]):
        part["note"] = f"{MARKUP} {CONTROLS}"
    spec = RunSpec.model_validate(stored["spec"])
    stored.update(spec_key=spec.key, row_key=spec.row_key, label=spec.label())
    path.write_text(json.dumps(stored))
    return cache


def assert_literal(output: str) -> None:
    assert MARKUP in output and SHOWN in output, output
    assert "\x1b" not in output and "\x07" not in output and "\r" not in output


def test_names_from_records_print_literally(hostile_run, cli, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")
    for args in (["leaderboard"], ["leaderboard", "--format", "markdown"], ["leaderboard", "--format", "csv"],
                 ["leaderboard", "compare", HOSTILE_ROW, "hog [resize=24x24]", "--dataset", "corridor"]):
        code, out, err = cli(*args, "--cache-dir", hostile_run)
        assert code == 0, err
        assert_literal(out)
    code, out, _ = cli("leaderboard", "--format", "json", "--cache-dir", hostile_run)
    assert HOSTILE_ROW in [cell["row"] for cell in json.loads(out)]  # JSON escapes its way
    code, _, err = cli("leaderboard", "compare", "nothing", "hog", "--dataset", "corridor", "--cache-dir", hostile_run)
    assert code == 1 and "Rows on corridor:" in err  # the error line names the rows
    assert_literal(err)


def test_dataset_texts_and_plugin_descriptions_print_literally(tmp_path, cli, monkeypatch, scratch_methods):
    root = tmp_path / "mine"
    tiny_images(root / "database", ["0.png", "1.png"])
    tiny_images(root / "queries", ["q.png"])
    (root / "positions.csv").write_text("image,x,y\ndatabase/0.png,0,0\ndatabase/1.png,100,0\nqueries/q.png,1,0\n")
    (root / "dataset.toml").write_text(f'title = "{MARKUP}"\ndomain = "{MARKUP}"\n')  # controls: refused there
    monkeypatch.setenv("COLUMNS", "300")
    code, out, _ = cli("datasets", "info", root)
    assert code == 0 and out.count(MARKUP) >= 2, out

    register_method("colorhist", "vprbench.methods.hog:HOG", description=f"{MARKUP} {CONTROLS}")
    code, out, _ = cli("methods", "list")
    assert code == 0
    assert_literal(out)


def test_a_vocabulary_files_metadata_prints_one_line_per_item(tmp_path, cli):
    """`vocabulary show` and `list` print a hand-made file's metadata as one line per item: a newline in a
    value cannot forge a line, control characters are written out, a huge value is cut, and metadata
    lacking what a fit writes beside it (features_used without features_seen) is no traceback."""
    from vprbench.aggregation import Vocabulary

    forged = f"/x\n  fake: line {CONTROLS}"
    meta = {"folder": forged, "imported_from": forged, "datasets": {forged: 3}, f"key\n{CONTROLS}": "v",
            "source": "x" * 100_000, "features_used": 5, "image_digests": b"\0" * 33}
    folder = tmp_path / "cache" / "vocabularies" / "dino_vits8-l11-value-c2" / "mine"
    Vocabulary(torch.zeros(2, 4), meta).save(folder / "vocabulary.pt")
    shown = []
    for args in (["show", folder / "vocabulary.pt"], ["list", "--cache-dir", tmp_path / "cache"]):
        code, out, err = cli("vocabulary", *args)
        assert code == 0, err
        assert SHOWN in out and "\x1b" not in out and "\r" not in out and "\n  fake" not in out, out
        assert len(out) < 5_000, len(out)
        shown.append(out)
    assert "image_digests: 33 bytes, not whole sha256" in shown[0]  # not counted as one image's


def test_text_from_data_in_another_encoding_is_written_out_so_it_can_be_shown_and_written():
    """A name of bytes that are not UTF-8 (a folder, a command-line argument) arrives holding lone
    surrogates; shown or written as they are they fail (UnicodeEncodeError), as a contributor's did."""
    from vprbench.leaderboard.escape import text
    from vprbench.text import literal

    name = "caf\udce9"
    assert literal(name) == "caf\\udce9" and text(name) == "caf\\udce9"
    text(name).encode("utf-8")  # what a page takes


def test_a_messages_first_clause_ends_with_no_period_nor_open_parenthesis():
    # was: "Folder /d does not exist." when its period stood before the parenthesis the cut left open
    from vprbench.text import first_clause

    assert first_clause("Folder /d does not exist. (closest existing folder: /)") == "Folder /d does not exist"
    assert first_clause("Folder /d does not exist (closest existing folder: /).") == "Folder /d does not exist"
    assert first_clause("Dataset 'x' is not in the data root /d.") == "Dataset 'x' is not in the data root /d"
