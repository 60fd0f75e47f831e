"""Which measured row is set against which reported number: the run of the paper's own setting
(the reproduction plan's method and options), never another setting of the same method."""
from pathlib import Path

from vprbench.leaderboard.cells import build_board
from vprbench.leaderboard.tables import comparisons, group_table


def _fitted_on_database(record):
    record["provenance"].update(vocabulary={"source": "fitted", "fitted_on_evaluated_database": True},
                                learnt=["vocabulary"], fitted_on_evaluated_database=True)
    return record


def test_table_2s_dino_vlad_is_compared_with_its_domain_vocabulary_run_only(make_record):
    # Tables II/III ran AnyLoc-VLAD-DINO on domain vocabularies (the reproduction plan's row); its
    # preset fits the map's (Tables VI/VII). Was: the preset's map run was set against 61.2 and
    # the plan's own run, 'anyloc-vlad-dino [vocabulary=domain]', against nothing.
    runs = [_fitted_on_database(make_record("anyloc-vlad-dino", "baidu-mall", quality=0.9, seed=0)),
            _fitted_on_database(make_record("anyloc-vlad-dino", "baidu-mall", quality=0.9, seed=1,
                                            options={"vocabulary": "domain"}))]
    board = build_board(runs)
    found = {(c["row"], c["metric"]): c["reported"] for c in comparisons(board)}
    domain = "anyloc-vlad-dino [vocabulary=domain] † fitted on the evaluated database"
    assert found == {(domain, "R@1"): 61.2, (domain, "R@5"): 78.3}
    # the paper-style table fills no map run's missing cell with the domain run's reported number
    table = group_table(board, "II")
    line = next(x for x in table.splitlines() if x.startswith("| anyloc-vlad-dino † "))
    assert "*95.0*" not in line and "*95.0*" in next(x for x in table.splitlines() if x.startswith(f"| {domain}"))
    # the presets of the paper's other rows pair as before
    board = build_board([_fitted_on_database(make_record("anyloc-vlad-dinov2", "hawkins", quality=0.9))])
    assert [(c["metric"], c["reported"], c["table"]) for c in comparisons(board)] == [("R@1", 65.2, "III"),
                                                                                      ("R@5", 94.1, "III")]


def test_the_reported_page_shows_table_6s_dimensions_as_the_paper_gives_them():
    from vprbench.leaderboard.tables import reported_page

    lines = reported_page().splitlines()
    header = lines.index("## Table VI") + 2
    assert [c.strip() for c in lines[header].strip("|").split("|")] == ["row", "baidu-mall R@1", "oxford R@1", "dim"]
    assert [c.strip() for c in lines[header + 2].strip("|").split("|")] == ["DINO GAP", "29.6", "28.8", "384"]
    assert [c.strip() for c in lines[header + 6].strip("|").split("|")] == ["DINO hard VLAD", "60.9", "64.9", "49152"]
    page = Path(__file__).resolve().parents[2] / "docs" / "leaderboard" / "reported.md"
    assert page.read_text(encoding="utf-8") == reported_page()  # the shipped page is the generated one


def test_a_domain_run_that_fitted_the_maps_vocabulary_is_not_compared(make_record):
    # no 'indoor' vocabulary fitted these features: the run fitted Baidu Mall's own (with a warning)
    record = _fitted_on_database(make_record("anyloc-vlad-dino", "baidu-mall", quality=0.9,
                                             options={"vocabulary": "domain"}))
    record["provenance"]["vocabulary"].update(option="domain", name="map-baidu-mall")
    assert comparisons(build_board([record])) == []
    record["provenance"]["vocabulary"].update(name="indoor")
    assert [c["reported"] for c in comparisons(build_board([record]))] == [61.2, 78.3]
