"""VPR-Bench's precomputed matches, in the exact Python 2 format, imported and re-scored against
the real Corridor ground truth; hostile and malformed files refused without running anything."""
from __future__ import annotations

import os
import pickletools
import re

import numpy as np
import pytest
from hardening.hostile_files import Payload, npy_with_pickle
from vpr_bench_files import FILE, precomputed, python2_npy, python2_pickle, thumbnail_similarity, write_method

from vprbench.bundles import export_bundle, verify_bundle
from vprbench.evaluation.rescore import DataGroundTruth
from vprbench.bundles.vpr_bench import import_vpr_bench, read_precomputed
from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.evaluation import read_results, save_result


@pytest.fixture(scope="module")
def corridor(shared_data):
    return load_dataset("corridor", shared_data)


@pytest.fixture(scope="module")
def similarity(corridor):
    return thumbnail_similarity(corridor.queries, corridor.database)


def expected_recall(similarity, positives, ks=(1, 5, 10, 20)):
    """Recall@K computed here, apart from vprbench: rank by similarity, look for a positive."""
    order = np.argsort(-similarity, axis=1, kind="stable")
    return {str(k): round(100 * np.mean([bool(set(order[q, :k]) & set(positives[q].tolist()))
                                         for q in range(len(order))]), 6) for k in ks}


def test_the_files_are_python2_pickles_that_numpy_reads_only_with_latin1(similarity, tmp_path):
    path = python2_npy(tmp_path / FILE, precomputed(similarity))
    data = path.read_bytes()
    ops = {op.name for op, *_ in pickletools.genops(data[data.index(b"\x80\x02"):])}
    assert {"BINSTRING", "SHORT_BINSTRING", "GLOBAL"} <= ops and not ops & {"BINBYTES", "SHORT_BINBYTES", "BINUNICODE"}
    assert b"numpy.core.multiarray\n_reconstruct" in data and b"_codecs" not in data
    with pytest.raises(UnicodeError, match="encoding"):
        np.load(path, allow_pickle=True)
    loaded = np.load(path, allow_pickle=True, encoding="latin1")
    found = read_precomputed(path)  # the restricted reader: the same values, nothing run
    assert np.array_equal(found.similarity, loaded[3]) and found.similarity.shape == (111, 111)
    assert np.array_equal(found.matched, loaded[1]) and found.matched.dtype == np.int64
    assert found.encoding_s == pytest.approx(0.0123, abs=1e-12) and found.matching_s == pytest.approx(0.0045, abs=1e-12)


def test_import_rescores_against_vprbench_ground_truth(corridor, similarity, shared_data, tmp_path):
    root = tmp_path / "precomputed_matches" / "Corridor"
    write_method(root, "Thumbs", precomputed(similarity))
    rng = np.random.default_rng(3)
    write_method(root, "Thumbs-shuffled", precomputed(similarity, order=rng.permutation(111)))  # rows in any order
    records = import_vpr_bench(root, "corridor", data_dir=shared_data, cache_dir=tmp_path / "cache")
    want = expected_recall(similarity, corridor.positives)
    assert [r["imported"]["method"] for r in records] == ["Thumbs", "Thumbs-shuffled"]
    for record in records:
        assert record["recall"] == want
        assert record["imported"]["from"] == "VPR-Bench" and record["protocol"]["id"] == "corridor:vpr-bench"
        assert record["method"] == f"vpr-bench/{record['imported']['method']}"
    top1 = similarity.argmax(axis=1)  # VPR-Bench's own top-1 gives the same R@1
    assert want["1"] == pytest.approx(100 * np.mean([top1[q] in corridor.positives[q] for q in range(111)]), abs=1e-4)
    assert 0 < want["1"] < want["20"] <= 100


def test_an_imported_record_is_stored_exported_and_verified(similarity, shared_data, tmp_path):
    root = tmp_path / "Corridor"
    write_method(root, "Thumbs", precomputed(similarity))
    cache = tmp_path / "cache"
    [record] = import_vpr_bench(root, "corridor", data_dir=shared_data, cache_dir=cache)
    save_result(record, cache)
    [stored] = read_results(cache)
    assert stored["imported"]["method"] == "Thumbs" and stored["recall"] == record["recall"]
    report = verify_bundle(export_bundle([stored], tmp_path / "b.tar.gz"), DataGroundTruth(shared_data))
    assert report.ok, report.lines()


def test_cli_import_vpr_bench(similarity, shared_data, tmp_path, capsys):
    write_method(tmp_path / "Corridor", "Thumbs", precomputed(similarity))
    cache = tmp_path / "cache"
    assert main(["results", "import-vpr-bench", str(tmp_path / "Corridor" / "Thumbs"), "--dataset", "corridor",
                 "--data-dir", str(shared_data), "--cache-dir", str(cache)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("Thumbs on corridor:vpr-bench: R@1 ") and "(imported from VPR-Bench, re-scored)" in out
    assert len(read_results(cache)) == 1


def test_a_gadget_in_the_file_is_refused_and_never_runs(similarity, shared_data, tmp_path):
    marker = tmp_path / "pwned"
    parts = precomputed(similarity[:3, :3])
    parts[4] = Payload(os.system, f"touch {marker}")
    payload = python2_pickle(parts, hostile=True)  # the Python 2 format, os.system in part 4
    folder = tmp_path / "Corridor" / "Evil"
    folder.mkdir(parents=True)
    npy_with_pickle(folder / FILE, payload, shape=(6,))
    # the gadget is real: the very file, loaded the way VPR-Bench's files are (numpy, pickles allowed), runs it
    loaded = np.load(folder / FILE, allow_pickle=True, encoding="latin1")
    assert marker.exists() and loaded.shape == (6,)
    marker.unlink()
    with pytest.raises(VPRBenchError, match=r"Cannot read VPR-Bench precomputed matches .*Evil/precomputed_data_corrected"
                                            r"\.npy: it asks to load posix\.system"):
        import_vpr_bench(folder, "corridor", data_dir=shared_data)
    assert not marker.exists()
    assert main(["results", "import-vpr-bench", str(folder), "--dataset", "corridor", "--data-dir", str(shared_data),
                 "--cache-dir", str(tmp_path / "cache")]) == 1
    assert not marker.exists() and not read_results(tmp_path / "cache")


def _bad(parts_edit, similarity):
    parts = precomputed(similarity)
    parts_edit(parts)
    return parts


@pytest.mark.parametrize(("edit", "message"), [
    (lambda p: p.__setitem__(3, p[3][0]), "part 3 is float64 (111,), not a 2-d float array"),
    (lambda p: p.__setitem__(0, p[0].astype(np.float64)), "part 0 is float64 (111,), not a 1-d whole-number array"),
    (lambda p: p.__setitem__(1, p[1][:-1]), "its parts disagree on the number of queries"),
    (lambda p: p[3].__setitem__((4, 4), np.nan), "its similarities hold NaN or infinity"),
    (lambda p: p.__setitem__(5, "fast"), "part 5 is a str, not a time in seconds"),
])
def test_malformed_files_are_named(edit, message, similarity, shared_data, tmp_path):
    write_method(tmp_path, "Bad", _bad(edit, similarity))
    with pytest.raises(VPRBenchError, match=f"{FILE} is not a VPR-Bench precomputed-matches file.*{re.escape(message)}"):
        import_vpr_bench(tmp_path / "Bad", "corridor", data_dir=shared_data)


def test_files_that_do_not_fit_the_protocol(similarity, shared_data, tmp_path):
    write_method(tmp_path, "Short", precomputed(similarity[:110]))
    with pytest.raises(VPRBenchError, match="similarity matrix is 110 x 111, but the protocol has 111 queries"):
        import_vpr_bench(tmp_path / "Short", "corridor", data_dir=shared_data)
    parts = precomputed(similarity)
    parts[0] = parts[0].copy()
    parts[0][5] = 4  # query 5 missing, query 4 twice
    write_method(tmp_path, "Repeat", parts)
    with pytest.raises(VPRBenchError, match="not each of the 111 queries once \\(query 5 is missing\\)"):
        import_vpr_bench(tmp_path / "Repeat", "corridor", data_dir=shared_data)
    distances = precomputed(-similarity)
    distances[3] = similarity  # matched by the smallest value: a distance matrix
    write_method(tmp_path, "Distances", distances)
    with pytest.raises(VPRBenchError, match="is not its most similar database image in the matrix"):
        import_vpr_bench(tmp_path / "Distances", "corridor", data_dir=shared_data)


def test_folders_without_files_or_with_odd_names(similarity, shared_data, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(VPRBenchError, match="holds no precomputed_data_corrected.npy"):
        import_vpr_bench(tmp_path / "empty", "corridor", data_dir=shared_data)
    write_method(tmp_path / "odd", "$(touch x)", precomputed(similarity))
    with pytest.raises(VPRBenchError, match="is not a method name this importer takes"):
        import_vpr_bench(tmp_path / "odd", "corridor", data_dir=shared_data)
    with pytest.raises(VPRBenchError, match="does not exist"):
        import_vpr_bench(tmp_path / "nowhere", "corridor", data_dir=shared_data)
