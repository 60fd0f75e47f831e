"""Post-retrieval stages pinned on tiny hand-computed inputs, each test written against a code change the
other stage tests let through (a mutation audit): the changes named in each docstring alter the ranking,
hence Recall@K, and must fail here."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from vprbench.row_sources import ArrayRows
from vprbench.stages import Candidates
from vprbench.stages.base import StageContext
from vprbench.stages.registry import create_stage
from vprbench.stages.run import run_stages


def rows(*vectors, dim=2):
    found = np.zeros((len(vectors), dim), dtype=np.float32)
    found[:, :2] = vectors
    return found


def context(database, queries, **more):
    return StageContext(dataset=None, database=ArrayRows(database), queries=ArrayRows(queries), **more)


def given(indices, scores):
    return Candidates(np.array([indices], dtype=np.int64), np.array([scores], dtype=np.float32))


def test_aqe_gives_a_candidate_less_similar_than_orthogonal_no_weight():
    """q = (1, 0); candidates (0.8, 0.6), (0.6, -0.8), (-0.6, 0.8), similarities 0.8, 0.6, -0.6; n = 3, alpha = 1.
    Expanded: q + 0.8 c0 + 0.6 c1 + 0 c2 = (2, 0), so the scores stay 0.8, 0.6, -0.6 and c0 stays first. Weighting
    the negative similarity (clipping at -1, not 0) gives (2.36, -0.48), which puts c1 (1.8) above c0 (1.6)."""
    database = rows((0.8, 0.6), (0.6, -0.8), (-0.6, 0.8))
    found = create_stage("aqe", {"k": 3, "n": 3, "alpha": 1.0}).apply(
        given([0, 1, 2], [0.8, 0.6, -0.6]), context(database, rows((1, 0))))
    assert found.indices.tolist() == [[0, 1, 2]]
    np.testing.assert_allclose(found.scores[0], [0.8, 0.6, -0.6], atol=1e-4)


def test_aqe_scores_closer_than_the_grid_tie_to_the_lower_database_index():
    """Scores are ranked on the exact search's grid (2^-16), ties to the lower database index, so a last-bit
    difference between CPUs cannot swap two candidates: database 2 scores 1e-6 above database 1 and must still
    come after it. Dropping the grid (in `reordered` or in alpha-QE's call) puts database 2 first."""
    database = rows((1, 0), (0.5, 0.8660254), (0.500001, 0.8660248))
    found = create_stage("aqe", {"k": 3, "n": 1, "alpha": 1.0}).apply(
        given([0, 2, 1], [1.0, 0.500001, 0.5]), context(database, rows((1, 0))))
    assert found.indices.tolist() == [[0, 1, 2]]
    np.testing.assert_allclose(found.scores[0], [1.0, 0.5, 0.5], atol=1e-6)


@pytest.mark.parametrize("budget", [1_000_000, 5000])  # 5000 B: two blocks of two database rows
def test_dba_excludes_each_image_itself_in_every_block(budget):
    """d0..d3 = (1, 0), (0.8, 0.6), (0, 1), (-0.6, 0.8); n = 1, alpha = 1: each is augmented by its nearest other
    (d1, d0, d3, d2, similarity 0.8 each), all four to norm 1.7088. For q = (0.6, 0.8) the scores are
    1.44, 1.368, 1.024, 0.92 over 1.7088: order 1, 0, 2, 3. Excluding block row i's `needed[i]` rather than
    `needed[start + i]` leaves d2 and d3 un-augmented in the second block (0.8, 0.28): order 1, 2, 0, 3."""
    database = rows((1, 0), (0.8, 0.6), (0, 1), (-0.6, 0.8), dim=64)
    found = create_stage("dba", {"k": 4, "n": 1, "alpha": 1.0}).apply(
        given([1, 2, 0, 3], [0.96, 0.8, 0.6, 0.28]), context(database, rows((0.6, 0.8), dim=64), memory_budget=budget))
    assert found.indices.tolist() == [[1, 0, 2, 3]]
    np.testing.assert_allclose(found.scores[0], np.array([1.44, 1.368, 1.024, 0.92]) / np.sqrt(2.92), atol=1e-4)


def test_run_stages_hands_a_re_ranker_only_its_top_k():
    """aqe@2 after a stage that handed over 3: database 2 = q itself is third and must stay out. With q = (1, 0),
    n = 1, alpha = 1 the expansion is q + 0.8 d0 = (1.64, 0.48): d0 1.6, d1 0.6 (over 1.7088). Handing it all
    three re-ranks d2 (1.64) first: recall@1 past the ceiling its record states."""
    database = rows((0.8, 0.6), (0.6, -0.8), (1, 0))
    stage = create_stage("aqe", {"k": 2, "n": 1, "alpha": 1.0})
    found, costs = run_stages([stage], given([0, 1, 2], [0.9, 0.8, 0.7]), context(database, rows((1, 0))), ks=(1,))
    assert found.indices.tolist() == [[0, 1]] and costs[0]["candidates_in"] == 2
    np.testing.assert_allclose(found.scores[0], np.array([1.6, 0.6]) / np.sqrt(2.92), atol=1e-4)


def test_ratio_test_drops_a_match_whose_two_nearest_are_equally_near():
    """Lowe's test keeps a match strictly below ratio x the second distance: query row 0 has two identical
    nearest database rows (distances 0 and 0), ambiguous, so only query row 1 -> database row 2 is kept."""
    pytest.importorskip("cv2")
    from vprbench.stages.geometric import ratio_matches

    a, b = np.eye(4, dtype=np.float32)[0] * 100, np.eye(4, dtype=np.float32)[1] * 100
    found = ratio_matches(np.stack([a, b]), np.stack([a, a, b]), 0.8)
    assert found.tolist() == [[1, 2]]


# ---------------------------------------------------------------- the diagonal sequence score
#: query t's similarity to database image d (queries and database both in traverse order)
SIMILARITY = np.array([[1.0, 0.0, 0.0],
                       [0.0, 0.5, 0.6],
                       [0.0, 0.0, 0.2]], dtype=np.float32)
#: length 2. causal: the mean of S[t - 1, d - 1] and S[t, d], offline: of S[t, d] and S[t + 1, d + 1], where they exist
EXPECTED = {"causal": ([[0, 1, 2], [1, 2, 0], [2, 0, 1]], [[1, 0, 0], [0.75, 0.3, 0], [0.35, 0, 0]]),
            "offline": ([[0, 1, 2], [2, 1, 0], [2, 0, 1]], [[0.75, 0.3, 0], [0.6, 0.35, 0], [0.2, 0, 0]])}


def diagonal(mode, similarity=SIMILARITY):
    traverse = SimpleNamespace(kind="benchmark", sequence_order="listing", database=[0, 1, 2], queries=[0, 1, 2])
    stage = create_stage("diagonal", {"length": 2, "mode": mode})
    worst_first = Candidates(np.tile([2, 1, 0], (3, 1)), np.zeros((3, 3), np.float32))
    return stage.apply(worst_first, StageContext(dataset=traverse, database=ArrayRows(np.eye(3, dtype=np.float32)),
                                                 queries=ArrayRows(similarity)))


@pytest.mark.parametrize("mode", ["causal", "offline"])
def test_the_diagonal_stage_scores_a_tiny_similarity_matrix_by_hand(mode):
    """The stage passes its mode on: a stage that always searched offline ranks query 1 [2, 1, 0], not [1, 2, 0]."""
    found = diagonal(mode)
    indices, scores = EXPECTED[mode]
    assert found.indices.tolist() == indices
    np.testing.assert_allclose(found.scores, scores, atol=1e-4)


def test_causal_mode_never_reads_a_later_query():
    """Changing query 2 leaves queries 0 and 1 as they were in causal mode (offline, query 1 reads query 2)."""
    later = SIMILARITY.copy()
    later[2] = [0.0, 0.9, 0.0]
    before, after = diagonal("causal"), diagonal("causal", later)
    assert after.indices[:2].tolist() == before.indices[:2].tolist() == EXPECTED["causal"][0][:2]
    np.testing.assert_array_equal(after.scores[:2], before.scores[:2])
    assert diagonal("offline", later).indices[1].tolist() != EXPECTED["offline"][0][1]


# ---------------------------------------------------------------- sift-ransac: a score is inliers, not matches
def test_sift_ransac_scores_a_candidate_by_its_inliers_not_its_ratio_matches(monkeypatch):
    """12 keypoints moved by one translation (a homography) and 6 sent elsewhere, every descriptor distinct so
    all 18 pass the ratio test: the score is the 12 inliers (counting the matches would give 18)."""
    pytest.importorskip("cv2")
    import vprbench.stages.geometric as geometric

    rng = np.random.default_rng(0)
    source = rng.uniform(0, 400, (18, 2)).astype(np.float32)
    target = source + np.float32([7, -3])
    target[12:] = rng.uniform(0, 400, (6, 2))
    descriptors = rng.integers(0, 256, (18, 128)).astype(np.uint8)
    seen = {}
    monkeypatch.setattr(geometric, "rerank_by_counts", lambda *args, prepare, **_: seen.update(count=args[-1],
                                                                                                  prepare=prepare))
    stage = create_stage("sift-ransac", {"model": "homography"})
    monkeypatch.setattr(type(stage), "_store", lambda self, context: None)
    stage.apply(None, None)
    query = seen["prepare"]({"points": source, "descriptors": descriptors})
    assert seen["count"](query, {"points": target, "descriptors": descriptors}) == 12


@pytest.mark.parametrize("model, points", [("homography", 4), ("fundamental", 8)])
def test_the_fewest_correspondences_a_model_takes_are_enough(model, points):
    """A candidate with exactly the minimal sample (4 for a homography, 8 for a fundamental matrix) of exact
    correspondences scores them all, not 0 (`<=` for `<` against MINIMUM)."""
    pytest.importorskip("cv2")
    from vprbench.stages.geometric import SiftRansacOptions, inliers

    source = np.random.default_rng(0).uniform(0, 400, (points, 2)).astype(np.float32)
    assert inliers(source, source + np.float32([7, -3]), SiftRansacOptions(model=model)) == points


def test_the_seqslam_stage_passes_its_windows_on():
    """The stage's enhance_window and uniqueness_window reach the search (the top-1 score is minus OpenSeqSLAM's
    quality ratio, so a dropped uniqueness window changes every PR number while leaving recall alone)."""
    from vprbench.stages.sequence.search import sequence_search

    rng = np.random.default_rng(2)
    route = np.cumsum(rng.standard_normal((12, 8)), axis=0)
    route = (route / np.linalg.norm(route, axis=1, keepdims=True)).astype(np.float32)
    noisy = route + 0.3 * rng.standard_normal(route.shape).astype(np.float32)
    traverse = SimpleNamespace(kind="benchmark", sequence_order="listing", database=list(range(12)),
                               queries=list(range(12)))
    options = {"length": 3, "enhance_window": 4, "uniqueness_window": 2}
    first_three = Candidates(np.tile(np.arange(3), (12, 1)), np.zeros((12, 3), np.float32))
    on_route = StageContext(dataset=traverse, database=ArrayRows(route), queries=ArrayRows(noisy))
    found = create_stage("seqslam", options).apply(first_three, on_route)
    wanted = sequence_search(route, noisy, 3, score="seqslam", grid=True, **options)
    default = sequence_search(route, noisy, 3, score="seqslam", grid=True, length=3)
    assert found.indices.tolist() == wanted.indices.tolist()
    np.testing.assert_array_equal(found.scores, wanted.scores)
    assert not np.allclose(found.scores[:, 0], default.scores[:, 0])


def test_the_sequence_stage_ranks_on_the_grid_ties_to_the_lower_database_index():
    """Length 1: the diagonal score is the similarity itself. Database 1 scores 1e-6 above database 0, less than the
    grid (2^-16), so they tie and database 0 comes first, on every CPU (the stage searching off the grid: 1 first)."""
    traverse = SimpleNamespace(kind="benchmark", sequence_order="listing", database=[0, 1], queries=[0])
    found = create_stage("diagonal", {"length": 1}).apply(
        given([1, 0], [0, 0]), StageContext(dataset=traverse, database=ArrayRows(np.eye(2, dtype=np.float32)),
                                            queries=ArrayRows(np.array([[0.5, 0.500001]], np.float32))))
    assert found.indices.tolist() == [[0, 1]]
    np.testing.assert_allclose(found.scores, [[0.5, 0.5]], atol=1e-6)
