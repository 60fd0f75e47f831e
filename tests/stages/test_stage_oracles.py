"""Each built-in stage given perfect inputs puts the true match first (R@1 = 100): queries that are the database
images themselves (for the image re-rankers in another format: grey, RGBA, 16-bit, twice the size), handed over
with the true match last; identical traverses for the sequence stages, ends included. A re-ranker only re-orders
what it was given. And the stage chain and option types: a re-ranker before a sequence stage (its work thrown
away), a re-ranker deeper than the one before it (labelled @K, re-ranked fewer), true/false read as 1/0."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from vprbench.errors import VPRBenchError
from vprbench.row_sources import ArrayRows
from vprbench.stages import Candidates, create_stage
from vprbench.stages.base import StageContext
from vprbench.stages.sequence.search import sequence_search

from oracles import PLACES, Images, assert_oracle, variants, worst_first

@pytest.fixture
def one_torch_thread():
    """Tiny inputs: one thread is faster on a busy machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("stage, options", [
    ("sift-ransac", {}),
    ("sift-ransac", {"model": "homography", "features": "sift"}),
    ("patch-mnn", {"backbone": "dinov2_vits14", "layer": 1, "resize": "56x70", "weights": "random"}),
])
def test_an_image_re_ranker_puts_the_same_place_first_in_any_format(stage, options, corridor, tmp_path, one_torch_thread):
    database = [corridor.database[row] for row in PLACES]
    images = Images(database, variants(corridor, tmp_path))
    given = worst_first(len(PLACES))
    ranker = create_stage(stage, {"k": len(PLACES), **options})
    found = ranker.apply(given, StageContext(dataset=images, database=None, queries=None, cache_dir=tmp_path / "cache"))
    assert_oracle(given, found)
    assert (found.scores[:, 0] > found.scores[:, 1]).all()  # first by a margin, not by the tie rule


def test_a_query_with_no_inliers_anywhere_keeps_its_retrieval_order(corridor, tmp_path):
    """A blank query (no SIFT keypoint): every candidate scores 0, a tie kept in the order retrieval gave."""
    blank = tmp_path / "blank.png"
    Image.fromarray(np.zeros((120, 160), np.uint8)).save(blank)
    database = [corridor.database[row] for row in PLACES]
    given = worst_first(len(PLACES))
    images = Images(database, [blank, *variants(corridor, tmp_path)[1:]])
    found = create_stage("sift-ransac", {"k": len(PLACES)}).apply(
        given, StageContext(dataset=images, database=None, queries=None, cache_dir=tmp_path / "cache"))
    assert found.indices[0].tolist() == given.indices[0].tolist() and found.scores[0].tolist() == [0.0] * len(PLACES)
    assert found.indices[1:, 0].tolist() == list(range(1, len(PLACES)))  # the others unaffected


def unit_rows(count, dim, seed):
    rows = np.random.default_rng(seed).standard_normal((count, dim))
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("stage", ["aqe", "dba"])
@pytest.mark.parametrize("n", [1, 3, 10])
def test_expansion_puts_the_same_descriptor_first(stage, n):
    database, rng = unit_rows(30, 64, seed=5), np.random.default_rng(6)
    others = [rng.choice(np.setdiff1d(np.arange(30), [q]), 9, replace=False) for q in range(10)]
    indices = np.array([[*row, q] for q, row in enumerate(others)], dtype=np.int64)  # the true one last
    given = Candidates(indices, np.tile(np.linspace(1, 0, 10, dtype=np.float32), (10, 1)))
    context = StageContext(dataset=None, database=ArrayRows(database), queries=ArrayRows(database[:10]))
    found = create_stage(stage, {"k": 10, "n": n}).apply(given, context)
    assert_oracle(given, found)


def smooth_traverse(count=40, dim=32, seed=0):
    """A route whose neighbouring frames look alike (as Corridor's), unit rows."""
    rng = np.random.default_rng(seed)
    route = np.cumsum(rng.standard_normal((count, dim)), axis=0) + 3 * rng.standard_normal((count, dim))
    return (route / np.linalg.norm(route, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("compare", ["cosine", "mean-absolute-difference"])
@pytest.mark.parametrize("seed", range(3))
def test_sequence_stages_match_a_traverse_to_itself_ends_included(seed, compare):
    route = smooth_traverse(seed=seed)
    everywhere = list(range(len(route)))
    for length in (1, 2, 5, 10, len(route)):  # the last: a window as long as the traverse
        for mode in ("offline", "causal"):
            found = sequence_search(route, route, 3, score="diagonal", length=length, mode=mode, compare=compare)
            assert found.indices[:, 0].tolist() == everywhere, (length, mode)
    for length in (3, 5, 10, len(route)):  # SeqSLAM's enhancement needs a sequence to beat one-frame contrast
        found = sequence_search(route, route, 3, score="seqslam", length=length, mode="offline", compare=compare)
        assert found.indices[:, 0].tolist() == everywhere, length
        found = sequence_search(route, route, 3, score="seqslam", length=length, mode="causal", compare=compare)
        assert found.indices[1:, 0].tolist() == everywhere[1:], length  # query 0's causal sequence is one frame


def test_sequence_stages_through_their_stage_with_a_window_as_long_as_the_traverse(monkeypatch):
    """The stage on perfect inputs, every trajectory leaving the traverse on one side or both."""
    import vprbench.datasets.traverse as traverse

    route = smooth_traverse(12)
    monkeypatch.setattr(traverse, "traverse_orders", lambda dataset, what: {"database": np.arange(12),
                                                                          "queries": np.arange(12)})
    for name in ("seqslam", "diagonal"):
        context = StageContext(dataset=None, database=ArrayRows(route), queries=ArrayRows(route))
        found = create_stage(name, {"length": 12}).apply(worst_first(12), context)
        assert found.indices[:, 0].tolist() == list(range(12)), name


# ---------------------------------------------------------------- the chain of stages, and option types
def test_a_re_ranker_before_a_sequence_stage_is_refused(shared_data):
    """Was: 'hog + aqe@5 + diagonal' ran aqe, then the sequence stage matched against the whole database and
    ignored it: the same result as 'hog + diagonal', under another name and row."""
    from vprbench.spec import resolve_spec

    with pytest.raises(VPRBenchError, match=r"^Stage 'aqe' runs before sequence stage 'diagonal', which matches every "
                                            r"query against the whole database and ignores the candidates it is given: "
                                            r"put 'diagonal' first"):
        resolve_spec("hog", "corridor", stages=[{"name": "aqe", "k": 10}, "diagonal"], ks=(1, 5), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match=r"^A run takes one sequence stage, got 'seqslam' and 'diagonal'"):
        resolve_spec("hog", "corridor", stages=["seqslam", "diagonal"], ks=(1, 5), data_dir=shared_data)
    after = resolve_spec("hog", "corridor", stages=["diagonal", {"name": "aqe", "k": 10}], ks=(1, 5), data_dir=shared_data)
    assert after.label() == "hog + diagonal + aqe@10"


def test_both_flags_run_the_sequence_stage_first():
    import argparse

    from vprbench.cli.options import add_spec_options, stage_flags

    parser = argparse.ArgumentParser()
    add_spec_options(parser)
    args = parser.parse_args(["--rerank", "aqe", "--rerank-k", "5", "--sequence", "diagonal", "--sequence-length", "3"])
    assert stage_flags(args) == [{"name": "diagonal", "length": 3}, {"name": "aqe", "k": 5}]


def test_a_re_ranker_cannot_re_rank_deeper_than_the_one_before_hands_over(shared_data):
    """Was: 'hog + aqe@5 + dba@50' ran, dba re-ranking the 5 aqe returned (its record: candidates_in 5)."""
    from vprbench.spec import resolve_spec

    with pytest.raises(VPRBenchError, match=r"^Stage 'dba' re-ranks the top 50, but stage 'aqe' before it hands over "
                                            r"only its top 10: give 'dba' k <= 10, or 'aqe' a larger k\.$"):
        resolve_spec("hog", "corridor", stages=[{"name": "aqe", "k": 10}, {"name": "dba", "k": 50}], ks=(1, 5),
                     data_dir=shared_data)
    shallower = resolve_spec("hog", "corridor", stages=[{"name": "aqe", "k": 50}, {"name": "dba", "k": 5}], ks=(1, 5),
                             data_dir=shared_data)
    assert shallower.label() == "hog + aqe@50 + dba@5"


@pytest.mark.parametrize("stage, option, value", [
    ("aqe", "n", True), ("sift-ransac", "max_features", False), ("sift-ransac", "ratio", True),
    ("seqslam", "length", True), ("patch-mnn", "min_similarity", False),
])
def test_true_or_false_is_not_a_number(stage, option, value):
    """Was: true was read as 1 and false as 0 (max_features=false: every keypoint), silently."""
    with pytest.raises(VPRBenchError, match=rf"^Stage '{stage}' option {option}: takes a number, not "
                                            rf"{str(value).lower()}\.$"):
        create_stage(stage, {option: value})


def test_the_command_line_refuses_true_for_a_number_in_one_line(cli, shared_data, tmp_path):
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--k", "1", "--rerank", "aqe",
                         "--rerank-option", "n=true", "--data-dir", shared_data, "--cache-dir", tmp_path / "cache")
    assert code != 0 and err.strip() == "error: Stage 'aqe' option n: takes a number, not true."


@pytest.mark.parametrize("option", ["max_features", "max_iterations"])
def test_a_count_opencv_cannot_take_is_refused_in_one_line(cli, shared_data, tmp_path, option):
    """Was: a traceback from inside OpenCV (its counts are C ints), after retrieval had run."""
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--k", "1", "--rerank", "sift-ransac",
                         "--rerank-k", "3", "--rerank-option", f"{option}=99999999999", "--data-dir", shared_data,
                         "--cache-dir", tmp_path / "cache")
    assert code != 0 and err.strip() == (f"error: Stage 'sift-ransac' option {option}: Input should be less than or "
                                         "equal to 2147483647 (got 99999999999).")


def searcher():
    """A plugin 're-ranker' that puts first a database image it was not given (as a search of its own would)."""
    from vprbench.stages import RerankOptions, Stage

    class Search(Stage):
        Options = RerankOptions

        def apply(self, candidates, context):
            indices = candidates.indices.copy()
            for q, row in enumerate(candidates.indices):
                indices[q] = [np.setdiff1d(np.arange(context.database.row_count), row)[0], *row[:-1]]
            return Candidates(indices, candidates.scores)

    return Search


def test_a_re_ranker_naming_an_image_it_was_not_given_is_refused(shared_data, stage_cache, scratch_stages):
    """Was taken: recall after it could pass the ceiling recorded for its candidates."""
    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings, resolve_spec
    from vprbench.stages import registry

    registry.register_stage("searcher", searcher())
    spec = resolve_spec("hog", "corridor", stages=[{"name": "searcher", "k": 2}], ks=(1, 2), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match=r"^Stage 'searcher' returned database image \d+ for query \d+, which is not "
                                            r"among the 2 candidates it was given: a re-ranker re-orders its "
                                            r"candidates; fix the stage\.$"):
        evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=stage_cache))


@pytest.mark.parametrize("stage", ["aqe", "dba"])
def test_expansion_with_a_huge_alpha_stays_finite(stage):
    """Was: alpha=1e300 turned a similarity a rounding above 1 (a row with itself) into inf: an overflow
    warning and NaN descriptors. Weights now stay in [0, 1]; the true one is still first."""
    database = unit_rows(30, 64, seed=5)
    indices = np.array([[*np.setdiff1d(np.arange(30), [q])[:9], q] for q in range(10)], dtype=np.int64)
    given = Candidates(indices, np.tile(np.linspace(1, 0, 10, dtype=np.float32), (10, 1)))
    context = StageContext(dataset=None, database=ArrayRows(database), queries=ArrayRows(database[:10] * 1.0001))
    with np.errstate(over="raise", invalid="raise"):  # underflow to 0 is the weight meant
        found = create_stage(stage, {"k": 10, "n": 3, "alpha": 1e300}).apply(given, context)
    assert np.isfinite(found.scores).all()
    assert_oracle(given, found)
    assert create_stage(stage, {"k": 10}).fingerprint() == {"version": 3}  # records of other code (3: no BLAS)
