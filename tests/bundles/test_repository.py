"""The results repository: verified bundles merged by identity, tampered ones refused with nothing
written, duplicates recognised, two imports at once both whole, and what the site reads back."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
from bundle_files import read_bundle, record_names, write_bundle

from vprbench.bundles import export_bundle, import_bundles, read_repository
from vprbench.evaluation.rescore import DataGroundTruth
from vprbench.cli.main import main
from vprbench.errors import VPRBenchError


@pytest.fixture
def truth(shared_data):
    return DataGroundTruth(shared_data)


@pytest.fixture
def bundles(records, tmp_path):
    """Two contributors, one run each."""
    return [export_bundle([records[0]], tmp_path / "alice.tar.gz", contributor="alice"),
            export_bundle([records[1]], tmp_path / "bob.tar.gz", contributor="bob")]


def snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
            and not p.name.startswith(".import.lock")} if folder.exists() else {}


def tampered(bundle, path):
    members = read_bundle(bundle)
    name = record_names(members)[0]
    record = json.loads(members[name])
    record["recall"]["1"] = 90.0
    members[name] = json.dumps(record).encode()
    return write_bundle(path, members)


def test_round_trip_two_contributors_one_tampered(bundles, records, truth, tmp_path):
    repo = tmp_path / "repo"
    bad = tampered(bundles[1], tmp_path / "mallory.tar.gz")
    reports = import_bundles([bundles[0], bad], repo, truth)
    assert reports[0].ok and reports[0].added == [records[0]["run_id"]]
    assert not reports[1].ok and reports[1].added == []
    assert any("R@1 is 90.0 in the record but" in line for line in reports[1].lines())
    assert reports[1].lines()[-1].endswith("refused; nothing of it was written.")
    found = read_repository(repo)
    assert [r["run_id"] for r in found] == [records[0]["run_id"]]
    before = snapshot(repo)
    assert import_bundles([bad], repo, truth)[0].problems  # refused again: the repository is unchanged
    assert snapshot(repo) == before
    assert import_bundles([bundles[1]], repo, truth)[0].ok
    found = {r["run_id"]: r for r in read_repository(repo)}
    assert {r["_contribution"]["contributor"] for r in found.values()} == {"alice", "bob"}
    for record in records:
        sent = found[record["run_id"]]["_contribution"]
        assert sent["date"] == record["created"] and sent["version"] == record["versions"]["vprbench"]
        assert sent["hardware"] == record["hardware"] and sent["imported"]
        assert found[record["run_id"]]["recall"] == record["recall"]
    layout = {str(p) for p in snapshot(repo)}
    r = records[0]
    assert {f"{r['protocol']['hash']}/{r['row_key']}/{r['run_id']}.json", f"methods/{r['row_key']}.json",
            "LAYOUT"} <= layout


def test_a_failing_bundle_writes_nothing_not_even_the_folder(bundles, truth, tmp_path):
    repo = tmp_path / "new-repo"
    report = import_bundles([tampered(bundles[0], tmp_path / "t.tar.gz")], repo, truth)[0]
    assert not report.ok and not repo.exists()


def test_duplicates_by_identity_and_by_content(bundles, records, truth, tmp_path):
    repo = tmp_path / "repo"
    import_bundles([bundles[0]], repo, truth)
    again = import_bundles([bundles[0]], repo, truth)[0]
    assert again.ok and again.added == [] and again.duplicates == [records[0]["run_id"]]
    # the same result under another run id (exported again after a rename): recognised by content
    members = read_bundle(bundles[0])
    name = record_names(members)[0]
    record = json.loads(members[name])
    old, new = record["run_id"], "20300101T000000Z-renamed"
    folder = name.rsplit("/", 1)[0]
    record["run_id"], record["per_query"]["file"] = new, f"{new}.npz"
    members[f"{folder}/{new}.npz"] = members.pop(f"{folder}/{old}.npz")
    del members[name]
    members[f"{folder}/{new}.json"] = json.dumps(record).encode()
    renamed = import_bundles([write_bundle(tmp_path / "renamed.tar.gz", members)], repo, truth)[0]
    assert renamed.ok and renamed.added == [] and renamed.duplicates == [f"{new} = {old}"]
    assert len(read_repository(repo)) == 1


def test_another_record_under_a_run_id_already_there_is_a_conflict(bundles, records, truth, tmp_path):
    repo = tmp_path / "repo"
    import_bundles([bundles[0]], repo, truth)
    members = read_bundle(bundles[0])
    name = record_names(members)[0]
    record = json.loads(members[name])
    record["run"]["device"] = "cuda:7"  # still sound, but not the record already there
    members[name] = json.dumps(record).encode()
    before = snapshot(repo)
    report = import_bundles([write_bundle(tmp_path / "c.tar.gz", members)], repo, truth)[0]
    assert not report.ok and "another record with this run id is already in" in report.problems[0]
    assert snapshot(repo) == before


def test_a_repository_of_a_newer_layout_is_refused(bundles, truth, tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    (repo / "LAYOUT").write_text(json.dumps({"layout": "vprbench-results", "version": 9}))
    with pytest.raises(VPRBenchError, match="written by another vprbench"):
        import_bundles([bundles[0]], repo, truth)
    with pytest.raises(VPRBenchError, match="does not exist"):
        read_repository(tmp_path / "nowhere")


def test_two_imports_at_once_both_land_whole(bundles, records, shared_data, tmp_path):
    repo = tmp_path / "repo"
    command = [sys.executable, "-m", "vprbench", "results", "import", "--into", str(repo), "--data-dir",
               str(shared_data), "--cache-dir", str(tmp_path / "cache")]
    running = [subprocess.Popen([*command, str(b)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for b in bundles]
    outputs = [p.communicate(timeout=300) for p in running]
    assert [p.returncode for p in running] == [0, 0], outputs
    assert sorted(r["run_id"] for r in read_repository(repo)) == sorted(r["run_id"] for r in records)
    assert not list(repo.rglob("*.tmp"))


def test_cli_import_exit_codes(bundles, shared_data, tmp_path, capsys):
    repo = tmp_path / "repo"
    bad = tampered(bundles[1], tmp_path / "bad.tar.gz")
    assert main(["results", "import", str(bundles[0]), str(bad), "--into", str(repo),
                 "--data-dir", str(shared_data)]) == 1
    out = capsys.readouterr().out
    assert "alice.tar.gz: 1 run(s) added" in out and "bad.tar.gz: refused; nothing of it was written." in out
    assert main(["results", "import", str(bundles[0]), "--into", str(repo), "--data-dir", str(shared_data)]) == 0
    assert "0 run(s) added, 1 already there" in capsys.readouterr().out
    assert main(["results", "verify", str(bundles[0]), "--max-size", "0"]) == 1
    assert "--max-size takes a positive number" in capsys.readouterr().err


def test_verify_a_repository_rescores_every_run_however_it_got_there(bundles, records, shared_data, tmp_path, capsys):
    """What a repository's CI runs on a pull request: a record edited by hand in the folder (not
    through an import) is caught, as are links and files out of place."""
    repo = tmp_path / "repo"
    assert all(r.ok for r in import_bundles(bundles, repo, DataGroundTruth(shared_data)))
    command = ["results", "verify", str(repo), "--data-dir", str(shared_data)]
    assert main(command) == 0
    assert capsys.readouterr().out.count(": ok, re-scored from its arrays") == 2
    r = records[0]
    path = repo / r["protocol"]["hash"] / r["row_key"] / f"{r['run_id']}.json"
    edited = json.loads(path.read_text())
    edited["recall"]["1"] = 99.0
    path.write_text(json.dumps(edited))
    (repo / "notes" / "misc").mkdir(parents=True)
    (repo / "notes" / "misc" / "stray.json").write_text("{}")
    link = repo / r["protocol"]["hash"] / r["row_key"] / "20300101T000000Z-link.json"
    link.symlink_to(path)
    assert main(command) == 1
    lines = capsys.readouterr().out.splitlines()
    member = path.relative_to(repo).as_posix()
    assert f"{repo}: {member} (run {r['run_id']}, hog on corridor:vpr-bench): R@1 is 99.0 in the record but " \
           f"{records[0]['recall']['1']:.6f} from its arrays" in lines
    assert f"{repo}: {link.relative_to(repo).as_posix()} is a link, not a regular file; refused." in lines
    assert f"{repo}: notes/misc/stray.json is not where a results repository keeps a record (<protocol hash>/" \
           "<row key>/<run id>.json); move or remove it." in lines
    assert sum(": ok, re-scored" in line for line in lines) == 1
