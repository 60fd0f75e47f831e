"""Bundles, repositories and VPR-Bench folders from a stranger, past test_export_verify,
test_hostile_bundles and hardening/test_bundle_audit: sparse members and a damaged deflate stream,
a manifest or a record whose text is megabytes long, a stage's weights said to be official, and
named pipes where a file is read."""
from __future__ import annotations

import gzip
import hashlib
import json
import os
import random
import tarfile

import pytest
from bundle_files import edit_record, read_bundle, record_names, respec, write_bundle
from special_files import no_hang

from vprbench.bundles import export_bundle
from vprbench.bundles.export import MANIFEST

ROW = "0123456789abcdef/0123456789abcdef"


@pytest.fixture
def bundle(records, tmp_path):
    return export_bundle(records, tmp_path / "runs.tar.gz", contributor="alice")


def _sparse_member(name: str, real_size: int) -> bytes:
    """A GNU sparse member: 512 bytes stored, `real_size` declared; tarfile unpacks the holes as zeros."""
    info = tarfile.TarInfo(name)
    info.type, info.size = tarfile.GNUTYPE_SPARSE, 512
    header = bytearray(info.tobuf(format=tarfile.GNU_FORMAT))
    header[386:398], header[398:410] = tarfile.itn(0, 12), tarfile.itn(512, 12)  # one stored block, at 0
    header[482], header[483:495] = 0, tarfile.itn(real_size, 12)
    header[148:156] = b" " * 8
    header[148:156] = b"%06o\0 " % sum(header)
    return bytes(header) + b"x" * 512


def test_sparse_members_are_refused_unpacked(cli, tmp_path):
    """Before: 20 sparse members of 1 MB each (a 300-byte bundle) were unpacked into memory whole, past a
    bound of 1 MiB; at the default bound, a thousand of them asked for a terabyte."""
    raw = b"".join(_sparse_member(f"{ROW}/run{i}.npz", 1_000_000) for i in range(20)) + bytes(1024)
    path = tmp_path / "sparse.tar.gz"
    path.write_bytes(gzip.compress(raw))
    with tarfile.open(path) as archive:  # the attack is real: tarfile gives a megabyte for each
        assert len(archive.extractfile(archive.next()).read()) == 1_000_000
    code, out, err = cli("results", "verify", path, "--max-size", "1")
    assert code == 1 and "Traceback" not in err
    assert out.splitlines() == [f"{path}: member '{ROW}/run0.npz' is a sparse file, not a regular file; refused."]


def test_a_damaged_deflate_stream_is_one_line(cli, tmp_path):
    """Before: damage inside a member's compressed bytes (past the headers) was a zlib traceback of verify and import."""
    info = tarfile.TarInfo(MANIFEST)
    info.size = 40_000
    body = bytes(random.Random(0).choices(b"abcdefgh  ", k=info.size))  # compressible: deflate's own codes
    data = gzip.compress(info.tobuf(format=tarfile.PAX_FORMAT) + body + bytes(1024), mtime=0)
    path = tmp_path / "damaged.tar.gz"
    for at in range(200, len(data) - 40, 7):  # the first damage zlib itself refuses
        damaged = bytearray(data)
        damaged[at:at + 4] = bytes(b ^ 0x5A for b in damaged[at:at + 4])
        path.write_bytes(bytes(damaged))
        try:
            with tarfile.open(fileobj=gzip.open(path), mode="r|") as archive:
                archive.extractfile(archive.next()).read()
        except Exception as error:  # noqa: BLE001 - looking for the one kind
            if type(error).__module__ == "zlib":
                break
    else:
        pytest.skip("no damage made zlib fail here")
    for args in (("verify", path), ("import", path, "--into", tmp_path / "repo")):
        code, out, err = cli("results", *args)
        assert code == 1 and "Traceback" not in err, err
        line = out.splitlines()[0]
        assert line.startswith(f"{path} is not a readable bundle archive (") and "Error -3 while decompressing" in line
    assert not (tmp_path / "repo").exists()


def test_a_manifest_listing_a_million_names_is_one_short_line(cli, tmp_path):
    """Before: each name it listed was said in full, all of them on one line (a line of gigabytes)."""
    files = {f"{'x' * 5000}{i}": {"sha256": "0" * 64} for i in range(200)}
    manifest = json.dumps({"format": "vprbench-bundle", "version": 1, "files": files}).encode()
    path = write_bundle(tmp_path / "listing.tar.gz", {MANIFEST: manifest}, resum=False)
    code, out, err = cli("results", "verify", path)
    assert code == 1 and len(out.splitlines()) == 1 and len(out) < 2000
    assert out.rstrip().endswith("is listed in MANIFEST.json but missing. And 195 more.")


@pytest.mark.parametrize("field", ["protocol id", "protocol name", "method"])
def test_a_claim_megabytes_long_is_cut(bundle, cli, shared_data, tmp_path, field):
    """Before: a record's protocol id, protocol name or label of a megabyte was printed whole, on each of its
    lines (the label leads every line of the record)."""
    members = read_bundle(bundle)
    long = "y" * 1_000_000
    edit = {"protocol id": lambda r: r["protocol"].update(id=long), "protocol name": lambda r: r["protocol"].update(
        name=long), "method": lambda r: r.update(method=long)}[field]
    edit_record(members, edit)
    path = write_bundle(tmp_path / "long.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in err
    assert f"it says {field} 'yyy" in out and max(map(len, out.splitlines())) < 1000


def test_a_stage_on_a_weights_file_said_to_be_official_is_refused(bundle, cli, shared_data, tmp_path):
    """A stage names its weights file by sha256 (as a method does); one that is no authors' release is the
    user's, and marks the row. Before: a record saying 'official' for it was 'ok' and its row read as official."""
    members = read_bundle(bundle)
    user_file = "sha256:" + hashlib.sha256(b"my own checkpoint").hexdigest()

    def staged(record):
        record["spec"]["stages"] = [{"name": "rerank-plugin", "options": {"k": 10, "weights": "/me/ckpt.pth"},
                                     "files": {"weights": user_file}}]
        record["stages"] = [{"name": "rerank-plugin", "provenance": {"weights": {"source": "official"}}}]
    respec(members, staged)
    path = write_bundle(tmp_path / "stage.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in err
    assert (f"it says stage rerank-plugin weights source 'official', but its weights file {user_file[:19]} says "
            "'user'") in out


def test_a_named_pipe_among_vpr_bench_files_is_refused_not_read(cli, shared_data, tmp_path):
    """Before: the import waited for a writer to the pipe, for ever."""
    folder = tmp_path / "Corridor" / "Thumbs"
    folder.mkdir(parents=True)
    os.mkfifo(folder / "precomputed_data_corrected.npy")
    with no_hang(20):
        code, out, err = cli("results", "import-vpr-bench", folder.parent, "--dataset", "corridor",
                             "--data-dir", shared_data, "--cache-dir", tmp_path / "cache")
    assert code == 1 and "Traceback" not in err
    assert "is not a regular file (a named pipe, device or socket)" in out + err
    assert not (tmp_path / "cache" / "results").exists()


def test_a_named_pipe_in_a_repository_is_named_and_hangs_no_import(bundle, records, cli, shared_data, tmp_path):
    """Before: verify passed over a pipe where a record belongs (as if nothing were there), and an import of
    that run waited for a writer to it, for ever."""
    repo = tmp_path / "repo"
    name = record_names(read_bundle(bundle))[0]
    (repo / name).parent.mkdir(parents=True)
    os.mkfifo(repo / name)
    with no_hang(20):
        code, out, err = cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in err
    assert f"{repo / name} is a named pipe, device or socket, not a file; remove it, then import again." in out
    os.unlink(repo / name)
    assert cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)[0] == 0
    os.mkfifo(repo / f"{name.rsplit('/', 1)[0]}/{'0' * 16}.json")
    with no_hang(20):
        code, out, err = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 1 and f"{'0' * 16}.json is not a regular file (a folder, named pipe, device or socket)" in out


@pytest.mark.parametrize("edit, part", [
    (lambda r: r.update(provenance="official"), "its provenance is a JSON str, not a table"),
    (lambda r: r["provenance"].update(weights="official"), "its provenance.weights is a JSON str, not a table"),
    (lambda r: r["provenance"].update(weights={"source": ["official"]}),
     "its provenance.weights.source is a JSON list, not a name"),
    (lambda r: r["provenance"].update(vocabulary="map"), "its provenance.vocabulary is a JSON str, not a table"),
    (lambda r: r.update(stages=[{"name": "x", "provenance": "official"}]),
     "its stages[0].provenance is a JSON str, not a table"),
], ids=["provenance", "weights", "source", "vocabulary", "stage"])
def test_provenance_that_is_no_table_is_named_not_a_traceback(bundle, cli, shared_data, tmp_path, edit, part):
    """The row's name and marks are read from these parts. Before: each was a traceback of verify and import."""
    members = read_bundle(bundle)
    edit_record(members, edit)
    path = write_bundle(tmp_path / "shapeless.tar.gz", members)
    for args in (("verify", path), ("import", path, "--into", tmp_path / "repo")):
        code, out, err = cli("results", *args, "--data-dir", shared_data)
        assert code == 1 and "Traceback" not in err and part in out, (out, err)
    assert not (tmp_path / "repo").exists()


@pytest.mark.parametrize("encode", [lambda text: text.encode("utf-16"), lambda text: text.encode("utf-8-sig")],
                         ids=["utf-16", "utf-8-bom"])
def test_a_record_no_reader_of_a_repository_reads_is_refused(bundle, cli, shared_data, tmp_path, encode):
    """Records are read as UTF-8 (read_record, the site). Before: one in UTF-16, or with a byte order mark, was
    'ok' and imported (json.loads of bytes takes both), then left out of the site with a warning."""
    members = read_bundle(bundle)
    name = record_names(members)[0]
    members[name] = encode(members[name].decode("utf-8"))
    path = write_bundle(tmp_path / "encoded.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 1 and f"{path}: {name} (run " in out and ": not JSON (" in out


def test_a_contribution_note_written_by_hand_is_shown_cut_to_one_line(bundle, shared_data, tmp_path):
    """A pull request can carry a note of its own beside a run. Before: its contributor was taken whole (a
    megabyte on every page naming the run) with its line breaks."""
    from vprbench.bundles import import_bundles, read_repository
    from vprbench.evaluation.rescore import DataGroundTruth

    repo = tmp_path / "repo"
    assert all(r.ok for r in import_bundles([bundle], repo, DataGroundTruth(shared_data)))
    note = sorted(repo.glob("*/*/*.contribution"))[0]
    note.write_text(json.dumps({"contributor": "mallory\n" + "m" * 1_000_000, "imported": "2026-01-01"}))
    shown = [r["_contribution"]["contributor"] for r in read_repository(repo)]
    assert "mallory\\n" + "m" * 191 in shown and max(map(len, shown)) == 200


@pytest.mark.parametrize("edit, said", [
    (lambda r: r["spec"].update(stages=[{"name": "aqe", "options": {"k": 10}}]), "'single-image', but its spec "
     "(its stages) says 're-ranked'"),
    (lambda r: r.update(track="sequence"), "'sequence', but its spec (its stages) says 'single-image'"),
    (lambda r: r.update(stages=[{"name": "x"}], track="single-image") or r["spec"].update(
        stages=[{"name": "not-installed-here", "options": {}}]), "'single-image', but its spec (its stages) says "
     "'re-ranked or sequence'"),
], ids=["re-ranked-as-single-image", "single-image-as-sequence", "stage-not-installed"])
def test_a_record_placing_itself_in_another_track_is_refused(bundle, cli, shared_data, tmp_path, edit, said):
    """The track is the table a run's numbers land in (a re-ranked run among single-image ones outranks them
    with work they did not do). Before: it was taken as the record said it."""
    members = read_bundle(bundle)
    respec(members, edit)
    path = write_bundle(tmp_path / "track.tar.gz", members)
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in err and f"it says track {said}" in out, out
