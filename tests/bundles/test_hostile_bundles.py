"""Bundles from a stranger, past what test_export_verify and hardening/test_bundle_audit cover:
recall keys that are no K, a record naming another copy of the dataset, names holding line
breaks and control characters, and an import killed between two of its writes."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ElementTree

import pytest

from bundles.bundle_files import edit_record, read_bundle, record_names, respec, write_bundle

from vprbench.bundles import export_bundle, import_bundles, verify_repository
from vprbench.evaluation.rescore import DataGroundTruth


@pytest.fixture
def bundle(records, tmp_path):
    return export_bundle(records, tmp_path / "runs.tar.gz", contributor="alice")


def refused(cli, shared_data, path, repo, message: str) -> None:
    """verify and import both refuse `path` with `message` on the record's line, no traceback, nothing written."""
    for args in (("verify", path), ("import", path, "--into", repo)):
        code, out, err = cli("results", *args, "--data-dir", shared_data)
        assert code == 1 and "Traceback" not in out + err, (out, err)
        assert any(line.startswith(f"{path}: ") and message in line for line in out.splitlines()), out
    assert not repo.exists()


def _rename(old: str, new: str):
    return lambda r: r["recall"].update({new: r["recall"].pop(old)})


@pytest.mark.parametrize("edit, key", [
    (_rename("1", " 1"), " 1"), (lambda r: r["recall"].update(abc=5.0), "abc"),
    (lambda r: r["recall"].update({"0": 0.0}), "0"), (lambda r: r["recall"].update({"01": 99.0}), "01"),
    (lambda r: r["recall"].update({"9" * 5000: 1.0}), "9" * 20),
], ids=["space", "word", "zero", "leading-zero", "5000-digits"])
def test_recall_keys_that_are_no_k_are_named(bundle, cli, shared_data, tmp_path, edit, key):
    """Before: ' 1', 'abc' and 5000 digits were tracebacks of verify and import; '0' and '01' (R@1
    claimed 99) were 'ok, re-scored' and imported, '01' never compared with the arrays."""
    members = read_bundle(bundle)
    edit_record(members, edit)
    path = write_bundle(tmp_path / "keys.tar.gz", members)
    refused(cli, shared_data, path, tmp_path / "repo", f"its recall has key {key!r}, not a K (a whole number from 1")


@pytest.mark.parametrize("edit, wrong", [
    (lambda r: r.update(dataset_fingerprint="f" * 16), "dataset"),
    (lambda r: r["dataset_fingerprints"]["images"].update(queries="0" * 64), "images"),
    (lambda r: r.pop("dataset_fingerprint"), "dataset"),
], ids=["fingerprint", "images", "none"])
def test_a_record_naming_another_copy_of_the_dataset_is_refused(bundle, cli, shared_data, tmp_path, edit, wrong):
    """Before: 'ok' and imported. The board keeps the copy of a column's data most runs name (the
    newest on a tie): one forged record, dated later, pushed this machine's true run of the same
    row out of Corridor's column as 'another copy of its images'."""
    members = read_bundle(bundle)
    edit_record(members, edit)
    path = write_bundle(tmp_path / "copy.tar.gz", members)
    refused(cli, shared_data, path, tmp_path / "repo",
            f"its dataset fingerprint ({wrong}) is not that of the copy of corridor here (")


def test_a_0_2_record_on_this_copy_of_the_dataset_is_not_called_another_copy(bundle, cli, shared_data, tmp_path):
    """0.2 hashed a dataset's fingerprint another way; the upgrade recomputes the top-level one from the
    parts but leaves the parts' own "dataset" as 0.2 wrote it. Before: verify compared that copy too and
    refused a 0.2 record run on this very data as naming 'another copy' of it."""
    def as_0_2(record):
        options = record["spec"]["options"]
        for key in ("spec", "spec_key", "row_key", "served_from_store", "run"):
            record.pop(key, None)
        record.update(schema_version=2, method_settings=options, method_options=options)
        record["dataset_fingerprint"] = record["dataset_fingerprints"]["dataset"] = "0" * 16  # 0.2's hash

    members = read_bundle(bundle)
    name = edit_record(members, as_0_2)
    path = write_bundle(tmp_path / "old.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 0 and "Traceback" not in err, out
    recall = json.loads(members[name])["recall"]
    [line] = [line for line in out.splitlines() if line.startswith(f"{path}: {name} (run ")]
    assert f": ok, re-scored from its arrays: R@1 {recall['1']:.1f} R@5 " in line, line
    edit_record(members, lambda r: r["dataset_fingerprints"]["images"].update(queries="0" * 64))  # still checked
    path = write_bundle(tmp_path / "old-forged.tar.gz", members)
    refused(cli, shared_data, path, tmp_path / "repo", "its dataset fingerprint (dataset, images) is not that of the copy")


def test_a_name_with_line_breaks_and_control_characters_forges_no_line_and_breaks_no_figure(
        bundle, records, cli, shared_data, tmp_path):
    """A method of a plugin not installed here is re-scored like any (its name is its spec's), but
    its name comes from a stranger. Before: a line break in it printed a verdict line of its own
    ('FAKE: ok'), and an escape character reached the site's SVG figures, which then were no XML
    (every figure of the dataset page and the radar failed to open)."""
    members = read_bundle(bundle)
    name = respec(members, lambda r: r["spec"].update(method="plug\x1b[2J\rin\nFAKE: ok"))
    path = write_bundle(tmp_path / "names.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 0 and "Traceback" not in err
    assert len(out.splitlines()) == len(record_names(members)) and "\nFAKE" not in out
    assert f"{name} (run {records[0]['run_id']}, plug\\x1b[2J\\x0din\\nFAKE: ok on corridor:vpr-bench): ok" in out
    repo, docs = tmp_path / "repo", tmp_path / "docs"
    assert cli("results", "import", path, "--into", repo, "--data-dir", shared_data)[0] == 0
    code, _, err = cli("leaderboard", "publish", "--to", docs, "--results", repo, "--cache-dir", tmp_path / "empty")
    assert code == 0, err
    figures = sorted((docs / "leaderboard" / "figures").glob("*.svg"))
    assert len(figures) >= 4
    for figure in figures:
        ElementTree.parse(figure)  # raises on a character XML does not allow


class Killed(BaseException):
    """Stands for a kill -9 between two steps (not an Exception: nothing catches it)."""


def test_an_import_killed_between_any_two_steps_leaves_a_sound_repository(bundle, records, shared_data, tmp_path,
                                                                          monkeypatch):
    """Every step of an import's commit (each staged file, the one rename that commits, each move
    after it) is a place it may die. Was: files written one by one to their places, so a kill left
    arrays, notes and cards no record used, which no later import or verify removed."""
    import vprbench.bundles.commit as commit

    truth, steps = DataGroundTruth(shared_data), []
    real = {"_write": commit._write, "_rename": commit._rename}

    def dies_at(count):
        def step(name):
            def run(*args):
                if len(steps) == count:
                    raise Killed
                steps.append((name, args[-1]))
                return real[name](*args)
            return run
        for name in real:
            monkeypatch.setattr(commit, name, step(name))

    files = 4 * len(records)  # two rows: per run its card, arrays, contribution note and record
    total = files + 1 + files  # staged, the commit, moved
    for count in range(total):
        steps.clear()
        repo = tmp_path / f"repo-{count}"
        dies_at(count)
        with pytest.raises(Killed):
            import_bundles([bundle], repo, truth)
        monkeypatch.undo()
        runs = sorted(repo.glob("*/*/*.json"))
        assert len(runs) == (0 if count <= files else max(0, count - 2 * files - 1 + len(records))), count
        for path in runs:  # what readers see: a record only with its arrays and card
            assert path.with_suffix(".npz").is_file() and (repo / "methods" / f"{path.parent.name}.json").is_file()
        [again] = import_bundles([bundle], repo, truth)  # undoes or finishes the killed one, under the lock
        assert again.ok and len(again.added) + len(again.duplicates) == len(records), again.lines()
        report = verify_repository(repo, truth)
        assert report.ok and {v.run_id for v in report.verdicts} == {r["run_id"] for r in records}, report.lines()
        left = sorted(p.relative_to(repo).as_posix() for p in repo.rglob("*") if p.is_file())
        assert left == sorted(["LAYOUT", ".import.lock", *(n for r in records for n in _files(r))]), (count, left)
    steps.clear()
    dies_at(total + 1)
    import_bundles([bundle], tmp_path / "whole", truth)
    assert len(steps) == total and steps[files] == ("_rename", steps[files][1])  # every point was tried
    assert steps[-1][1].name == f"{records[-1]['run_id']}.json"


def _files(record) -> list[str]:
    folder = f"{record['protocol']['hash']}/{record['row_key']}/{record['run_id']}"
    return [f"{folder}.json", f"{folder}.npz", f"{folder}.contribution", f"methods/{record['row_key']}.json"]


def test_a_contributor_that_is_no_utf8_text_is_kept_as_escapes_and_the_site_is_built(bundle, shared_data, tmp_path):
    """A manifest's contributor '\\udcff' (JSON can say it, UTF-8 cannot hold it) was imported as it was,
    and 'leaderboard publish' then died writing its CSV: UnicodeEncodeError ... surrogates not allowed."""
    from bundles.bundle_files import MANIFEST
    from vprbench.cli.main import main

    members = read_bundle(bundle)
    manifest = json.loads(members[MANIFEST])
    manifest["contributor"] = "eve\udcff\x1b[2J"
    members[MANIFEST] = json.dumps(manifest).encode()  # ensure_ascii: '\udcff' is written as its escape
    forged = write_bundle(tmp_path / "forged.tar.gz", members)
    repo, docs = tmp_path / "repo", tmp_path / "docs"
    assert all(r.ok for r in import_bundles([forged], repo, DataGroundTruth(shared_data)))
    assert main(["leaderboard", "publish", "--to", str(docs), "--results", str(repo), "--cache-dir", str(tmp_path / "c")]) == 0
    assert "eve\\udcff\\x1b[2J" in (docs / "leaderboard" / "downloads" / "corridor.csv").read_text(encoding="utf-8")


@pytest.mark.parametrize("contributor", ["", "   ", "a\udcffb", "a\x1b]0;owned\x07", "two\nlines", "a" * 201])
def test_a_contributor_that_is_not_a_name_is_refused_before_the_bundle_is_written(store, cli, tmp_path, contributor):
    """Each was written into the bundle (a '\\udcff' from a command-line argument of bytes that are not UTF-8
    then failed the site's writing wherever it was imported)."""
    to = tmp_path / "runs.tar.gz"
    code, out, err = cli("results", "export", "--method", "hog", "--dataset", "corridor", "--to", to,
                         "--contributor", contributor, "--cache-dir", store)
    assert code == 1 and "Traceback" not in err and "is not a name: give text of at most 200 characters" in err, err
    assert len(err.strip().splitlines()) == 1 and not to.exists()
