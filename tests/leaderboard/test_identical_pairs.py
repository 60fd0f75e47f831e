"""Two runs that succeed on exactly the same queries (e.g. one method with and without a float16
store) have nothing to test: the terminal and the site say "same queries right", not p = 1 (which
reads as a finding of no difference). A pair that differs still gets its p-values."""
from __future__ import annotations

from vprbench.evaluation import save_result

A, B, C = "hog [note=a]", "hog [note=b]", "hog [note=c]"


def _runs(make_record):
    save_result(make_record("hog", seed=3, options={"note": "a"}))
    save_result(make_record("hog", seed=3, options={"note": "b"}))  # the same top K for every query
    save_result(make_record("hog", seed=4, options={"note": "c"}))


def test_the_terminal_says_identical_results(make_record, cli):
    _runs(make_record)
    code, out, err = cli("leaderboard", "compare", A, B, "--dataset", "corridor")
    assert code == 0, err
    assert "same queries right: both get the same" in out and "no paired test is meaningful" in out
    assert "p = 1" not in out and "p 1" not in out and "= 1\n" not in out and "No difference at the 5 % level" not in out
    code, out, _ = cli("leaderboard", "compare", A, C, "--dataset", "corridor")
    assert code == 0 and "identical" not in out and "paired bootstrap p = " in out and "McNemar" in out


def test_the_site_says_identical_results(make_record, cli, tmp_path):
    _runs(make_record)
    docs = tmp_path / "docs"
    assert cli("leaderboard", "publish", "--to", docs)[0] == 0
    page = (docs / "leaderboard" / "corridor.md").read_text()
    rows = {line.split(" | ")[0].strip("| "): line for line in page.split("### Paired tests")[1].splitlines()
            if line.startswith("| hog")}
    identical = next(line for pair, line in rows.items() if {A, B} == set(pair.split(" − ")))
    assert identical.endswith("| +0.0 [+0.0, +0.0] | same queries right | 0 / 0 | – |"), identical
    assert any(C in pair for pair in rows)
    assert all("identical" not in line and line.split(" | ")[-1].strip("| ") != "–"
               for pair, line in rows.items() if C in pair)


def test_a_row_compared_with_itself_is_refused(make_record, cli):
    """Was: 'compare hog hog' compared the one run with itself, 'same queries right', exit 0 (a finding
    of nothing). A row named twice, by its name or by its key, is one run: refused, naming it."""
    from vprbench.evaluation import read_results
    from vprbench.leaderboard import build_board

    _runs(make_record)
    row = next(r for r in build_board(read_results()).rows if r.name == A)
    for second in (A, row.key):
        code, out, err = cli("leaderboard", "compare", A, second, "--dataset", "corridor")
        assert code == 1 and out == "" and err.count("\n") == 1, (code, out, err)
        assert f"{A!r} and {second!r} name the same run" in err and "two different rows" in err
