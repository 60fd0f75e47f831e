"""The `sad` method (SeqSLAM's front end): patch normalisation, its descriptors on real images,
retrieval by the mean absolute difference, and its bad options."""
import json

import cv2
import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.evaluation.retrieve import retrieve
from vprbench.methods import create_method
from vprbench.methods.sad import patch_normalise
from vprbench.spec import RunSettings, resolve_spec

TOLERANCE = 1e-5  # float32 means and deviations of 64 pixels


def test_patches_are_normalised_one_by_one_and_flat_ones_become_zero():
    rng = np.random.default_rng(0)
    image = np.zeros((1, 16, 24), dtype=np.float32)
    image[0, :8, :8] = 50 + 10 * rng.standard_normal((8, 8))
    image[0, 8:, 8:16] = 200.0  # flat: no contrast
    image[0, :8, 16:] = np.arange(64).reshape(8, 8)
    out = patch_normalise(image, 8)[0]
    for rows, cols in ((slice(0, 8), slice(0, 8)), (slice(0, 8), slice(16, 24))):
        assert abs(out[rows, cols].mean()) < TOLERANCE
        assert abs(out[rows, cols].std(ddof=1) - 1) < TOLERANCE
    assert (out[8:, 8:16] == 0).all() and (out[8:, :8] == 0).all()
    ramp = np.arange(64, dtype=np.float64)
    np.testing.assert_allclose(out[:8, 16:].ravel(), (ramp - ramp.mean()) / ramp.std(ddof=1), atol=TOLERANCE)


def test_descriptors_of_real_images(shared_data):
    method = create_method("sad")
    assert method.compare == "mean-absolute-difference" and method.provenance() == {"weights": {"source": "none"}}
    paths = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]
    rows = method.describe(paths)
    assert rows.shape == (3, 32 * 64) and rows.dtype == np.float32
    grey = cv2.cvtColor(cv2.imread(str(paths[1]))[:, :, ::-1], cv2.COLOR_RGB2GRAY)
    small = cv2.resize(grey, (64, 32), interpolation=cv2.INTER_AREA).astype(np.float32)
    np.testing.assert_allclose(rows[1], patch_normalise(small[None], 8).ravel(), atol=TOLERANCE)
    assert create_method("sad", resize=[16, 32], patch=4).describe(paths[:1]).shape == (1, 512)


@pytest.mark.parametrize("options, message", [
    ({"patch": 0}, "option patch takes a whole number >= 2"),
    ({"resize": [30, 64]}, "must be a whole number of 8-pixel patches"),
    ({"resize": "native"}, "option resize takes the size images are downsampled to"),
])
def test_bad_options_are_refused(options, message):
    with pytest.raises(VPRBenchError, match=message):
        create_method("sad", **options)


def test_retrieval_is_by_mean_absolute_difference_and_exact_only():
    method = create_method("sad")
    rng = np.random.default_rng(1)
    database = rng.standard_normal((30, 2048)).astype(np.float32)
    queries = database[::-1] + 0.3 * rng.standard_normal((30, 2048)).astype(np.float32)
    found = retrieve(method, database, queries, 3)
    distance = np.abs(queries[:, None] - database[None]).mean(axis=2)
    np.testing.assert_array_equal(found.indices, np.argsort(distance, axis=1)[:, :3])
    np.testing.assert_allclose(found.scores, -np.sort(distance, axis=1)[:, :3], atol=TOLERANCE)
    assert found.info["compare"] == "mean-absolute-difference"
    with pytest.raises(VPRBenchError, match="only exact search does; drop --index hnsw"):
        retrieve(method, database, queries, 3, index="hnsw")


def test_sad_on_corridor_end_to_end(shared_data, tmp_path, capsys):
    spec = resolve_spec("sad", "corridor", ks=(1, 5))
    record = evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=tmp_path))
    assert record["search"]["compare"] == "mean-absolute-difference"
    assert record["descriptor_dim"] == 2048
    assert 0 < record["recall"]["1"] <= record["recall"]["5"] <= 100
    code = main(["evaluate", "--method", "sad", "--dataset", "corridor", "--data-dir", str(shared_data),
                 "--index", "hnsw", "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code != 0 and "only exact search does" in err and "Traceback" not in err
    assert json.loads(json.dumps(record["recall"]))  # plain data


def test_a_plan_pairing_sad_with_an_approximate_index_lists_it_with_its_other_problems(tmp_path, capsys, monkeypatch):
    """Was: the plan check passed it (hog's cells would run) and sad's cells failed only when they ran."""
    monkeypatch.setenv("COLUMNS", "1000")
    plan = tmp_path / "plan.toml"
    plan.write_text('search = { index = "hnsw" }\n\n[[methods]]\nname = "hog"\n\n[[methods]]\nname = "sad"\n\n'
                    '[[methods]]\nname = "hogg"\n\n[[datasets]]\nname = "corridor"\n')
    assert main(["run", str(plan), "--cache-dir", str(tmp_path / "cache")]) == 1
    err = " ".join(capsys.readouterr().err.split())
    assert "2 problem(s); nothing was run" in err and "plan.toml:10: unknown method 'hogg'" in err, err
    assert "plan.toml:7: Method 'sad' compares descriptors by mean-absolute-difference, which only exact search " \
           "does; drop --index hnsw" in err and "Traceback" not in err, err
    assert not (tmp_path / "cache").exists()


def test_a_matrix_or_a_run_of_sad_with_an_approximate_index_is_refused_before_any_image_is_described(
        shared_data, tmp_path, capsys, monkeypatch):
    """Was: the matrix ran hog's cell, then sad's failed after describing Corridor; the single run
    described the whole dataset (stores written) before it was refused."""
    monkeypatch.setenv("COLUMNS", "1000")
    cache = tmp_path / "cache"
    for methods in (["sad", "hog"], ["sad"]):
        code = main(["evaluate", "--method", *methods, "--dataset", "corridor", "--index", "ivf-pq",
                     "--data-dir", str(shared_data), "--cache-dir", str(cache)])
        err = " ".join(capsys.readouterr().err.split())
        assert code == 1 and "'sad' compares descriptors by mean-absolute-difference, which only exact search does; " \
                             "drop --index ivf-pq" in err and "Traceback" not in err, err
        assert not (cache / "stores").exists() and not (cache / "results").exists(), methods
    with pytest.raises(VPRBenchError, match="only exact search does; drop --index hnsw"):
        resolve_spec("sad", "corridor", search="hnsw")


def test_a_budget_too_small_for_sads_search_names_a_comparison_not_sequence_matching():
    """sad's retrieval is the sequence search with sequences of one frame: its refusal said "sequence
    matching", which a run without a sequence stage does not do."""
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    database, queries = (rng.random((50, 16), dtype=np.float32) for _ in range(2))
    sad = SimpleNamespace(name="sad", compare="mean-absolute-difference")
    with pytest.raises(VPRBenchError, match=r"too small for comparing queries against 50 database images: .* Raise "
                                            r"--search-memory"):
        retrieve(sad, database, queries, 5, memory_budget=10_000)
