"""The verify gate and the import behind it, each check pinned by a bundle only it refuses: found by
changing verify.py and repository.py one check at a time (a flipped comparison, a dropped check) and
seeing which change the other bundle tests let through. Bundles hold real hog runs on the real Corridor."""
from __future__ import annotations

import json

import pytest

from bundles.bundle_files import edit_arrays, edit_record, read_bundle, record_names, respec, write_bundle

from vprbench.bundles import export_bundle, verify_bundle
from vprbench.evaluation.rescore import DataGroundTruth


@pytest.fixture(scope="module")
def members(corridor_store, tmp_path_factory) -> dict[str, bytes]:
    """The members of a sound bundle of the two stored runs (exported once: tests change a copy)."""
    from vprbench.evaluation import read_results

    path = export_bundle(read_results(corridor_store), tmp_path_factory.mktemp("b") / "runs.tar.gz")
    return read_bundle(path)


@pytest.fixture
def verify(shared_data, tmp_path):
    truth = DataGroundTruth(shared_data)

    def run(members):
        return verify_bundle(write_bundle(tmp_path / "sent.tar.gz", members), truth)
    return run


def problems_of(report, name) -> list[str]:
    """The problems of the one refused record, `name`."""
    refused = [v for v in report.verdicts if not v.ok]
    assert not report.ok and [v.member for v in refused] == [name], report.lines()
    return refused[0].problems


def test_the_sound_bundle_is_accepted(members, verify):
    report = verify(dict(members))
    assert report.ok, report.lines()


def test_a_recall_claimed_below_what_its_arrays_give_is_refused(members, verify):
    """Off by more than the tolerance either way, not only upwards (a rival's run under-reported)."""
    members = dict(members)
    name = edit_record(members, lambda r: r["recall"].update({"5": round(r["recall"]["5"] - 0.9, 4)}))
    [problem] = problems_of(verify(members), name)
    assert problem.startswith("R@5 is ") and "in the record but" in problem


def test_a_spec_naming_another_protocol_than_the_records_place_is_refused(members, verify):
    """The spec decides the row (its key); its protocol hash must be the folder's and the record's."""
    members = dict(members)
    name = respec(members, lambda r: r["spec"]["dataset"].update(protocol_hash="0" * 16))
    [problem] = problems_of(verify(members), name)
    assert "are not its place in the bundle" in problem


def test_arrays_whose_bytes_are_not_the_sha256_their_record_gives_are_refused(members, verify):
    """Scores below rank 1 lowered (still ranked, every metric the same): only the sha256 tells."""
    members = dict(members)
    sha = json.loads(members[record_names(members)[0]])["per_query"]["sha256"]

    def lowered(arrays):
        arrays["similarities"][:, 1:] -= 1.0
    name = edit_arrays(members, lowered)
    edit_record(members, lambda r: r["per_query"].update(sha256=sha))
    [problem] = problems_of(verify(members), name)
    assert problem.endswith(".npz does not match the sha256 its record gives")


def test_arrays_kept_under_another_name_than_the_run_id_are_refused(members, verify):
    """A repository finds a run's arrays as <run id>.npz: a record pointing elsewhere would import
    and then fail every later verify of the repository."""
    members = dict(members)
    name = record_names(members)[0]
    record = json.loads(members[name])
    folder = name.rsplit("/", 1)[0]
    members[f"{folder}/other.npz"] = members.pop(f"{folder}/{record['per_query']['file']}")
    edit_record(members, lambda r: r["per_query"].update(file="other.npz"))
    assert problems_of(verify(members), name) == ["its per-query arrays are missing (a bundle record must keep them)"]


def test_a_record_without_its_method_card_is_refused(members, verify):
    """Import writes the row's card from the bundle: without it the record would land cardless."""
    members = dict(members)
    name = record_names(members)[0]
    card = f"methods/{name.split('/')[1]}.json"
    del members[card]
    assert problems_of(verify(members), name) == [f"its method card {card} is missing"]


def test_a_benchmark_run_relabelled_as_a_run_on_own_data_is_refused(members, verify):
    """Own data has no shipped ground truth: such a record cannot be re-scored, so it is not taken in,
    even when its arrays happen to fit a benchmark's."""
    members = dict(members)

    def own(record):
        record["spec"]["dataset"]["kind"] = record["dataset_kind"] = "own"
    name = respec(members, own)
    [problem] = problems_of(verify(members), name)
    assert problem.startswith("it was run on a folder of your own, whose ground truth vprbench does not ship")


@pytest.mark.parametrize("field, change", [("database", 1), ("queries", -1)])
def test_counts_not_the_protocols_are_refused(members, verify, field, change):
    """Each count alone: a right query count does not vouch for a wrong database count."""
    members = dict(members)
    name = edit_record(members, lambda r: r["counts"].update({field: r["counts"][field] + change}))
    [problem] = problems_of(verify(members), name)
    assert problem.startswith("its counts (") and "are not protocol corridor:vpr-bench's (111, 111)" in problem


def test_a_negative_database_index_is_refused(members, verify):
    """numpy would read index -1 as the last database image: it is named, not re-scored."""
    members = dict(members)
    name = edit_arrays(members, lambda a: a["database_indices"].__setitem__((7, 3), -1))
    assert problems_of(verify(members), name) == ["query 7 lists database index -1, outside the 111 database images"]


@pytest.mark.parametrize("name", ["auc_pr", "max_f1", "recall_at_100_precision"])
def test_a_pr_metric_off_by_a_few_thousandths_is_refused(members, verify, name):
    """Fractions of 1, checked to 1e-3: a tolerance of a tenth would let a 0.6 pass as 0.69."""
    members = dict(members)
    record = edit_record(members, lambda r: r.update({name: round(min(r[name] + 0.005, 1.0) if r[name] < 0.995
                                                                else r[name] - 0.005, 6)}))
    [problem] = problems_of(verify(members), record)
    assert problem.startswith(f"{name} is ") and "in the record but" in problem


def _another_run(members: dict, run_id: str) -> None:
    """The first record sent again as another run of the same spec, whose arrays differ (scores
    below rank 1 lowered: every metric the same), as a second machine's run would."""
    name = record_names(members)[0]
    folder = name.rsplit("/", 1)[0]
    old = json.loads(members[name])["run_id"]
    edit_arrays(members, lambda a: a["similarities"].__setitem__((slice(None), slice(1, None)),
                                                                   a["similarities"][:, 1:] - 1.0))
    record = json.loads(members.pop(name))
    record.update(run_id=run_id, per_query={**record["per_query"], "file": f"{run_id}.npz"})
    members[f"{folder}/{run_id}.json"] = json.dumps(record).encode()
    members[f"{folder}/{run_id}.npz"] = members.pop(f"{folder}/{old}.npz")
    manifest = json.loads(members["MANIFEST.json"])
    manifest["runs"] = [run_id if r == old else r for r in manifest["runs"]]
    members["MANIFEST.json"] = json.dumps(manifest).encode()


def test_another_run_of_the_same_spec_with_other_arrays_is_added_not_called_a_duplicate(members, shared_data,
                                                                                       tmp_path):
    """A duplicate is the same spec and the same arrays: the same spec alone would drop a real second run."""
    from vprbench.bundles import import_bundles

    truth, repo = DataGroundTruth(shared_data), tmp_path / "repo"
    [first] = import_bundles([write_bundle(tmp_path / "a.tar.gz", dict(members))], repo, truth)
    assert first.ok and len(first.added) == 2, first.lines()
    second = dict(members)
    _another_run(second, "20991231T000000Z-0123456789ab")
    [report] = import_bundles([write_bundle(tmp_path / "b.tar.gz", second)], repo, truth)
    assert report.ok and report.added == ["20991231T000000Z-0123456789ab"], report.lines()


def test_a_bundle_holding_no_record_is_not_passed(members, verify):
    """Nothing re-scored is nothing proven: `results verify` must not exit 0 on it."""
    manifest = json.loads(members["MANIFEST.json"])
    manifest["runs"] = []
    report = verify({"MANIFEST.json": json.dumps(manifest).encode()})
    assert not report.ok and report.verdicts == [] and report.lines()[-1].endswith(": it holds no records.")


def test_a_bundle_with_one_conflicting_record_writes_none_of_its_runs(members, shared_data, tmp_path):
    """'refused; nothing of it was written' holds for its sound new runs too, not only the conflicting one."""
    from vprbench.bundles import import_bundles

    truth, repo = DataGroundTruth(shared_data), tmp_path / "repo"
    [first] = import_bundles([write_bundle(tmp_path / "a.tar.gz", dict(members))], repo, truth)
    assert first.ok, first.lines()
    second, new = dict(members), "20991231T000000Z-0123456789ab"
    _another_run(second, new)
    clash = next(i for i, n in enumerate(record_names(second)) if new not in n)
    edit_record(second, lambda r: r.update(hardware={"note": "another machine"}), which=clash)
    before = sorted(p.relative_to(repo) for p in repo.rglob("*") if p.is_file())
    [report] = import_bundles([write_bundle(tmp_path / "b.tar.gz", second)], repo, truth)
    assert not report.ok and "a run id names one run" in report.problems[0], report.lines()
    assert report.lines()[-1].endswith("refused; nothing of it was written.")
    assert sorted(p.relative_to(repo) for p in repo.rglob("*") if p.is_file()) == before


def test_a_planted_pending_import_replaces_no_file_already_there(members, shared_data, tmp_path):
    """A pull request could carry `.import.pending/commit-*/` with other bytes for a run already in the
    repository: finishing it adds files, it never overwrites a record, its arrays or its card."""
    from vprbench.bundles import import_bundles, verify_repository

    truth, repo = DataGroundTruth(shared_data), tmp_path / "repo"
    [first] = import_bundles([write_bundle(tmp_path / "a.tar.gz", dict(members))], repo, truth)
    assert first.ok, first.lines()
    name = record_names(members)[0]
    kept = [name, name[:-len("json")] + "npz", f"methods/{name.split('/')[1]}.json"]
    before = {n: (repo / n).read_bytes() for n in kept}
    for n in kept:
        planted = repo / ".import.pending" / "commit-1-ab" / n
        planted.parent.mkdir(parents=True, exist_ok=True)
        planted.write_bytes(b"{}")
    report = verify_repository(repo, truth)
    assert {n: (repo / n).read_bytes() for n in kept} == before
    assert report.ok and not (repo / ".import.pending").exists(), report.lines()
