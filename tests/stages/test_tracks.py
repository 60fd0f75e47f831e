"""Tracks: a re-ranked run has a table of its own and never appears in the single-image tables."""
import pytest

from vprbench.evaluation import evaluate, read_results, save_result
from vprbench.leaderboard import build_board, publish
from vprbench.spec import RunSettings, resolve_spec


@pytest.fixture(scope="module")
def results(shared_data, stage_cache, tmp_path_factory):
    cache = tmp_path_factory.mktemp("track-results")
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    for stages in ([], [{"name": "aqe", "k": 20, "n": 1}]):
        save_result(evaluate(resolve_spec("hog", "corridor", stages=stages, ks=(1, 5, 20), data_dir=shared_data),
                             settings), cache)
    return cache


def test_each_track_is_a_board_of_its_own(results):
    board = build_board(read_results(results))
    assert board.tracks == ["single-image", "re-ranked"]
    single, ranked = board.of_track("single-image"), board.of_track("re-ranked")
    assert [r.label for r in single.rows] == ["hog"] and [r.label for r in ranked.rows] == ["hog + aqe@20 [n=1]"]
    assert {c.row.track for c in single.cells.values()} == {"single-image"}
    assert board.of_track("sequence").cells == {}


def test_the_site_shows_a_re_ranked_run_only_on_its_track_page(results, tmp_path):
    section = publish(tmp_path / "docs", results)
    pages = {p.name: p.read_text() for p in section.glob("*.md")}
    assert "track-re-ranked.md" in pages and "track-sequence.md" not in pages
    ranked = pages["track-re-ranked.md"]
    assert "hog + aqe@20 [n=1]" in ranked and "| hog |" not in ranked
    row = next(line for line in ranked.splitlines() if line.startswith("| hog + aqe@20"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    board = build_board(read_results(results))
    alone = board.of_track("single-image").cells
    assert cells[6] == f"{next(iter(alone.values())).recall(1):.1f}"  # beside its retriever alone
    assert float(cells[5]) == pytest.approx(next(iter(alone.values())).recall(20), abs=0.05)  # ceiling: its R@20
    for name, page in pages.items():
        if name != "track-re-ranked.md":
            assert "aqe" not in page.replace("track-re-ranked.md", ""), name
    assert "[Re-ranked](track-re-ranked.md)" in pages["index.md"]
