"""patch-mnn on real Corridor images with a random ViT-S/14 (a pipeline check, never a result): mutual
nearest neighbours counted here independently, patches kept and reused, bad options refused."""
import shutil

import h5py
import numpy as np
import pytest
import torch

from vprbench import create_method
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.features.backbones import backbone_spec, create_model
from release_formats import official_state_dict
from vprbench.leaderboard.cells import RANDOM, build_board
from vprbench.spec import RunSettings, resolve_spec
from vprbench.stages import StageContext, create_stage
from vprbench.stages.patches import mutual_matches

#: a small, fast setting: block 1 of ViT-S/14 on Corridor resized to 56x70 (4x5 patches)
SMALL = {"backbone": "dinov2_vits14", "layer": 1, "resize": "56x70"}


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny inputs run faster on one thread; on a busy machine several threads mostly wait on each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def weights_file(tmp_path_factory):
    """A random ViT-S/14 saved in the official DINOv2 checkpoint format."""
    torch.manual_seed(1)
    spec = backbone_spec("dinov2_vits14")
    path = tmp_path_factory.mktemp("weights") / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), path)
    return path


def spec_of(shared_data, k=5, ks=(1, 5), **options):
    stage = {"name": "patch-mnn", "k": k, **SMALL, **options}
    return resolve_spec("hog", "corridor", stages=[stage], ks=ks, data_dir=shared_data)


def counted_here(query: np.ndarray, candidate: np.ndarray) -> tuple[int, float]:
    """Mutual nearest neighbours as a boolean matrix (another route than the stage's argmaxes), and the
    smallest gap between a best and a second-best similarity: no tie, so both routes must agree."""
    similarity = query.astype(np.float64) @ candidate.astype(np.float64).T
    mutual = (similarity == similarity.max(1, keepdims=True)) & (similarity == similarity.max(0, keepdims=True))
    gaps = [np.diff(np.sort(similarity, axis=axis), axis=axis).take(-1, axis=axis).min() for axis in (0, 1)]
    return int(mutual.sum()), float(min(gaps))


def test_mutual_matches_and_the_threshold():
    query = np.eye(3, dtype=np.float32)
    candidate = np.array([[1, 0, 0], [0.6, 0.8, 0], [0, 0.8, 0.6]], np.float32)  # unit rows
    # query 0 <-> candidate 0 (1.0); query 1 -> candidate 1 or 2 (0.8; the first), candidate 1 -> query 0 (0.6 vs 0.8:
    # query 1): mutual; query 2 -> candidate 2 (0.6), candidate 2 -> query 1 (0.8): not mutual
    assert mutual_matches(query, candidate) == 2
    assert mutual_matches(query, candidate, min_similarity=0.9) == 1
    assert mutual_matches(candidate, candidate) == 3  # an image matches itself patch for patch


def test_patch_mnn_reorders_hogs_candidates_by_mutual_matches(shared_data, stage_cache, corridor):
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    alone = evaluate(resolve_spec("hog", "corridor", ks=(1, 5, 10), data_dir=shared_data), settings)
    ranked = evaluate(spec_of(shared_data, k=10, ks=(1, 5, 10), weights="random"), settings)
    before = np.array(alone["per_query"]["database_indices"])
    after, scores = np.array(ranked["per_query"]["database_indices"]), np.array(ranked["per_query"]["similarities"])
    # the counts, from AnyLoc's own patch features (the stage stores them as unit float16 rows)
    method = create_method("anyloc", backbone="dinov2_vits14", weights="random", layer=1, aggregation="gap",
                           resize=(56, 70))

    def patches(paths):
        return [torch.nn.functional.normalize(f, dim=-1).numpy().astype(np.float16) for f in method.iter_patch_features(paths)]

    queries, database = patches(corridor.queries), dict(zip(np.unique(before), patches([corridor.database[i] for i in np.unique(before)])))
    assert queries[0].shape == (20, 384)  # 4 x 5 patches of 14 pixels
    counts, gaps = np.zeros(before.shape, np.int64), []
    for q, row in enumerate(before):
        for c, index in enumerate(row):
            counts[q, c], gap = counted_here(queries[q], database[index])
            gaps.append(gap)
    assert min(gaps) > 1e-9  # float64 sums of float16 products round near 1e-16
    expected = np.take_along_axis(before, np.argsort(-counts, axis=1, kind="stable"), 1)  # ties: retrieval order
    assert (after == expected).all()
    assert (scores == -np.sort(-counts, axis=1)).all()
    assert (after != before).any() and ranked["recall"]["10"] == alone["recall"]["10"]
    cost = ranked["stages"][0]
    assert cost["provenance"]["weights"] == {"source": "random"} and cost["provenance"]["backbone"]["name"] == "dinov2_vits14"
    assert cost["stored_bytes_per_database_image"] == 20 * 384 * 2  # float16
    # the stored patches are those features
    stored = sorted((stage_cache / "features").glob("patches-*/corridor-*/queries.*.h5"))
    assert len({p.parent for p in stored}) == 1  # one store, its segments (images 0-63 in the first)
    with h5py.File(next(p for p in stored if p.name == "queries.1.h5")) as f:
        np.testing.assert_allclose(f["images/7/patches"][...].astype(np.float32), queries[7].astype(np.float32), atol=1e-3)
    # a run on random weights is recorded as such and fills no cell of the board
    board = build_board([ranked])
    assert not board.cells and board.excluded[0][1] == RANDOM


def test_patches_are_kept_and_a_second_run_loads_no_model(shared_data, tmp_path, weights_file, monkeypatch):
    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path)
    spec = spec_of(shared_data, weights=str(weights_file))
    first = evaluate(spec, settings)
    assert first["stages"][0]["features_computed"] > 111  # every query and the candidates' database images
    assert first["stages"][0]["provenance"]["weights"]["source"] == "user"
    digest = first["stages"][0]["provenance"]["weights"]["sha256"]
    assert spec.stages[0].files == {"weights": f"sha256:{digest}"}
    row = next(iter(build_board([first]).cells.values())).row  # the user's weights: a marked row, never official
    assert not row.official and f"patch-mnn user weights sha256:{digest[:12]}" in row.mark

    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded although every patch is stored")

    monkeypatch.setattr("vprbench.methods.anyloc.load_backbone", no_model)
    again = evaluate(spec, settings)
    assert again["stages"][0]["features_computed"] == 0
    assert again["per_query"]["database_indices"] == first["per_query"]["database_indices"]


def test_another_layers_patches_are_never_mixed(shared_data, tmp_path, corridor, weights_file):
    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path)
    evaluate(spec_of(shared_data, weights=str(weights_file)), settings)
    context = StageContext(dataset=corridor, database=None, queries=None, cache_dir=tmp_path)
    layer2 = create_stage("patch-mnn", {"k": 5, **SMALL, "layer": 2, "weights": str(weights_file)})
    folder = context.features("patches", layer2.feature_identity(context)).path
    assert not folder.exists()  # another layer: a store of its own
    layer1 = next(p for p in (tmp_path / "features").glob("patches-*/corridor-*"))
    shutil.copytree(layer1, folder)  # the first layer's files where the second's belong
    with pytest.raises(VPRBenchError, match=r"Local features .*database\.\d+\.h5 were computed by another extractor "
                                            r"\('patches' with layer=1\), not 'patches' with layer=2 as this run"):
        evaluate(spec_of(shared_data, weights=str(weights_file), layer=2), settings)


@pytest.mark.parametrize("options, message", [
    ({"backbone": "dinov2_vitz14"}, r"Stage 'patch-mnn' option backbone: Unknown backbone 'dinov2_vitz14'. Did you mean"),
    ({"layer": 12}, r"Stage 'patch-mnn': layer 12 is out of range for dinov2_vits14: it has 12 blocks, 0..11"),
    ({"facet": "keys"}, r"Stage 'patch-mnn': facet 'keys': dinov2_vits14 gives token, query, key, value"),
    ({"weights": "/nowhere/w.pth"}, r"Stage 'patch-mnn': weights file /nowhere/w.pth does not exist"),
    ({"resize": "big"}, r"Stage 'patch-mnn' option resize: takes HEIGHT WIDTH"),
    ({"min_similarity": 2}, r"Stage 'patch-mnn' option min_similarity: Input should be less than or equal to 1"),
    ({"lyer": 3}, r"Stage 'patch-mnn' does not take option lyer. Did you mean: layer?"),
])
def test_bad_options_are_refused_with_the_spec(shared_data, options, message):
    with pytest.raises(VPRBenchError, match=message):
        spec_of(shared_data, **options)


def test_the_options_resolve_to_one_identity(shared_data, weights_file, tmp_path):
    spec = spec_of(shared_data, weights="random")
    options = spec.stages[0].options
    assert options == {"k": 5, "backbone": "dinov2_vits14", "weights": "random", "layer": 1, "facet": "value",
                       "resize": [56, 70], "min_similarity": None}
    assert spec.label() == "hog + patch-mnn@5 [backbone=dinov2_vits14 layer=1 resize=56x70]"
    unset = resolve_spec("hog", "corridor", stages=[{"name": "patch-mnn", "k": 5, "backbone": "dinov2_vits14"}],
                         ks=(1, 5), data_dir=shared_data)
    assert unset.stages[0].options["layer"] == 9  # AnyLoc's block 31 of 40 at the same relative depth
    copy = tmp_path / "copy.pth"
    shutil.copy(weights_file, copy)  # one file under two names: one run
    assert spec_of(shared_data, weights=str(copy)).row_key == spec_of(shared_data, weights=str(weights_file)).row_key
    assert spec_of(shared_data, weights=str(copy)).row_key != spec.row_key


def test_the_command_line_refuses_a_bad_option_in_one_line(shared_data, tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "vprbench", "evaluate", "--method", "hog", "--dataset", "corridor",
                           "--data-dir", str(shared_data), "--cache-dir", str(tmp_path), "--rerank", "patch-mnn",
                           "--rerank-k", "10", "--rerank-option", "backbone=dinov2_vits14", "--rerank-option", "layer=40"],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: Stage 'patch-mnn': layer 40 is out of range for dinov2_vits14: it has 12 blocks, 0..11 (0-based)."]
    assert not (tmp_path / "results").exists()


def test_the_release_is_taken_through_the_weights_resolver(shared_data, tmp_path, monkeypatch):
    def offline(url, *args, **kwargs):
        raise OSError("no network")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    settings, spec = RunSettings(data_dir=shared_data, cache_dir=tmp_path), spec_of(shared_data)
    with pytest.raises(VPRBenchError, match=r"Stage 'patch-mnn': backbone dinov2_vits14: could not download "
                                            r"dinov2_vits14_pretrain\.pth .*pass it with --rerank-option weights=PATH"):
        evaluate(spec, settings)
    backbone = backbone_spec("dinov2_vits14")
    torch.manual_seed(2)
    state = official_state_dict(create_model(backbone), backbone)
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda url, to, **kwargs: torch.save(state, to))
    found = evaluate(spec, settings)["stages"][0]["provenance"]["weights"]  # downloaded by vprbench: official
    assert (tmp_path / "torch" / "hub" / "checkpoints" / backbone.file_name).is_file()
    assert found == {"source": "official", "url": backbone.url, "recognised_by": "download", "release": "dinov2"}
