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
