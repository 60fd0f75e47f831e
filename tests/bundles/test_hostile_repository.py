"""An import into a results repository whose content is hostile (as a pull request may make it):
links, a record not matching its name, truncated arrays; and hostile bundles at import. Each
gives one line naming the file at fault and exit 1, and nothing outside the repository, or in it,
is changed."""
from __future__ import annotations

import hashlib
import json

import pytest

from bundles.bundle_files import read_bundle, record_names, write_bundle

from vprbench.bundles import export_bundle


@pytest.fixture
def bundles(records, tmp_path):
    return [export_bundle([records[0]], tmp_path / "alice.tar.gz", contributor="alice"),
            export_bundle([records[1]], tmp_path / "bob.tar.gz", contributor="bob")]


def tree(folder) -> dict[str, str]:
    """Every file and link under `folder` (links by target, not followed)."""
    return {p.relative_to(folder).as_posix(): (f"-> {p.readlink()}" if p.is_symlink() else
                                               hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.rglob("*")) if p.is_symlink() or p.is_file()}


def refused(cli, shared_data, *args) -> str:
    code, out, err = cli("results", *args, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in out + err, out + err
    return out + err


@pytest.fixture
def repo(bundles, shared_data, tmp_path, cli):
    """A repository holding alice's run."""
    repo = tmp_path / "repo"
    code, out, err = cli("results", "import", bundles[0], "--into", repo, "--data-dir", shared_data)
    assert code == 0, out + err
    return repo


def _row_of(bundle) -> tuple[str, str]:
    name = record_names(read_bundle(bundle))[0]
    return name.split("/")[0], name.split("/")[1]


@pytest.mark.parametrize("linked", ["protocol", "row", "methods", "pending"])
def test_a_link_in_the_repository_is_refused_and_nothing_is_written_through_it(
        bundles, repo, shared_data, tmp_path, cli, linked):
    """Was: bob's files were written through a linked folder, to wherever it points (outside)."""
    protocol, row = _row_of(bundles[1])
    outside = tmp_path / "outside"
    outside.mkdir()
    place = {"protocol": repo / protocol, "row": repo / protocol / row, "methods": repo / "methods",
             "pending": repo / ".import.pending"}[linked]
    if place.exists():  # alice's folder: moved outside, a link left in its place
        place.rename(outside / place.name)
        place.symlink_to(outside / place.name)
    else:
        place.parent.mkdir(parents=True, exist_ok=True)
        place.symlink_to(outside)
    before, outside_before = tree(repo), tree(outside)
    out = refused(cli, shared_data, "import", bundles[1], "--into", repo)
    lines = out.splitlines()
    assert f"{place} is a link, not a file or folder of the repository; remove it, then import again." in lines[0]
    assert lines[0].startswith(f"{bundles[1]}: ") and lines[1:] == [f"{bundles[1]}: refused; nothing of it was written."]
    assert tree(repo) == before and tree(outside) == outside_before
    link = place.relative_to(repo).as_posix()
    assert f"{repo}: {link} is a link, not a regular file or folder; refused" in refused(cli, shared_data, "verify", repo)


@pytest.mark.parametrize("name", [".import.lock", ".import.lock.holder"])
def test_a_linked_lock_file_is_refused_and_its_target_kept(bundles, repo, shared_data, tmp_path, cli, name):
    """Was: taking the lock through `.import.lock -> victim` emptied the victim (opened to truncate),
    and the holder note was written into what `.import.lock.holder` points to."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (repo / name).unlink(missing_ok=True)
    (repo / name).symlink_to(victim)
    out = refused(cli, shared_data, "import", bundles[1], "--into", repo)
    assert out == f"error: The lock file {repo / name} is a link; remove it (vprbench makes its own), then run again.\n"
    assert victim.read_text() == "precious\n" and len(list(repo.glob("*/*/*.json"))) == 1


def test_a_linked_record_is_not_taken_for_a_duplicate(bundles, repo, shared_data, tmp_path, cli):
    protocol, row = _row_of(bundles[1])
    members = read_bundle(bundles[1])
    name = record_names(members)[0]
    elsewhere = tmp_path / "copy.json"
    elsewhere.write_bytes(members[name])
    (repo / protocol / row).mkdir(parents=True, exist_ok=True)
    (repo / name).symlink_to(elsewhere)
    out = refused(cli, shared_data, "import", bundles[1], "--into", repo)
    assert f"{repo / name} is a link, not a file or folder of the repository" in out.splitlines()[0]


def test_a_record_in_the_repository_not_matching_its_name_is_named(bundles, repo, records, shared_data, cli):
    """A record edited by hand to say another run id than its file name: verify names it; an import
    of the true run is a conflict (the record there is kept as it is)."""
    r = records[0]
    path = repo / r["protocol"]["hash"] / r["row_key"] / f"{r['run_id']}.json"
    edited = json.loads(path.read_text())
    edited["run_id"] = "20300101T000000Z-000000000000"
    path.write_text(json.dumps(edited))
    before = tree(repo)
    out = refused(cli, shared_data, "verify", repo)
    assert f"{repo}: {path.relative_to(repo).as_posix()} (run {r['run_id']}, hog on corridor:vpr-bench): its protocol " \
           "hash, row key and run id" in out
    out = refused(cli, shared_data, "import", bundles[0], "--into", repo)
    assert "another record with this run id is already in" in out.splitlines()[0]
    assert tree(repo) == before


def test_truncated_arrays_in_the_repository_are_named(bundles, repo, records, shared_data, cli):
    r = records[0]
    npz = repo / r["protocol"]["hash"] / r["row_key"] / f"{r['run_id']}.npz"
    npz.write_bytes(npz.read_bytes()[:100])
    out = refused(cli, shared_data, "verify", repo)
    assert [line for line in out.splitlines() if "ok, re-scored" not in line] == [
        f"{repo}: {npz.relative_to(repo).as_posix()[:-4]}.json (run {r['run_id']}, hog on corridor:vpr-bench): "
        f"{npz.relative_to(repo).as_posix()} does not match the sha256 its record gives"]


def test_arrays_left_without_their_record_that_differ_are_not_replaced(bundles, repo, records, shared_data, cli):
    """bob's arrays already there, truncated, without bob's record: the import refuses bob and says
    what to do, rather than keep them (a record whose arrays are not its own) or overwrite them."""
    protocol, row = _row_of(bundles[1])
    members = read_bundle(bundles[1])
    name = record_names(members)[0]
    npz = repo / f"{name[:-5]}.npz"
    npz.parent.mkdir(parents=True, exist_ok=True)
    npz.write_bytes(members[f"{name[:-5]}.npz"][:100])
    before = tree(repo)
    out = refused(cli, shared_data, "import", bundles[1], "--into", repo)
    assert out.splitlines()[0].endswith(f"{npz} is there without its record and holds other arrays (left by a killed "
                                        "import of an older vprbench, or added by hand): remove it, then import again.")
    assert tree(repo) == before


@pytest.mark.parametrize("hostile", ["climbs", "truncated-npz", "content-not-its-name"])
def test_hostile_bundles_at_import_write_nothing(bundles, repo, shared_data, tmp_path, cli, hostile):
    members = read_bundle(bundles[1])
    name = record_names(members)[0]
    npz = f"{name[:-5]}.npz"
    if hostile == "climbs":
        members[f"../{name.split('/')[-1]}"] = members.pop(name)
        expected = "escapes the folder it would be written to; refused."
    elif hostile == "truncated-npz":  # and its sha256 made to match, in the record and the manifest
        members[npz] = members[npz][:200]
        record = json.loads(members[name])
        record["per_query"]["sha256"] = hashlib.sha256(members[npz]).hexdigest()
        members[name] = json.dumps(record).encode()
        expected = f"{npz} is not readable per-query arrays"
    else:  # alice's record under bob's name
        alice = read_bundle(bundles[0])
        members[name] = alice[record_names(alice)[0]]
        expected = "are not its place in the bundle"
    bad = write_bundle(tmp_path / "bad.tar.gz", members)
    before = tree(repo)
    out = refused(cli, shared_data, "import", bad, "--into", repo)
    assert expected in out.splitlines()[0] and out.splitlines()[-1] == f"{bad}: refused; nothing of it was written."
    assert tree(repo) == before


@pytest.mark.parametrize("command", ["verify", "import"])
def test_a_planted_pending_import_moves_nothing_through_a_link(bundles, repo, shared_data, tmp_path, cli, command):
    """A pull request could carry `.import.pending/commit-*/` (which the next import or verify
    finishes) and a linked folder beside it: nothing is moved through the link, outside."""
    protocol, row = _row_of(bundles[1])
    outside = tmp_path / "outside"
    outside.mkdir()
    (repo / protocol / row).symlink_to(outside)  # alice's protocol folder is there; bob's row is not
    planted = repo / ".import.pending" / "commit-1-ab" / protocol / row / "20300101T000000Z-000000000000.json"
    planted.parent.mkdir(parents=True)
    planted.write_text("{}")
    args = ("verify", repo) if command == "verify" else ("import", bundles[1], "--into", repo)
    code, out, err = cli("results", *args, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in out + err, out + err
    assert tree(outside) == {} and not (repo / ".import.pending").exists()
