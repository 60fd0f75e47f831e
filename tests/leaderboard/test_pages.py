"""The published pages' layout: averages that never mix coverage, the cell rule below the tables,
and every dataset page in the navigation."""
from vprbench.cli.main import main
from vprbench.evaluation import save_result
from vprbench.leaderboard.cells import build_board
from vprbench.leaderboard.tables import group_table

STRUCTURED_PAPER = ("baidu-mall", "gardens-point", "17places", "pitts30k", "st-lucia", "oxford")


def table_rows(table: str) -> dict[str, list[str]]:
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    return {"header": header, **{cells[0]: cells for cells in
                                 ([c.strip() for c in line.strip("|").split("|")] for line in lines[1:])}}


def test_an_average_is_over_all_the_papers_datasets_else_measured_so_far(make_record):
    partial = table_rows(group_table(build_board([make_record("hog", "corridor", quality=0.6)]), "II"))
    assert partial["header"][-2:] == ["Average (6)", "Measured so far"]
    hog = partial["hog"]
    assert hog[-2] == "–" and hog[-1].endswith("(1 of 7)")  # corridor alone: never in the Average column
    assert hog[-1].split(" (")[0] == hog[7].replace("**", "")  # its mean is its one cell (corridor, after the six)
    netvlad = partial["*NetVLAD* (paper)"]
    assert netvlad[-2] == "*62.5* / *79.7*" and netvlad[-1] == ""  # the paper's own average of its six
    assert "(6/7)" not in group_table(build_board([make_record("hog", "corridor")]), "II")

    runs = [make_record("hog", name, seed=i) for i, name in enumerate(("corridor", *STRUCTURED_PAPER))]
    board = build_board(runs)
    complete = table_rows(group_table(board, "II"))
    assert "Measured so far" not in complete["header"]
    row = board.rows[0]
    r1 = [board.cell(row, c).recall(1) for c in board.columns if c.dataset in STRUCTURED_PAPER]
    r5 = [board.cell(row, c).recall(5) for c in board.columns if c.dataset in STRUCTURED_PAPER]
    assert complete["hog"][-1] == f"{sum(r1) / 6:.1f} / {sum(r5) / 6:.1f}"  # the six, corridor left out


def test_the_cell_rule_is_below_the_tables_and_linked_from_the_top(make_record, tmp_path, capsys):
    save_result(make_record("hog", "corridor"))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    for name in ("index.md", "corridor.md"):
        page = (docs / "leaderboard" / name).read_text()
        link, rule, tables = (page.index("(#how-a-cell-is-chosen)"), page.index("## How a cell is chosen"),
                              page.rindex("\n| "))
        assert link < page.index("\n| ") and tables < rule, name
        assert page.count("Each cell is exactly one run") == 1, name
    navigation = (docs / "leaderboard" / "SUMMARY.md").read_text()
    assert "* Datasets\n    * [corridor](corridor.md)\n" in navigation


def test_a_row_fitted_on_the_evaluated_database_is_compared_with_the_paper_and_marked(make_record):
    """AnyLoc's domain vocabularies (and its PCA) are fitted on the databases the paper evaluates: such a
    run's row is marked †, and its cells are still set against the paper's numbers. Was: only unmarked
    rows were, so a run of the paper's own setting never was. A row set apart otherwise (HNSW) is not."""
    from vprbench.leaderboard.tables import comparisons

    runs = []
    for seed, search in enumerate((None, {"index": "hnsw"})):
        record = make_record("anyloc-vlad-dinov2", "baidu-mall", quality=0.9, seed=seed, search=search)
        record["provenance"].update(vocabulary={"source": "released", "fitted_on_evaluated_database": True},
                                    learnt=["vocabulary"], fitted_on_evaluated_database=True)
        runs.append(record)
    board = build_board(runs)
    name = "anyloc-vlad-dinov2 † fitted on the evaluated database"
    other = "anyloc-vlad-dinov2 † hnsw search; fitted on the evaluated database"
    assert sorted(r.name for r in board.rows) == [name, other]
    found = comparisons(board)
    assert [(c["row"], c["dataset"], c["metric"], c["reported"]) for c in found] == [
        (name, "baidu-mall", "R@1", 75.2), (name, "baidu-mall", "R@5", 87.6)]
    row = next(r for r in board.rows if r.name == name)
    cell = board.cell(row, board.columns[0])
    table = table_rows(group_table(board, "II"))
    assert table[name][1].replace("**", "") == f"{cell.recall(1):.1f} / {cell.recall(5):.1f}"  # Baidu Mall, first
    assert other not in table
