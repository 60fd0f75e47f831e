"""Bundles: exported from a real results store, re-scored against the real Corridor ground truth,
and every kind of tampering or hostile archive refused with a line naming the file and the record."""
from __future__ import annotations

import gzip
import io
import json
import tarfile

import numpy as np
import pytest
from bundle_files import edit_arrays, edit_record, read_bundle, record_names, write_bundle

from vprbench.bundles import export_bundle, select_records, verify_bundle
from vprbench.bundles.export import MANIFEST
from vprbench.evaluation.rescore import DataGroundTruth
from vprbench.cli.main import main
from vprbench.errors import VPRBenchError


@pytest.fixture
def truth(shared_data):
    return DataGroundTruth(shared_data)


@pytest.fixture
def bundle(records, tmp_path):
    return export_bundle(records, tmp_path / "runs.tar.gz", contributor="alice")


def test_export_holds_records_arrays_cards_and_sums_only(bundle, records):
    members = read_bundle(bundle)
    manifest = json.loads(members[MANIFEST])
    assert manifest["contributor"] == "alice" and sorted(manifest["runs"]) == sorted(r["run_id"] for r in records)
    assert set(manifest["files"]) == set(members) - {MANIFEST}
    assert len(record_names(members)) == 2
    assert sum(n.endswith(".npz") for n in members) == 2 and sum(n.startswith("methods/") for n in members) == 2
    assert not [n for n in members if n.endswith((".jpg", ".png", ".h5", ".npy"))]  # no images, no descriptors
    for record in records:  # byte for byte what the store holds
        folder = f"{record['protocol']['hash']}/{record['row_key']}"
        assert members[f"{folder}/{record['run_id']}.json"] == open(record["_source"], "rb").read()


def test_select_by_run_or_by_method_and_dataset(records):
    assert [r["run_id"] for r in select_records(records, run_ids=[records[1]["run_id"]])] == [records[1]["run_id"]]
    assert len(select_records(records, method="hog", dataset="corridor")) == 2
    assert len(select_records(records, method="hog [resize=96x128]", dataset="corridor")) == 1
    with pytest.raises(VPRBenchError, match="No stored run of 'hog' on 'nordland'"):
        select_records(records, method="hog", dataset="nordland")
    with pytest.raises(VPRBenchError, match="No stored run 'nope'"):
        select_records(records, run_ids=["nope"])
    with pytest.raises(VPRBenchError, match="not both"):
        select_records(records, run_ids=["x"], method="hog", dataset="corridor")


def test_verify_rescores_each_record_against_the_shipped_ground_truth(bundle, records, truth):
    report = verify_bundle(bundle, truth)
    assert report.ok, report.lines()
    by_id = {r["run_id"]: r for r in records}
    assert len(report.verdicts) == 2
    for verdict in report.verdicts:
        assert verdict.recall == pytest.approx(by_id[verdict.run_id]["recall"], abs=1e-4)
        assert set(verdict.recall) == {"1", "5", "10", "20"}
    assert all(": ok, re-scored from its arrays: R@1 " in line for line in report.lines())


def _only_failure(report, name):
    failed = [v for v in report.verdicts if not v.ok]
    assert not report.ok and len(failed) == 1 and failed[0].member == name
    return failed[0].problems


def test_an_edited_recall_is_caught(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = edit_record(members, lambda r: r["recall"].update({"1": r["recall"]["1"] + 10}))
    report = verify_bundle(write_bundle(tmp_path / "tampered.tar.gz", members), truth)
    problems = _only_failure(report, name)
    assert len(problems) == 1 and "R@1 is 58.6" in problems[0] and "but 48.6" in problems[0]
    line = next(line for line in report.lines() if "R@1 is" in line)
    assert str(tmp_path / "tampered.tar.gz") in line and name in line and "run " in line


def test_edited_arrays_are_rescored_not_trusted(bundle, truth, tmp_path):
    members = read_bundle(bundle)

    def better(arrays):  # claim every query's first positive at rank 1
        arrays["first_positive_rank"][:] = 1

    name = edit_arrays(members, better)
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "b.tar.gz", members), truth), name)
    assert any("its first positive is at rank" in p for p in problems)


def test_a_list_not_ranked_by_its_own_similarities_is_caught(bundle, truth, tmp_path):
    members = read_bundle(bundle)

    def unranked(arrays):  # query 4's scores reversed: its order no longer follows them
        scores = arrays["similarities"]
        assert scores[4, 0] > scores[4, -1]
        scores[4] = scores[4][::-1].copy()

    name = edit_arrays(members, unranked)
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "b.tar.gz", members), truth), name)
    assert "query 4: its similarities increase along its top 20, so the list is not ranked by them (best first)" \
        in problems


def test_missing_queries_and_indices_out_of_range(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = edit_arrays(members, lambda a: a.update({k: v[:-1] for k, v in a.items()}))
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "short.tar.gz", members), truth), name)
    assert problems == ["it has top-K lists for 110 queries; protocol corridor:vpr-bench has 111 (missing queries)"]

    members = read_bundle(bundle)
    name = edit_arrays(members, lambda a: a["database_indices"].__setitem__((7, 3), 111))
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "range.tar.gz", members), truth), name)
    assert problems == ["query 7 lists database index 111, outside the 111 database images"]


def test_unknown_protocol_hash_is_refused(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = record_names(members)[0]
    record = json.loads(members[name])
    wrong = "0123456789abcdef"
    record["protocol"]["hash"] = wrong
    record["spec"]["dataset"]["protocol_hash"] = wrong
    from vprbench.spec import RunSpec

    record["spec_key"] = RunSpec.from_json(record["spec"]).key
    moved = f"{wrong}/{name.split('/', 1)[1]}"
    npz = name.rsplit("/", 1)[0] + "/" + record["per_query"]["file"]
    members[f"{wrong}/{npz.split('/', 1)[1]}"] = members.pop(npz)
    del members[name]
    members[moved] = json.dumps(record).encode()
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "p.tar.gz", members), truth), moved)
    assert len(problems) == 1 and "protocol hash 0123456789abcdef is none of the protocols vprbench ships" in problems[0]


def test_newer_schema_is_refused_by_name(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = edit_record(members, lambda r: r.update(schema_version=9))
    report = verify_bundle(write_bundle(tmp_path / "s.tar.gz", members), truth)
    problems = _only_failure(report, name)
    assert problems == ["schema version 9 is from a newer vprbench (this one reads up to 3); upgrade vprbench to "
                        "read it."]
    assert any(line.startswith(f"{tmp_path / 's.tar.gz'}: {name} (run ") and "schema version 9" in line
               for line in report.lines())


def test_every_count_that_can_be_recomputed_is(bundle, truth, tmp_path):
    """Positives per query, the record's ground-truth counts, max F1 and the top predictions of
    vprbench 0.1's key are recomputed too: each edit is named."""
    edits = {
        "arrays": (lambda a: a["positives"].__setitem__(3, 40), "query 3: its arrays give it 40 positives, "
                                                                "protocol corridor:vpr-bench 5"),
        "pairs": (lambda r: r["counts"].update(positive_pairs=1), "its counts say 1 positive pairs; protocol "
                                                                  "corridor:vpr-bench has 549"),
        "f1": (lambda r: r.update(max_f1=0.99), "max_f1 is 0.99 in the record but"),
        "top": (lambda r: r["top_predictions"][5].reverse(), "its top_predictions are not the first columns"),
    }
    for what, (edit, message) in edits.items():
        members = read_bundle(bundle)
        name = (edit_arrays if what == "arrays" else edit_record)(members, edit)
        problems = _only_failure(verify_bundle(write_bundle(tmp_path / f"{what}.tar.gz", members), truth), name)
        assert len(problems) == 1 and problems[0].startswith(message), (what, problems)


def test_an_archive_bomb_inside_the_arrays_stops_at_the_bound(bundle, truth, tmp_path):
    """An .npz is a zip of its own: first-positive ranks of 64 MiB of zeros (64 kB deflated) are refused
    by the sizes the zip declares, before numpy would allocate and fill them (at 16 GiB, a machine's memory)."""
    import hashlib
    import zipfile

    members = read_bundle(bundle)
    name = record_names(members)[0]
    record = json.loads(members[name])
    npz = name.rsplit("/", 1)[0] + "/" + record["per_query"]["file"]
    with np.load(io.BytesIO(members[npz])) as found:
        kept = {k: found[k] for k in found.files if k != "first_positive_rank"}
    packed = io.BytesIO()
    with zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, array in kept.items():
            with archive.open(f"{key}.npy", "w") as handle:
                np.save(handle, array)
        with archive.open("first_positive_rank.npy", "w") as handle:
            np.lib.format.write_array_header_1_0(handle, {"descr": "<i8", "fortran_order": False, "shape": (8 << 20,)})
            handle.write(bytes(64 << 20))
    members[npz] = packed.getvalue()
    assert len(members[npz]) < 1 << 20
    record["per_query"]["sha256"] = hashlib.sha256(members[npz]).hexdigest()
    members[name] = json.dumps(record).encode()
    report = verify_bundle(write_bundle(tmp_path / "inner-bomb.tar.gz", members), truth, max_bytes=16 << 20)
    assert _only_failure(report, name) == [f"{npz} unpacks to 64 MiB, more than the bound of 16 MiB (an archive "
                                           "bomb, or a bundle too big: raise --max-size)"]


def test_json_nested_too_deeply_is_named_not_a_crash(bundle, truth, tmp_path):
    deep = b"[" * 100_000 + b"]" * 100_000
    members = read_bundle(bundle)
    name = record_names(members)[0]
    members[name] = deep
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "deep.tar.gz", members), truth), name)
    assert problems == ["not JSON (nested too deeply)"]
    members = read_bundle(bundle)
    members[MANIFEST] = deep
    report = verify_bundle(write_bundle(tmp_path / "deep-manifest.tar.gz", members, resum=False), truth)
    assert report.problems == [f"{tmp_path / 'deep-manifest.tar.gz'}: MANIFEST.json is not a bundle manifest "
                               "(ValueError: nested too deeply)."]


def test_manifest_sum_mismatch(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = edit_record(members, lambda r: r.update(method_options={"x": 1}))
    report = verify_bundle(write_bundle(tmp_path / "m.tar.gz", members, resum=False), truth)
    assert not report.ok and not report.verdicts
    assert report.problems == [f"{tmp_path / 'm.tar.gz'}: {name} does not match its sha256 sum in MANIFEST.json "
                               "(changed after export)."]


def test_extra_and_missing_files(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    members["methods/0123456789abcdef.json"] = b"{}"
    report = verify_bundle(write_bundle(tmp_path / "x.tar.gz", members, resum=False), truth)
    assert "methods/0123456789abcdef.json is not listed in MANIFEST.json" in report.problems[0]


def _raw_tar(path, entries, compress=True):
    with tarfile.open(path, "w:gz" if compress else "w") as archive:
        for info, data in entries:
            archive.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


@pytest.mark.parametrize("name", ["../evil.json", "/etc/evil.json", "ab/../../evil.json"])
def test_paths_escaping_the_folder_are_refused(truth, tmp_path, name):
    info = tarfile.TarInfo(name)
    info.size = 2
    report = verify_bundle(_raw_tar(tmp_path / "e.tar.gz", [(info, b"{}")]), truth)
    assert not report.ok and "escapes the folder it would be written to" in report.problems[0]
    assert not (tmp_path.parent / "evil.json").exists()


def test_links_are_refused(truth, tmp_path):
    info = tarfile.TarInfo("methods/0123456789abcdef.json")
    info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
    report = verify_bundle(_raw_tar(tmp_path / "l.tar.gz", [(info, None)]), truth)
    assert "is a link, not a regular file" in report.problems[0]


def test_an_archive_bomb_stops_at_the_bound(bundle, truth, tmp_path):
    """4 MiB of zeros gzip to ~4 KiB (a 1000:1 bomb); members under the bound but over it together stop too."""
    big = tarfile.TarInfo("methods/0123456789abcdef.json")
    big.size = 4 << 20
    path = _raw_tar(tmp_path / "bomb.tar.gz", [(big, bytes(big.size))])
    assert path.stat().st_size < 64 << 10
    report = verify_bundle(path, truth, max_bytes=1 << 20)
    assert not report.ok and "claims 4194304 bytes, over the bound" in report.problems[0]
    parts = []
    for i in range(3):
        info = tarfile.TarInfo(f"methods/{i:016x}.json")
        info.size = 600 << 10
        parts.append((info, bytes(info.size)))
    report = verify_bundle(_raw_tar(tmp_path / "bomb2.tar.gz", parts), truth, max_bytes=1 << 20)
    assert "unpacks to more than the bound of 1 MiB (an archive bomb" in report.problems[0]
    assert verify_bundle(bundle, truth, max_bytes=1 << 20).ok  # a real bundle is far under it


def test_not_an_archive(truth, tmp_path):
    path = tmp_path / "junk.tar.gz"
    path.write_bytes(gzip.compress(b"not a tar at all" * 10))
    report = verify_bundle(path, truth)
    assert not report.ok and "is not a readable bundle archive" in report.problems[0]


def test_without_the_dataset_nothing_can_be_checked(bundle, tmp_path):
    report = verify_bundle(bundle, DataGroundTruth(tmp_path / "no-data"))
    assert not report.ok and all(p.startswith("cannot be checked: ") for v in report.verdicts for p in v.problems)


def test_cli_export_and_verify(store, records, shared_data, tmp_path, capsys):
    out = tmp_path / "cli.tar.gz"
    assert main(["results", "export", "--method", "hog", "--dataset", "corridor", "--to", str(out),
                 "--cache-dir", str(store)]) == 0
    assert main(["results", "verify", str(out), "--data-dir", str(shared_data)]) == 0
    assert capsys.readouterr().out.count(": ok, re-scored") == 2
    members = read_bundle(out)
    edit_record(members, lambda r: r["recall"].update({"5": 99.0}))
    write_bundle(tmp_path / "bad.tar.gz", members)
    assert main(["results", "verify", str(out), str(tmp_path / "bad.tar.gz"), "--data-dir", str(shared_data)]) == 1
    text = capsys.readouterr().out
    assert text.count(": ok, re-scored") == 3 and text.count("R@5 is 99.0 in the record") == 1
    assert main(["results", "export", "--to", str(out), "--cache-dir", str(store)]) == 1
    assert "needs --run ID, or --method M --dataset D" in capsys.readouterr().err


def test_a_record_of_a_stage_not_installed_here_says_so(records):
    """A plugin stage's defaults shape the label ('consensus@20 [n=2]' leaves out its default
    weight); without the plugin the label cannot be derived, so the verdict names the missing
    stage instead of calling a sound record false."""
    from vprbench.bundles.claims import false_claims

    record = json.loads(json.dumps(records[0]))
    record["spec"]["stages"] = [{"name": "consensus", "options": {"k": 20, "n": 2, "weight": 1.0}}]
    record["label"] = f"{record['label']} + consensus@20 [n=2]"
    record["track"] = "re-ranked"  # as a run with a re-ranking stage records it
    assert false_claims(record) == [
        "its stage consensus is not installed here, so its label cannot be checked: install the package "
        "that provides it ('vprbench stages list' shows what is installed), then verify again"]


def test_a_stored_record_without_its_card_exports_with_the_card_rebuilt(store, records, shared_data, tmp_path, cli):
    """A store of an older vprbench kept a record without its row's method card. Was: `results
    export` refused it, exit 1: 'Run ...: Cannot use .../methods/<row key>.json: No such file or
    directory; check the path. Nothing was exported.', until the row was run again."""
    r = records[0]
    card = store / "results" / "methods" / f"{r['row_key']}.json"
    saved = card.read_bytes()
    card.unlink()
    to = tmp_path / "rebuilt.tar.gz"
    code, out, err = cli("results", "export", "--run", r["run_id"], "--to", to, "--cache-dir", store)
    assert code == 0, out + err
    assert read_bundle(to)[f"methods/{r['row_key']}.json"] == saved  # as the store would have kept it
    assert not card.exists()  # export reads the store, it does not write it
    code, out, err = cli("results", "verify", to, "--data-dir", shared_data)
    assert code == 0 and out.count(": ok, re-scored from its arrays") == 1, out + err


def test_a_recall_off_by_less_than_a_query_is_still_caught(bundle, truth, tmp_path):
    """Records keep 4 decimals: a recall nudged by 0.001 points (far below one query's 0.9) is no rounding."""
    members = read_bundle(bundle)
    name = edit_record(members, lambda r: r["recall"].update({"5": round(r["recall"]["5"] + 0.001, 4)}))
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "nudged.tar.gz", members), truth), name)
    assert len(problems) == 1 and problems[0].startswith("R@5 is ") and problems[0].endswith(" from its arrays")


def test_a_recall_beyond_the_kept_top_k_and_a_repeated_candidate_are_refused(bundle, truth, tmp_path):
    members = read_bundle(bundle)
    name = edit_record(members, lambda r: r["recall"].update({"25": 90.0}))
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "k.tar.gz", members), truth), name)
    assert "it reports R@25 but keeps only the top 20 per query" in problems

    members = read_bundle(bundle)

    def repeat(arrays):  # query 5's second candidate is its first again (scores stay ranked)
        arrays["database_indices"][5, 1] = arrays["database_indices"][5, 0]
        arrays["similarities"][5, 1] = arrays["similarities"][5, 0]

    name = edit_arrays(members, repeat)
    problems = _only_failure(verify_bundle(write_bundle(tmp_path / "twice.tar.gz", members), truth), name)
    assert "query 5 lists a database image twice in its top 20" in problems


@pytest.mark.parametrize("kind", ["own", "given"])
def test_a_run_no_one_can_rescore_is_not_exported(records, kind, tmp_path):
    """Was: `results export` packed a run on an own folder into a bundle, exit 0, which `results
    verify` then refused ('it was run on a own dataset ...'), so the contributor learnt it too late."""
    record = {**records[0], "dataset_kind": kind}
    to = tmp_path / "own.tar.gz"
    with pytest.raises(VPRBenchError, match=f"Run {record['run_id']} .* ground truth vprbench does not ship.*"
                                            "bundles carry benchmark runs only.*Nothing was exported"):
        export_bundle([records[1], record], to)
    assert not to.exists()
    # a folder of one's own named as the benchmark is: its runs left out of a choice by method and dataset
    assert select_records([record, records[1]], method="hog", dataset="corridor") == [records[1]]
    assert select_records([record], method="hog", dataset="corridor") == [record]  # alone: refused when exported


def test_an_own_folder_is_found_by_the_path_evaluate_was_given(records, tmp_path, monkeypatch):
    """Was: `results export --method hog --dataset ./mydata` said "No stored run ...; run 'vprbench
    evaluate --method hog --dataset ./mydata' first" of a run just made so: the path is now matched
    with the folder the record names, and the export refused for what it is, a run on one's own data."""
    (tmp_path / "mydata").mkdir()
    record = {**records[0], "dataset_kind": "own", "dataset": "mycorr", "dataset_root": str(tmp_path / "mydata")}
    monkeypatch.chdir(tmp_path)
    assert select_records([record, records[1]], method="hog", dataset="./mydata") == [record]
    with pytest.raises(VPRBenchError, match="No stored run of 'hog' on './other'"):
        select_records([record], method="hog", dataset="./other")
    with pytest.raises(VPRBenchError, match="is on a folder of your own"):
        export_bundle(select_records([record], method="hog", dataset="./mydata"), tmp_path / "own.tar.gz")


@pytest.mark.parametrize("given, said", [("loop/", "a symbolic link in this path leads back to itself"),
                                         ("my\0data/", "holds a NUL character")])
def test_a_dataset_path_no_folder_can_have_is_one_line_in_export_and_compare(records, tmp_path, monkeypatch, given, said):
    """Was: a RuntimeError (a link loop) or a ValueError (a NUL) from resolving the path, a traceback."""
    from vprbench.leaderboard import build_board
    from vprbench.leaderboard.compare import compare

    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(VPRBenchError, match=said):
        select_records(records, method="hog", dataset=given)
    with pytest.raises(VPRBenchError, match=said):
        compare(build_board(records), "hog", "hog", given)
