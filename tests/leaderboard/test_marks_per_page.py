"""The "Marks" note of a dataset page counts and names only the marks that page shows."""
from vprbench.cli.main import main
from vprbench.evaluation import save_result


def _note(page: str) -> str:
    return page.split('!!! note "Marks"', 1)[1].split("\n\n", 1)[0]


def test_a_dataset_page_counts_only_its_own_marks(tmp_path, make_record):
    """Before: every page's note counted the whole site, so Corridor's page said '1 cell(s) are on the
    user's own data' and '1 cell(s) are on rows marked †' though it shows neither."""
    save_result(make_record("hog", seed=1))
    save_result(make_record("hog", "hawkins", weights={"source": "user", "sha256": "ab" * 32}, seed=2))
    save_result(make_record("hog", "hawkins", weights={"source": "random"}, seed=3))  # left out
    own = make_record("hog", kind="own", dataset="garden", n_database=40, n_queries=30, fingerprint="g1", seed=4)
    save_result(own)
    assert main(["leaderboard", "publish", "--to", str(tmp_path / "docs")]) == 0
    section = tmp_path / "docs" / "leaderboard"

    corridor = _note((section / "corridor.md").read_text())
    assert "own data" not in corridor and "†" not in corridor and "left out" not in corridor, corridor
    assert "Every cell on this page is an official run on a benchmark's protocol" in corridor, corridor
    hawkins = _note((section / "hawkins.md").read_text())
    assert "1 cell(s) on this page are on rows marked †" in hawkins and "own data" not in hawkins, hawkins
    assert "1 run(s) on hawkins are left out of every cell" in hawkins, hawkins
    garden = _note((section / f"own-garden-{own['protocol']['hash'][:8]}.md").read_text())
    assert "1 cell(s) on this page are on the user's own data" in garden and "†" not in garden, garden
    assert "left out" not in garden, garden
    overview = _note((section / "index.md").read_text())  # the overview shows every table: it counts the site
    assert "Across the leaderboard, 1 cell(s) are on rows marked †" in overview, overview
    assert "1 cell(s) are on the user's own data" in overview and "1 run(s) are left out" in overview, overview
