"""The stage interface: options checked with the spec, stages run by evaluate, what they return checked."""
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.spec import RunSettings, resolve_spec
from vprbench.stages import Candidates, Stage, check_candidates, registry
from vprbench.stages.features import FeatureStore


def spec_of(shared_data, stages, ks=(1, 5)):
    return resolve_spec("hog", "corridor", stages=stages, ks=ks, data_dir=shared_data)


def test_stage_options_are_checked_when_the_spec_is_made(shared_data):
    spec = spec_of(shared_data, [{"name": "aqe", "k": "20"}])
    assert spec.stages[0].options == {"k": 20, "n": 10, "alpha": 3.0}  # resolved: one identity per stage
    assert spec.row_key == spec_of(shared_data, [{"name": "aqe", "options": {"k": 20}}]).row_key
    assert spec.row_key == spec_of(shared_data, [{"name": "aqe", "options": {"k": 20}, "k": 20}]).row_key  # once, agreeing
    assert spec.row_key != spec_of(shared_data, [{"name": "aqe", "k": 30}]).row_key != spec_of(shared_data, []).row_key
    for stage, message in [({"name": "aqe", "k": "many"}, "Stage 'aqe' option k: Input should be a valid integer"),
                           ({"name": "aqe", "kk": 3}, "Stage 'aqe' does not take option kk. Did you mean: k?"),
                           ({"name": "aqe", "k": 0}, "Stage 'aqe' option k: Input should be greater than or equal to 1"),
                           ("sift-ransak", "Unknown stage 'sift-ransak'. Did you mean: sift-ransac?"),
                           ({"k": 3}, "A stage needs a name"),
                           ({"name": "aqe", "options": "k=20"}, "Stage 'aqe': options must be a table of option = value"),
                           ({"name": "aqe", "options": 5}, "Stage 'aqe': options must be a table"),
                           ({"name": "aqe", "options": [["k", 20]]}, "Stage 'aqe': options must be a table"),
                           ({"name": "aqe", "options": {"n": 3}, "n": 4},
                            "Stage 'aqe': option n is given twice, 3 in options and 4 beside the name; give it once")]:
        with pytest.raises(VPRBenchError, match=message):
            spec_of(shared_data, [stage])
    with pytest.raises(VPRBenchError, match=r"re-ranks the top 10 \(--rerank-k\), fewer than the largest K reported \(20\)"):
        spec_of(shared_data, [{"name": "aqe", "k": 10}], ks=(1, 20))


def test_a_re_ranking_run_reorders_the_retrievers_candidates(shared_data, stage_cache):
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    alone = evaluate(spec_of(shared_data, [], ks=(1, 5, 20)), settings)
    ranked = evaluate(spec_of(shared_data, [{"name": "aqe", "k": 20, "n": 1}], ks=(1, 5, 20)), settings)
    assert alone["track"] == "single-image" and alone["stages"] == []
    assert ranked["track"] == "re-ranked" and ranked["row_key"] != alone["row_key"]
    before, after = np.array(alone["per_query"]["database_indices"]), np.array(ranked["per_query"]["database_indices"])
    assert after.shape == before.shape == (111, 20)
    assert (np.sort(after, 1) == np.sort(before, 1)).all()  # the same 20 candidates, re-ordered
    assert (after != before).any()
    assert ranked["recall"]["20"] == alone["recall"]["20"]  # the ceiling: a re-ranker of the top 20 keeps R@20
    cost = ranked["stages"][0]
    assert cost["name"] == "aqe" and cost["candidates_in"] == 20 and cost["ms_per_query"] > 0
    assert cost["stored_bytes_per_database_image"] == 0 and cost["peak_rss_bytes"] > 0


def test_expansion_beyond_what_it_can_sum_in_is_refused(shared_data, stage_cache):
    """Was: aqe's n was capped at its k, and dba's at the database's other images, silently: "aqe@20
    [n=50]" and "aqe@20 [n=20]" were two rows of one computation."""
    with pytest.raises(VPRBenchError, match=r"Stage 'aqe': n = 50 sums in more candidates than the top k = 20 it "
                                            r"re-ranks; give n <= 20, or a larger k\.$"):
        spec_of(shared_data, [{"name": "aqe", "k": 20, "n": 50}])
    assert spec_of(shared_data, [{"name": "aqe", "k": 20, "n": 20}]).stages[0].options["n"] == 20
    with pytest.raises(VPRBenchError, match=r"n = 10 \(its default\) sums in more candidates than the top k = 5"):
        spec_of(shared_data, [{"name": "aqe", "k": 5}])
    before = sorted(stage_cache.rglob("*"))
    with pytest.raises(VPRBenchError, match=r"Stage 'dba': n = 111 nearest database images, but each database image "
                                            r"of corridor has 110 others: give n <= 110\.$"):
        evaluate(spec_of(shared_data, [{"name": "dba", "k": 20, "n": 111}]),
                 RunSettings(data_dir=shared_data, cache_dir=stage_cache))
    assert sorted(stage_cache.rglob("*")) == before  # refused before any work


def test_rerank_k_larger_than_the_database_is_refused(shared_data, stage_cache):
    with pytest.raises(VPRBenchError, match=r"Stage 'aqe' re-ranks the top 500 .* database of corridor holds 111 "
                                            r"images: give --rerank-k <= 111"):
        evaluate(spec_of(shared_data, [{"name": "aqe", "k": 500}]), RunSettings(data_dir=shared_data, cache_dir=stage_cache))


class Broken(Stage):
    """A plugin that breaks the contract in the way its option says."""

    from vprbench.stages import RerankOptions as Options

    def apply(self, candidates, context):
        broken = self.options.k
        if broken == 11:  # an index past the database
            return Candidates(candidates.indices + 1000, candidates.scores)
        return Candidates(candidates.indices[1:], candidates.scores[1:])  # a query dropped


@pytest.mark.parametrize("k, message", [(11, r"Stage 'broken' returned database indices out of range for query 0 "
                                                r"\(the database has 111 images, 0..110\)"),
                                        (12, "Stage 'broken' returned candidates for 110 queries, but there are 111")])
def test_a_stage_that_breaks_the_contract_is_named(shared_data, stage_cache, scratch_stages, k, message):
    registry.register_stage("broken", Broken)
    with pytest.raises(VPRBenchError, match=message):
        evaluate(spec_of(shared_data, [{"name": "broken", "k": k}]), RunSettings(data_dir=shared_data, cache_dir=stage_cache))


def test_check_candidates():
    good = Candidates(np.array([[2, 0, 1]]), np.array([[3.0, 2.0, 1.0]], np.float32))
    assert check_candidates(good, "s", 1, 3, 3).indices.dtype == np.int64
    for found, message in [(good, "fewer than the largest K reported \\(4\\)"),
                           (Candidates(np.array([[2, 2, 1]]), good.scores), "one database image twice"),
                           (Candidates(good.indices, np.array([[np.nan, 1, 1]])), "not finite"),
                           (Candidates(good.indices, np.array([[3.0, 1.0, 2.0]], np.float32)),
                            "the candidates of query 0 not best first \\(scores must not increase along a row\\)"),
                           (Candidates(good.indices.astype(float), good.scores), "not integers"),
                           ((good.indices, good.scores), "tuple, not Candidates")]:
        with pytest.raises(VPRBenchError, match="Stage 's' returned .*" + message):
            check_candidates(found, "s", 1, 3, 4 if "largest" in message else 3)


def test_feature_store_resumes_and_refuses_another_extractors_file(tmp_path):
    calls = []

    def compute(row):
        calls.append(row)
        return {"points": np.full((row + 1, 2), row, np.float32)}

    store = FeatureStore("sift", {"options": {"n": 1}}, "set", {"database": "abc"}, tmp_path)
    with store.opened("database", compute) as get:
        assert get(2)["points"].shape == (3, 2) and get(2)["points"][0, 0] == 2
    with store.opened("database", compute) as get:
        assert get(2)["points"].shape == (3, 2) and get(0)["points"].shape == (1, 2)
    assert calls == [2, 0]  # row 2 was read back, not computed again
    assert [p.name for p in store.files("database")] == ["database.1.h5", "database.2.h5"]  # a segment per run
    assert store.bytes_per_image() == (3 * 2 * 4 + 1 * 2 * 4) / 2
    other = FeatureStore("sift", {"options": {"n": 2}}, "set", {"database": "abc"}, tmp_path)
    other.path.mkdir(parents=True)
    store.files("database")[0].rename(other.path / "database.1.h5")  # a file of another extractor where this one's belongs
    with pytest.raises(VPRBenchError, match=r"Local features .*database.1.h5 were computed by another extractor \('sift' with options=\{'n': 1\}\), "
                                            r"not 'sift' with options=\{'n': 2\} as this run computes them: delete that file"):
        with other.opened("database", compute):
            pass


def test_flags_and_plans_make_the_same_stage_list(shared_data):
    import argparse

    from vprbench.cli.options import add_spec_options, spec_overrides
    from vprbench.sweep import build_plan

    parser = argparse.ArgumentParser()
    add_spec_options(parser)
    args = parser.parse_args(["--rerank", "sift-ransac", "--rerank-k", "50", "--rerank-option", "model=homography",
                              "--k", "1", "5"])
    stages = spec_overrides(args)["stages"]
    assert stages == [{"name": "sift-ransac", "model": "homography", "k": 50}]
    flag = spec_of(shared_data, stages)
    plan = build_plan({"methods": [{"name": "hog", "stages": [{"name": "sift-ransac", "k": 50, "model": "homography"}]}],
                       "datasets": ["corridor"], "k": [1, 5]}, "plan", data_dir=shared_data)
    assert plan.cells[0].spec.key == flag.key and flag.label() == "hog + sift-ransac@50 [model=homography]"
    with pytest.raises(VPRBenchError, match="stages of method 'hog' must be a list of tables"):
        build_plan({"methods": [{"name": "hog", "stages": "aqe"}], "datasets": ["corridor"]}, "plan", data_dir=shared_data)
    with pytest.raises(VPRBenchError, match="--sequence-length and --sequence-option need --sequence STAGE"):
        spec_overrides(parser.parse_args(["--sequence-length", "5"]))
