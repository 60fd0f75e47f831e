"""SIFT-RANSAC on real Corridor images: inlier counts, repeatable, features kept and reused."""
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.spec import RunSettings, resolve_spec
from vprbench.stages.geometric import SiftRansacOptions, inliers, matchable, ratio_matches, sift_features


def test_an_image_matches_itself_better_than_another(corridor):
    options = SiftRansacOptions(model="homography")
    first, other = sift_features(corridor.queries[0], 2000), sift_features(corridor.queries[60], 2000)
    assert first["descriptors"].dtype == np.uint8 and first["points"].shape == (len(first["descriptors"]), 2)
    same = ratio_matches(matchable(first["descriptors"], "rootsift"), matchable(first["descriptors"], "rootsift"), 0.8)
    assert len(same) > 20 and (same[:, 0] == same[:, 1]).all()  # itself: every kept match is a keypoint with itself
    different = ratio_matches(matchable(first["descriptors"], "rootsift"), matchable(other["descriptors"], "rootsift"), 0.8)
    assert len(different) < len(same)
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 160, (50, 2)).astype(np.float32)
    moved = points + 5
    moved[:20] = rng.uniform(0, 160, (20, 2))  # 20 outliers
    assert inliers(points, points + 5, options) == 50  # a pure translation: all inliers
    assert inliers(points, moved, options) == 30
    assert inliers(first["points"][:3], first["points"][:3], options) == 0  # too few for a homography
    assert len(other["descriptors"]) > 20


def test_sift_ransac_run_is_repeatable_and_reuses_its_features(shared_data, stage_cache, tmp_path):
    spec = resolve_spec("hog", "corridor", stages=[{"name": "sift-ransac", "k": 5}], ks=(1, 5), data_dir=shared_data)
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    first, again = evaluate(spec, settings), evaluate(spec, settings)
    assert first["per_query"]["database_indices"] == again["per_query"]["database_indices"]
    scores = np.array(first["per_query"]["similarities"])
    assert (scores == np.rint(scores)).all() and (np.diff(scores, axis=1) <= 0).all()  # inlier counts, best first
    assert first["stages"][0]["stored_bytes_per_database_image"] > 1000
    stored = list((stage_cache / "features").glob("sift-*/corridor-*/database.*.h5"))
    assert len({p.parent for p in stored}) == 1  # one store, its segments
    assert again["stages"][0]["ms_per_query"] < first["stages"][0]["ms_per_query"]  # no SIFT computed the second time


def test_root_sift_is_the_hellinger_map():
    found = matchable(np.array([[4, 0, 0, 12]], np.uint8), "rootsift")
    assert np.allclose(found, [[0.5, 0, 0, np.sqrt(0.75)]]) and np.isclose(np.linalg.norm(found), 1)


def test_a_wrong_model_is_refused(shared_data):
    with pytest.raises(VPRBenchError, match="Stage 'sift-ransac' option model: Input should be 'fundamental' or 'homography'"):
        resolve_spec("hog", "corridor", stages=[{"name": "sift-ransac", "model": "affine"}], data_dir=shared_data)


def test_two_processes_rerank_on_one_cache_and_compute_each_image_once(shared_data, tmp_path):
    """Two evaluations with sift-ransac started together on one empty cache: both finish with the
    same ranking, and the feature store holds every image once (one of them computed it, the other
    read it under the folder's lock)."""
    import json
    import subprocess
    import sys

    command = [sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--dataset", "corridor", "--k", "1", "5",
               "--rerank", "sift-ransac", "--rerank-k", "5", "--rerank-option", "max_features=300",
               "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "cache"), "--json", "--inline-arrays"]
    runs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outputs = [run.communicate(timeout=600) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], [err[-2000:] for _, err in outputs]
    first, second = (json.loads(out) for out, _ in outputs)
    assert first["per_query"]["database_indices"] == second["per_query"]["database_indices"]
    computed = sorted(run["stages"][0]["features_computed"] for run in (first, second))
    touched = len({i for row in first["per_query"]["database_indices"] for i in row})  # the top 5s, re-ordered
    assert computed == [0, 111 + touched]  # the 111 queries and every candidate, computed once between the two
    assert len({p.parent for p in (tmp_path / "cache" / "features").glob("sift-*/corridor-*/database.*.h5")}) == 1


def test_a_damaged_features_file_is_said_in_one_line_and_its_images_computed_again(shared_data, tmp_path):
    """hog + sift-ransac on corridor, a kept segment of query features then overwritten at its
    start (HDF5 cannot open it). Was: discarded and its 64 images recomputed without a word; now
    one warning line names it, the run succeeds as before."""
    import json
    import subprocess
    import sys

    command = [sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--resize", "64", "64", "--dataset",
               "corridor", "--k", "1", "--rerank", "sift-ransac", "--rerank-k", "2", "--rerank-option",
               "max_features=100", "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "cache"), "--json",
               "--quiet"]
    first = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert (first.returncode, first.stderr) == (0, "")
    segment = next((tmp_path / "cache" / "features").glob("sift-*/corridor-*/queries.1.h5"))
    with open(segment, "r+b") as f:
        f.write(b"garbage!")  # HDF5's signature
    again = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and again.stderr == (
        f"warning: Local features {segment} are damaged (Unable to synchronously open file (file signature not "
        "found)); the file was discarded and its images are computed again.\n")
    before, after = json.loads(first.stdout), json.loads(again.stdout)
    assert after["stages"][0]["features_computed"] == 64 and after["recall"] == before["recall"]


def test_the_ratio_test_keeps_a_match_clearly_nearer_than_the_second():
    query = np.zeros((2, 128), np.float32)
    query[1, 2] = 10.0  # about equally far from both database rows: ambiguous, dropped
    database = np.zeros((2, 128), np.float32)
    database[0, 0], database[1, 1] = 0.7, 1.0  # query 0: nearest at 0.7, second at 1.0
    assert ratio_matches(query, database, 0.8).tolist() == [[0, 0]]
    assert ratio_matches(query, database, 0.69).tolist() == []


def test_the_ransac_threshold_decides_which_matches_are_inliers():
    """Half the points map exactly (identity homography), half are 2.8 px off: an 8 px threshold
    takes them all, a 1 px one only the exact half."""
    rng = np.random.default_rng(0)
    query = rng.uniform(0, 400, size=(60, 2)).astype(np.float32)
    moved = query.copy()
    moved[30:] += rng.choice([-2.0, 2.0], size=(30, 2)).astype(np.float32)
    wide = inliers(query, moved, SiftRansacOptions(model="homography", threshold=8.0))
    narrow = inliers(query, moved, SiftRansacOptions(model="homography", threshold=1.0))
    assert wide == 60 and narrow == 30


def test_equal_counts_keep_their_retrieval_order():
    from vprbench.stages.base import Candidates, by_count

    k = 40  # past the short rows a non-stable sort would still keep in order
    indices = np.arange(100, 100 + k)[None]
    counts = (np.arange(k) % 3)[None]  # many ties
    found = by_count(Candidates(indices, np.zeros((1, k), np.float32)), counts)
    expected = sorted(range(k), key=lambda c: -counts[0, c])  # Python's sort is stable
    assert found.indices[0].tolist() == [100 + c for c in expected]
    assert found.scores[0].tolist() == [float(counts[0, c]) for c in expected]


def test_a_sweep_runs_again_under_another_opencv(shared_data, tmp_path, capsys, monkeypatch):
    """Before: sift-ransac had no fingerprint, so after an OpenCV upgrade a sweep served the inliers the old
    version counted, while the same run not served computed new SIFT features (stored per OpenCV version)."""
    import cv2

    from vprbench.cli.main import main
    from vprbench.evaluation import read_results

    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')

    def run() -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", 1, "--rerank", "sift-ransac", "--rerank-k", 2, "--quiet",
                                      "--data-dir", shared_data, "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)

    [first] = run()
    assert first["stages"][0]["fingerprint"] == {"opencv": cv2.__version__}
    assert len(run()) == 1  # served
    monkeypatch.setattr(cv2, "__version__", "0.0.1")
    assert len(run()) == 2, "the record of another OpenCV's inliers was served"
