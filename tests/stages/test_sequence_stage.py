"""The sequence stages end to end through `evaluate`: real Corridor images, the record's track and
options, sad + SeqSLAM, and the refusals (an unordered dataset, bad options)."""
import pytest

from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.spec import RunSettings, resolve_spec
from vprbench.stages import available_stages, create_stage


def run(method, stage, shared_data, cache, ks=(1, 5)):
    spec = resolve_spec(method, "corridor", stages=[stage], ks=ks)
    return spec, evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=cache))


def test_hog_with_sequences_on_corridor_offline_and_causal(shared_data, tmp_path):
    single = evaluate(resolve_spec("hog", "corridor", ks=(1, 5)), RunSettings(data_dir=shared_data, cache_dir=tmp_path))
    offline_spec, offline = run("hog", {"name": "diagonal", "length": 5}, shared_data, tmp_path)
    causal_spec, causal = run("hog", {"name": "diagonal", "length": 5, "mode": "causal"}, shared_data, tmp_path)
    assert offline["track"] == causal["track"] == "sequence" and single["track"] == "single-image"
    assert [s["options"]["mode"] for s in (offline["stages"][0], causal["stages"][0])] == ["offline", "causal"]
    assert offline_spec.row_key != causal_spec.row_key  # the mode is part of the identity
    assert offline["descriptors_computed"]["database"] == 0  # sequences reuse the stored descriptors
    # on a corridor walked twice, neighbours in time agree with each other: sequences help
    assert offline["recall"]["1"] > single["recall"]["1"]
    assert causal["recall"]["1"] > single["recall"]["1"]
    assert 0 < offline["max_f1"] <= 1 and offline["auc_pr"] > 0
    # it matches against the whole database, so retrieval's top K is no ceiling of it (R@5 passes retrieval's)
    assert offline["recall"]["5"] > single["recall"]["5"]
    assert all("ceiling_recall" not in run["stages"][0] for run in (offline, causal))


def test_sad_with_seqslam_end_to_end(shared_data, tmp_path):
    alone = evaluate(resolve_spec("sad", "corridor", ks=(1, 5)), RunSettings(data_dir=shared_data, cache_dir=tmp_path))
    spec, record = run("sad", "seqslam", shared_data, tmp_path)
    assert spec.stages[0].options == {"length": 10, "mode": "offline", "enhance_window": 10, "v_min": 0.8,
                                      "v_max": 1.2, "v_step": 0.1, "uniqueness_window": 10}
    assert record["track"] == "sequence" and record["method"] == "sad"
    assert record["search"]["compare"] == "mean-absolute-difference"
    # measured: 40.5 alone, 47.7 with SeqSLAM (a direct port of OpenSeqSLAM's MATLAB gets 45.5 on its
    # 101 interior queries); the scores are minus OpenSeqSLAM's quality ratio
    assert record["recall"]["1"] == pytest.approx(47.7477, abs=0.01) and alone["recall"]["1"] == pytest.approx(40.5405, abs=0.01)


@pytest.mark.parametrize("options, message", [
    ({"length": 0}, "option length: Input should be greater than or equal to 1"),
    ({"length": "ten"}, "option length: Input should be a valid integer"),
    ({"mode": "future"}, "option mode: Input should be 'offline' or 'causal'"),
    ({"v_min": 1.5}, "v_min \\(1.5\\) must not exceed v_max"),
    ({"v_step": 0.00001}, "more than 1000 velocities"),
    ({"k": 5}, "does not take option k"),
])
def test_bad_options_are_refused_when_the_spec_is_made(options, message):
    with pytest.raises(VPRBenchError, match=message):
        resolve_spec("hog", "corridor", stages=[{"name": "seqslam", **options}])


def test_a_sequence_longer_than_the_queries_is_refused(shared_data, tmp_path):
    with pytest.raises(VPRBenchError, match="--sequence-length 500 exceeds the 111 queries of corridor"):
        run("hog", {"name": "diagonal", "length": 500}, shared_data, tmp_path)
    assert not list(tmp_path.rglob("*.h5"))  # refused before any descriptor is computed


def test_a_uniqueness_window_over_the_whole_database_is_refused(shared_data, tmp_path):
    """Before: accepted; a match in the middle had no second best, its score fell back to minus its bare cost,
    another scale than the other queries' ratios in one PR curve (AUC-PR 0.51 at window 500, 0.63 at 10)."""
    with pytest.raises(VPRBenchError, match="uniqueness_window 110 leaves out every one of the 111 database images "
                                            "of corridor .* give uniqueness_window <= 109"):
        run("hog", {"name": "seqslam", "length": 3, "uniqueness_window": 110}, shared_data, tmp_path)
    assert not list(tmp_path.rglob("*.h5"))  # refused before any descriptor is computed


@pytest.mark.parametrize("dataset", ["pitts30k", "tokyo247"])
def test_unordered_benchmarks_are_refused_from_their_manifest(dataset, capsys, tmp_path):
    code = main(["evaluate", "--method", "hog", "--dataset", dataset, "--sequence", "seqslam",
                 "--data-dir", str(tmp_path / "no-data"), "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "Traceback" not in err and len(err.splitlines()) == 1
    assert "Sequence stage 'seqslam' needs a dataset whose database and queries are ordered traverses" in err
    assert f"{dataset!r} is not one: its images are separate photographs of places" in err
    assert not list(tmp_path.rglob("*.h5")) and not list(tmp_path.rglob("*.json"))


def test_pitts30k_on_disk_is_refused_before_any_descriptor(pitts30k_tree, tmp_path):
    # a Dataset given directly (no manifest check in the spec): the stage's own check refuses it
    dataset = load_dataset("pitts30k", pitts30k_tree.data)
    spec = resolve_spec("hog", dataset)
    staged = spec.model_copy(update={"stages": resolve_spec("hog", "corridor", stages=["seqslam"]).stages})
    with pytest.raises(VPRBenchError, match="'pitts30k' is not one"):
        evaluate(staged, RunSettings(cache_dir=tmp_path), dataset=dataset)
    assert not list(tmp_path.rglob("*.h5"))


def test_sequence_stages_are_registered_on_the_sequence_track():
    assert {"seqslam", "diagonal"} <= set(available_stages())
    stage = create_stage("diagonal", {"length": 3})
    assert stage.track == "sequence" and stage.candidates_needed() is None and stage.options.mode == "offline"
