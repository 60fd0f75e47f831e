"""The result record: a real run's provenance and per-query data; weights sources; the store's
read side (round trip, corrupt, foreign, newer and 0.1 records)."""
import json

import numpy as np
import pytest

from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from runs import evaluate_method as evaluate
from vprbench.evaluation import per_query, read_results, results_dir, save_result
from vprbench.evaluation.identity import benchmark_protocols, fingerprint_of
from vprbench.evaluation.provenance import method_provenance
from vprbench.leaderboard import build_board
from vprbench.evaluation.metrics import successes
from vprbench.methods import create_method
from vprbench.weights import weights_provenance

CONTRACT = ("method", "dataset", "recall", "counts", "descriptors_computed", "timings", "descriptor_dim",
            "provenance", "search")


def test_real_run_record_has_provenance_and_recomputable_metrics(shared_data):
    dataset = load_dataset("corridor", shared_data)
    record = evaluate(create_method("hog", resize=(64, 64)), dataset, ks=(1, 5, 10))
    assert set(CONTRACT) <= set(record)
    assert record["schema_version"] == 3 and record["dataset_kind"] == "benchmark"
    assert record["spec"]["method"] == "hog" and record["spec"]["ks"] == [1, 5, 10] and len(record["spec_key"]) == 16
    assert record["protocol"] == next(iter(benchmark_protocols("corridor").values()))  # the default protocol
    assert record["provenance"]["weights"] == {"source": "none"} and record["needs_fit"] is False
    assert record["method_options"] == {"resize": [64, 64]}
    assert {"torch", "faiss", "vprbench", "git"} <= set(record["versions"]) and record["hardware"]["cpu_count"] >= 1
    assert record["descriptor_bytes"] == 4 * record["descriptor_dim"]

    arrays = per_query(record)
    assert arrays["database_indices"].shape == (111, 10) == arrays["similarities"].shape
    assert (np.diff(arrays["similarities"], axis=1) <= 1e-6).all(), "similarities are sorted, best first"
    assert arrays["positives"].sum() == record["counts"]["positive_pairs"] == 549
    for k, value in record["recall"].items():  # every metric from the record, without descriptors
        assert 100 * successes(arrays["first_positive_rank"], int(k)).mean() == pytest.approx(value, abs=1e-3)
    positives = dataset.positives
    for q in (0, 50, 110):
        hits = np.isin(arrays["database_indices"][q], positives[q])
        assert arrays["first_positive_rank"][q] == (hits.argmax() + 1 if hits.any() else 0)

    path = save_result(record)
    [stored] = read_results()
    assert stored["run_id"] == record["run_id"] and path.name.startswith(record["run_id"])
    assert path.parent == results_dir() / record["protocol"]["hash"] / record["row_key"]  # found by identity
    assert stored["per_query"]["file"] == path.with_suffix(".npz").name
    for name, array in per_query(stored).items():
        np.testing.assert_allclose(array, arrays[name], atol=1e-6)


def test_dense_vlad_says_its_vocabulary_is_fitted_on_the_evaluated_database():
    found = method_provenance(create_method("dense-vlad"))
    assert found["weights"] == {"source": "none"}
    assert found["vocabulary"]["fitted_on_evaluated_database"] is True


def test_a_plugin_that_does_not_declare_weights_is_never_official(make_record):
    from vprbench.methods import Method

    class Plugin(Method):
        name, options = "plugin", {}

        def describe(self, images):  # pragma: no cover
            raise AssertionError

    assert method_provenance(Plugin())["weights"] == {"source": "undeclared"}

    class Speaking(Plugin):  # says where its vocabulary came from, not its weights (was: "nothing learnt")
        def provenance(self):
            return {"vocabulary": {"source": "file", "fitted_on": "x", "fitted_on_evaluated_database": False}}

    assert method_provenance(Speaking())["weights"] == {"source": "undeclared"}
    assert method_provenance(type("Empty", (Plugin,), {"provenance": lambda self: {}})())["weights"] == {
        "source": "undeclared"}


def test_weights_sources(monkeypatch):
    assert weights_provenance(None) == {"source": "random"}
    url = "https://dl.fbaipublicfiles.com/dinov2/dinov2_vitg14/dinov2_vitg14_pretrain.pth"
    assert weights_provenance(url) == {"source": "official", "url": url, "recognised_by": "download", "release": "dinov2"}
    assert weights_provenance("sha256:" + "ab" * 32) == {"source": "user", "sha256": "ab" * 32}
    # a local copy of an official file is official only through a published checksum
    import vprbench.weights as weights

    published = ({"name": "dinov2", "url_prefix": "https://x/", "checksum_source": "the authors' README",
                  "sha256": {"dinov2_vits14_pretrain.pth": "cd" * 32}},)
    monkeypatch.setattr(weights, "official_releases", lambda: published)
    found = weights_provenance("sha256:" + "CD" * 32)
    assert found["source"] == "official" and found["recognised_by"] == "sha256"
    assert found["file"] == "dinov2_vits14_pretrain.pth" and found["checksum_source"] == "the authors' README"


def test_shipped_release_table_has_no_unsourced_checksum():
    from vprbench.weights import official_releases

    releases = official_releases()
    assert {"dinov2", "dino", "cosplace", "salad", "open_clip"} <= {r["name"] for r in releases}
    for release in releases:
        assert release["sha256"] == {} or release.get("checksum_source"), release["name"]


def test_torch_baselines_report_their_weights_source(tmp_path):
    torch = pytest.importorskip("torch")
    from vprbench_baselines.common import Preprocess, TorchMethod

    def method(identity):
        return TorchMethod(torch.nn.Identity(), Preprocess(), {"architecture": "x", **identity})

    official = method({"weights_url": "https://github.com/gmberton/CosPlace/releases/download/v1.0/R.pth", "weights_sha256": None})
    assert official.provenance()["weights"]["source"] == "official"
    assert official.provenance()["weights"]["release"] == "cosplace"
    assert method({"weights_sha256": "ef" * 32}).provenance() == {"weights": {"source": "user", "sha256": "ef" * 32}}
    clip = method({"weights": "open_clip:ViT-bigG-14/laion2b_s39b_b160k", "hf_hub": "laion/CLIP-ViT-bigG-14/"})
    assert clip.provenance()["weights"] == {"source": "official", "url": "open_clip:ViT-bigG-14/laion2b_s39b_b160k",
                                            "recognised_by": "download", "release": "open_clip",
                                            "hub": "laion/CLIP-ViT-bigG-14/"}


def test_own_folder_named_like_a_benchmark_is_own_data(tmp_path, shared_data):
    import shutil

    root = tmp_path / "mine"
    for split, source in (("database", "ref"), ("queries", "query")):
        (root / split).mkdir(parents=True)
        for i in range(6):
            shutil.copy(shared_data / "corridor" / source / f"{i:07d}.jpg", root / split / f"{i:04d}.jpg")
    rows = ["image,x,y"] + [f"{s}/{i:04d}.jpg,{i * 10},0" for s in ("database", "queries") for i in range(6)]
    (root / "positions.csv").write_text("\n".join(rows))
    (root / "dataset.toml").write_text('name = "corridor"\nradius = 5\n')
    record = evaluate(create_method("hog", resize=(64, 64)), load_dataset(str(root)), ks=(1, 5))
    assert record["dataset"] == "corridor" and record["dataset_kind"] == "own"


def test_corrupt_foreign_newer_and_old_records_are_named_and_skipped(make_record):
    path = save_result(make_record("hog"))
    folder = path.parent
    (folder / "torn.json").write_text('{"method": "hog", "dataset": "corr')
    (folder / "foreign.json").write_text(json.dumps({"model": "bert", "score": 1}))
    (folder / "list.json").write_text("[1, 2]")
    (folder / "future.json").write_text(json.dumps({**make_record("hog"), "schema_version": 99}))
    (folder / "binary.json").write_bytes(b"\xff\xfe\x00garbage")
    (folder / "edited.json").write_text(json.dumps({**make_record("hog"), "spec_key": "0" * 16}))
    legacy = {"method": "hog", "dataset": "corridor", "recall": {"1": 48.6, "5": 75.7}, "counts": {"queries": 111}}
    (results_dir().parent / "results.jsonl").write_text(json.dumps(legacy) + "\n")
    with pytest.warns(UserWarning) as caught:
        records = read_results()
    messages = " | ".join(str(w.message) for w in caught)
    for name in ("torn.json", "foreign.json", "list.json", "future.json", "binary.json", "edited.json", "results.jsonl"):
        assert name in messages
    assert "newer vprbench" in messages and "vprbench 0.1 records" in messages and "nothing was deleted" in messages
    assert [r["run_id"] for r in records] == [json.loads(path.read_text())["run_id"]]
    assert len(list(folder.glob("*.json"))) == 7  # nothing deleted
    assert len(build_board(records).cells) == 1


def test_a_0_2_record_is_moved_into_its_identity_folder_and_upgraded(make_record):
    """A schema-2 record (flat in results/, no spec) lands in the row of a new run of the same method."""
    new = make_record("hog", options={"resize": [64, 64]}, seed=1, created="2026-02-01T00:00:00+00:00")
    new["dataset_fingerprint"] = fingerprint_of("corridor", new["dataset_fingerprints"])  # as 0.3 computes it
    old = {k: v for k, v in make_record("hog", options={"resize": [64, 64]}, seed=2,
                                        created="2026-01-01T00:00:00+00:00").items()
           if k not in ("spec", "spec_key", "row_key", "label", "served_from_store", "run")}
    old.update(schema_version=2, method_settings={"resize": [64, 64]}, method_options={"resize": [64, 64], "device": "cpu"})
    old.pop("per_query")
    folder = results_dir()
    folder.mkdir(parents=True)
    (folder / f"{old['run_id']}-hog-corridor.json").write_text(json.dumps(old))
    save_result(new)
    records = read_results()
    assert [r["run_id"] for r in records] == [old["run_id"], new["run_id"]]
    assert records[0]["upgraded_from"] == 2 and records[0]["row_key"] == new["row_key"]
    assert not list(folder.glob("*.json"))  # moved, unchanged
    moved = folder / new["protocol"]["hash"] / new["row_key"] / f"{old['run_id']}-hog-corridor.json"
    assert json.loads(moved.read_text()) == old
    board = build_board(records)  # the old run kept no per-query arrays: nothing of it can be recomputed
    assert len(board.rows) == 1 and next(iter(board.cells.values())).record["run_id"] == new["run_id"]
    assert [(r["run_id"], why) for r, why in board.excluded] == [
        (old["run_id"], "it keeps no per-query arrays, so its metrics cannot be recomputed; rerun it")]


def test_damaged_per_query_file_is_named_and_only_statistics_are_lost(make_record):
    path = save_result(make_record("hog"))
    path.with_suffix(".npz").write_bytes(b"PK\x03\x04 not really")
    [record] = read_results()
    with pytest.warns(UserWarning, match=r"Per-query data .*\.npz of run .* is unreadable"):
        assert per_query(record) is None
    assert record["recall"]["1"] >= 0


def _huge_npz() -> bytes:
    """An .npz of a few bytes whose top-K array's header claims 2**40 x 20 int32 (80 TiB)."""
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i4", "fortran_order": False, "shape": (2**40, 20)})
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as bundle:
        bundle.writestr("database_indices.npy", header.getvalue() + b"\0" * 80)
    return out.getvalue()


@pytest.mark.parametrize("content", [b"PK\x03\x04 not really", _huge_npz()], ids=["not-a-zip", "huge-header"])
def test_a_per_query_file_its_record_vouches_for_is_still_read_as_untrusted(make_record, content):
    """Record and file written together (a copied cache): the sha256 matches, yet the file is no
    .npz (before: zipfile's traceback) or claims an 80 TiB array (before: an 'out of memory, lower
    --batch-size' ending the whole leaderboard). Named, its statistics skipped, the board kept."""
    import hashlib

    path = save_result(make_record("hog"))
    path.with_suffix(".npz").write_bytes(content)
    data = json.loads(path.read_text())
    data["per_query"]["sha256"] = hashlib.sha256(content).hexdigest()
    path.write_text(json.dumps(data))
    [record] = read_results()
    with pytest.warns(UserWarning, match=r"Per-query data .*\.npz of run .* is unreadable"):
        assert per_query(record) is None


def test_a_results_folder_of_another_layout_and_unreadable_records_fail_the_command(make_record, capsys):
    from vprbench.cli.main import main

    path = save_result(make_record("hog"))
    assert main(["leaderboard"]) == 0
    capsys.readouterr()
    (path.parent / "torn.json").write_text("{")
    with pytest.warns(UserWarning, match="torn.json"):
        assert main(["leaderboard"]) == 1  # the board is shown, the unread file named, exit 1
    out, err = capsys.readouterr()
    assert "hog" in out and "1 stored file(s) could not be read" in err and (path.parent / "torn.json").exists()
    assert err.splitlines()[-1] == ("error: 1 stored file(s) could not be read (named above) and are left out; nothing "
                                    "was deleted. Fix or move them, or rerun those evaluations."), "one line, not wrapped"
    (results_dir() / "LAYOUT").write_text(json.dumps({"layout": "vprbench-results", "version": 9}))
    assert main(["leaderboard"]) == 1
    err = capsys.readouterr().err
    assert "was written by another vprbench (vprbench-results version 9" in err and "Traceback" not in err
    with pytest.raises(VPRBenchError, match="another vprbench"):
        save_result(make_record("hog", seed=3))
    assert sorted(p.name for p in path.parent.iterdir()) == sorted([path.name, path.with_suffix(".npz").name, "torn.json"])


def test_old_records_without_origins_still_publish_and_a_plugin_is_shown_escaped(capsys, tmp_path, make_record):
    from vprbench.cli.main import main
    from vprbench.leaderboard.escape import text

    old = make_record("hog", seed=1, created="2026-01-01T00:00:00+00:00")
    del old["origins"]
    save_result(old)
    assert main(["leaderboard", "publish", "--to", str(tmp_path / "core")]) == 0, capsys.readouterr().err
    assert "Plugins" not in (tmp_path / "core" / "leaderboard" / "corridor.md").read_text()  # vprbench's own runs only
    plugin = make_record("thumbnail", seed=2)
    plugin["origins"] = {"method": {"name": "thumbnail", "module": "acme", "distribution": "acme-<b>vpr</b>",
                                    "version": "1.2|3"}, "stages": []}
    save_result(plugin)
    assert {r["run_id"] for r in read_results()} == {old["run_id"], plugin["run_id"]}
    assert main(["leaderboard", "publish", "--to", str(tmp_path / "docs")]) == 0, capsys.readouterr().err
    page = (tmp_path / "docs" / "leaderboard" / "corridor.md").read_text()
    assert "| Plugins |" in page and f"| {text('thumbnail: acme-<b>vpr</b> 1.2|3')} |" in page, page
    assert "<b>" not in page
    old_row = next(line for line in page.splitlines() if old["run_id"] in line)
    assert "| – |" in old_row  # a record written before origins: nothing claimed
