"""Result bundles from a hostile sender, or tampered with after export: each is refused with a
line naming the bundle, the file and what is wrong, exit code 1, no traceback, nothing written
into the repository and the runs already there untouched. What a record says beside its numbers
(its method, protocol, domain, weights, method card, run id) is proven as its numbers are."""
from __future__ import annotations

import gzip
import json
import tarfile

import numpy as np
import pytest

from bundles.bundle_files import edit_arrays, edit_record, read_bundle, record_names, write_bundle

from vprbench.bundles import export_bundle
from vprbench.bundles.export import MANIFEST
from vprbench.evaluation import evaluate, read_results, save_result
from vprbench.spec import RunSettings, RunSpec, resolve_spec


@pytest.fixture(scope="module")
def runs(shared_data, tmp_path_factory) -> list[dict]:
    """Two real hog runs on Corridor, in two rows (small images: a few seconds)."""
    cache = tmp_path_factory.mktemp("audit-store")
    settings = RunSettings(cache_dir=cache, data_dir=shared_data, workers=0)
    for size in ([48, 64], [96, 128]):
        spec = resolve_spec("hog", "corridor", options={"resize": size}, data_dir=shared_data, cache_dir=cache)
        save_result(evaluate(spec, settings), cache)
    return read_results(cache)


@pytest.fixture
def bundle(runs, tmp_path):
    return export_bundle(runs, tmp_path / "runs.tar.gz", contributor="alice")


def snapshot(folder) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.startswith(".import.lock")} if folder.exists() else {}


def refused(cli, shared_data, path, repo, message: str) -> None:
    """verify and import both refuse `path` with `message` on the record's line; the repository is unchanged."""
    code, out, err = cli("results", "verify", path, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in out + err, (out, err)
    assert any(line.startswith(f"{path}: ") and message in line for line in out.splitlines()), out
    before = snapshot(repo)
    code, out, err = cli("results", "import", path, "--into", repo, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in out + err and message in out, (out, err)
    assert out.splitlines()[-1] == f"{path}: refused; nothing of it was written."
    assert snapshot(repo) == before


# ---------------------------------------------------------------- arrays of the wrong kind
def _filled(name, value):
    return lambda a: a.update({name: np.full(a[name].shape, value)})


NOT_FINITE = "its similarities are float64 (111, 20), not (111, 20) finite numbers (one per top-K index)"


@pytest.mark.parametrize("edit, message", [
    (_filled("similarities", np.nan), NOT_FINITE),
    (_filled("similarities", np.inf), NOT_FINITE),
    (_filled("similarities", "abc"), "its similarities are <U3"),
    (_filled("first_positive_rank", "x"), "its first_positive_rank array is <U1"),
    (lambda a: a.update(positives=a["positives"][:, None]),
     "its positives array is int32 (111, 1), not one whole number per query (111)"),
    (lambda a: a.update(place=np.array(["x"] * len(a["positives"]))), "its place array is <U1 (111,)"),
], ids=["nan", "inf", "strings", "string-ranks", "2d-positives", "string-places"])
def test_per_query_arrays_of_the_wrong_kind_are_named_not_a_traceback(bundle, cli, shared_data, tmp_path, edit, message):
    """Before: NaN or infinite similarities failed in the PR curve, strings in a float conversion,
    2-D ranks in an int(): a traceback from verify and import."""
    members = read_bundle(bundle)
    name = edit_arrays(members, edit)
    path = write_bundle(tmp_path / "kinds.tar.gz", members)
    refused(cli, shared_data, path, tmp_path / "repo", f"{name.removesuffix('.json')}.npz: {message}")


def test_the_stores_own_reader_refuses_non_finite_similarities(runs):
    """The same test guards a record read from a results store: NaN similarities are named, not
    passed on to the leaderboard's PR curve."""
    from vprbench.evaluation.results import per_query

    record = {k: v for k, v in runs[0].items() if k != "_source"}
    arrays = per_query(runs[0])
    record["per_query"] = {"k": arrays["database_indices"].shape[1], **{k: v.tolist() for k, v in arrays.items()}}
    record["per_query"]["similarities"][3][0] = float("nan")
    with pytest.warns(UserWarning, match=r"its similarities are float32 \(111, 20\), not \(111, 20\) finite numbers"):
        assert per_query(record) is None


# ---------------------------------------------------------------- one run id, one run
def move_run(members, which: int, run_id: str) -> str:
    """Record `which` (and its arrays) renamed to `run_id`, in its own row folder."""
    name = record_names(members)[which]
    folder, old = name.rsplit("/", 1)[0], json.loads(members[name])["run_id"]
    record = json.loads(members.pop(name))
    record["run_id"], record["per_query"]["file"] = run_id, f"{run_id}.npz"
    members[f"{folder}/{run_id}.npz"] = members.pop(f"{folder}/{old}.npz")
    members[f"{folder}/{run_id}.json"] = json.dumps(record).encode()
    return f"{folder}/{run_id}.json"


def test_a_run_id_already_in_the_repository_under_another_row_is_a_conflict(runs, bundle, cli, shared_data, tmp_path):
    """Before: run B renamed to run A's id, in B's own row folder, was added beside A: two
    different runs under one id in the repository, 'ok' from verify of the repository too."""
    repo = tmp_path / "repo"
    first = export_bundle([runs[0]], tmp_path / "a.tar.gz")
    assert cli("results", "import", first, "--into", repo, "--data-dir", shared_data)[0] == 0
    members = read_bundle(bundle)
    a_name = record_names(members)[0]
    for member in [m for m in members if m.startswith(a_name.rsplit("/", 1)[0] + "/")]:
        del members[member]  # only run B is sent, under run A's id
    clash = move_run(members, 0, runs[0]["run_id"])
    path = write_bundle(tmp_path / "clash.tar.gz", members)
    before = snapshot(repo)
    code, out, err = cli("results", "import", path, "--into", repo, "--data-dir", shared_data)
    assert code == 1 and "Traceback" not in err
    assert f"{path}: {clash} (run {runs[0]['run_id']}): another record with this run id is already in {repo} " \
           f"({a_name}); a run id names one run." in out.splitlines()
    assert snapshot(repo) == before


def test_two_records_under_one_run_id_are_refused_in_a_bundle_and_a_repository(runs, bundle, cli, shared_data, tmp_path):
    members = read_bundle(bundle)
    a_name = record_names(members)[0]
    twin = move_run(members, 1, runs[0]["run_id"])
    path = write_bundle(tmp_path / "twins.tar.gz", members)
    refused(cli, shared_data, path, tmp_path / "repo",
            f"its run id is also that of {a_name}; a run id names one run")
    # the same pair added to a repository by hand (a pull request, no import)
    repo = tmp_path / "repo"
    assert cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)[0] == 0
    b_name = record_names(read_bundle(bundle))[1]
    for member in (twin, twin.replace(".json", ".npz")):
        (repo / member).write_bytes(members[member])
    for member in (b_name, b_name.replace(".json", ".npz")):
        (repo / member).unlink()
    code, out, _ = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 1 and f"{repo}: {twin} (run {runs[0]['run_id']}, hog [resize=96x128] on corridor:vpr-bench): its " \
                         f"run id is also that of {a_name}; a run id names one run" in out.splitlines()


# ---------------------------------------------------------------- names beside the numbers
@pytest.mark.parametrize("edit, message", [
    (lambda r: r["protocol"].update(id="corridor:official"),
     "it says protocol id 'corridor:official', but protocol f60ac2fa1d51bc67 as vprbench ships it says "
     "'corridor:vpr-bench'; a record names only the run it made"),
    (lambda r: r.update(method="netvlad"), "it says method 'netvlad', but its spec says 'hog'"),
    (lambda r: r.update(label="<b>NetVLAD</b> (official)\x1b[2J"),
     "it says label '<b>NetVLAD</b> (official)\\x1b[2J', but its spec says 'hog [resize=48x64]'"),
    (lambda r: r.update(domain="urban"), "it says domain 'urban', but the corridor manifest says 'indoor'"),
    (lambda r: r["spec"]["dataset"].update(name="nordland"), "it says dataset 'corridor', but its spec says 'nordland'"),
], ids=["protocol", "method", "label-markup", "domain", "dataset"])
def test_a_record_naming_what_it_did_not_run_is_refused(bundle, cli, shared_data, tmp_path, edit, message):
    """Before: each was 'ok, re-scored' and imported; the protocol id reached the downloads, the
    domain moved Corridor out of its table on the site, the method and label the downloads."""
    members = read_bundle(bundle)
    edit_record(members, edit)
    refused(cli, shared_data, write_bundle(tmp_path / "named.tar.gz", members), tmp_path / "repo", message)


def test_a_run_on_a_weights_file_claiming_official_weights_is_refused(bundle, cli, shared_data, tmp_path):
    """The spec names the weights file by its sha256; a file vprbench does not know as a release is
    the user's, whatever the record's provenance says (an official row would be marked none)."""
    members = read_bundle(bundle)
    name = record_names(members)[0]
    record = json.loads(members.pop(name))
    old_folder = name.rsplit("/", 1)[0]
    digest = "sha256:" + "ab" * 32
    record["spec"]["options"]["weights"] = "mine.pth"
    record["spec"]["files"] = {"weights": digest}
    spec = RunSpec.model_validate(record["spec"])
    record.update(spec_key=spec.key, row_key=spec.row_key)
    record["provenance"]["weights"] = {"source": "official"}
    folder = f"{record['protocol']['hash']}/{spec.row_key}"
    members[f"{folder}/{record['run_id']}.json"] = json.dumps(record).encode()
    members[f"{folder}/{record['per_query']['file']}"] = members.pop(f"{old_folder}/{record['per_query']['file']}")
    card = json.loads(members.pop(f"methods/{old_folder.split('/')[1]}.json"))
    card.update(row_key=spec.row_key, options=record["spec"]["options"], files=record["spec"]["files"],
                weights=record["provenance"]["weights"])
    members[f"methods/{spec.row_key}.json"] = json.dumps(card).encode()
    refused(cli, shared_data, write_bundle(tmp_path / "weights.tar.gz", members), tmp_path / "repo",
            f"it says weights source 'official', but its weights file {digest[:19]} says 'user'")


def test_a_method_card_describing_another_method_is_refused(runs, bundle, cli, shared_data, tmp_path):
    """Before: the card was written into the repository as sent, whatever it said."""
    members = read_bundle(bundle)
    card, other = f"methods/{runs[0]['row_key']}.json", f"methods/{runs[1]['row_key']}.json"
    forged = json.dumps({**json.loads(members[card]), "method": "netvlad", "label": "NetVLAD",
                         "weights": {"source": "official"}}).encode()
    message = f"its method card {card} disagrees with the record on method, label, weights"
    refused(cli, shared_data, write_bundle(tmp_path / "card.tar.gz", {**members, card: forged}), tmp_path / "repo", message)
    # the two rows' cards swapped, each under the other's name
    swapped = write_bundle(tmp_path / "swapped.tar.gz", {**members, card: members[other], other: members[card]})
    code, out, _ = cli("results", "verify", swapped, "--data-dir", shared_data)
    assert code == 1 and out.count("disagrees with the record on row_key, label, options, given") == 2
    # and in a repository, edited by hand
    repo = tmp_path / "repo"
    assert cli("results", "import", bundle, "--into", repo, "--data-dir", shared_data)[0] == 0
    (repo / card).write_bytes(forged)
    code, out, _ = cli("results", "verify", repo, "--data-dir", shared_data)
    assert code == 1 and message in out


# ---------------------------------------------------------------- the archive itself
@pytest.mark.parametrize("version", [True, 0, "2"])
def test_a_format_version_no_vprbench_writes_is_named(bundle, cli, tmp_path, version):
    """Before: version true (JSON) or 0 was read as a version-1 bundle; "2" was called newer."""
    members = read_bundle(bundle)
    manifest = json.loads(members[MANIFEST])
    members[MANIFEST] = json.dumps({**manifest, "version": version}).encode()
    path = write_bundle(tmp_path / "v.tar.gz", members)
    code, out, err = cli("results", "verify", path)
    assert code == 1 and out.splitlines() == [f"{path}: MANIFEST.json says format version {version!r}, which no "
                                              "vprbench writes; it is damaged or not a vprbench bundle: export it again."]


def test_a_member_claiming_a_huge_size_names_the_bound_and_the_fix(cli, tmp_path):
    info = tarfile.TarInfo("methods/0123456789abcdef.json")
    info.size = 1 << 40  # 1 TiB declared, nothing behind it
    path = tmp_path / "huge.tar.gz"
    path.write_bytes(gzip.compress(info.tobuf(format=tarfile.PAX_FORMAT) + bytes(1024)))
    code, out, err = cli("results", "verify", path)
    assert code == 1 and out.splitlines() == [
        f"{path}: member methods/0123456789abcdef.json claims 1099511627776 bytes, over the bound of 1024 MiB "
        "(an archive bomb, or a bundle too big: raise --max-size)."]


@pytest.mark.parametrize("damage, message", [
    (lambda data: data[: len(data) // 2], "is not a readable bundle archive (EOFError: Compressed file ended"),
    (lambda data: b"", "is not a readable bundle archive (ReadError: empty file)"),
    (lambda data: gzip.compress(gzip.decompress(data)[:3000]), "is not a readable bundle archive (ReadError: "
                                                                "unexpected end of data)"),
], ids=["truncated", "empty", "cut-inside-a-member"])
def test_a_damaged_archive_is_one_line(bundle, cli, tmp_path, damage, message):
    path = tmp_path / "damaged.tar.gz"
    path.write_bytes(damage(bundle.read_bytes()))
    code, out, err = cli("results", "import", path, "--into", tmp_path / "repo")
    assert code == 1 and message in out.splitlines()[0] and not (tmp_path / "repo").exists()
