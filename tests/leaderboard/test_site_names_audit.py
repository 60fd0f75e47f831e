"""Names from records that the hostile-site tests did not reach: a lone square bracket or a
backslash inside a link's text (the overview's and the navigation's links to a dataset page), and
row names that share one file name once made safe (each row's mosaic its own file), bidi and
zero-width characters, and a name too long for a figure's legend."""
import re

import markdown
from test_hostile_site import mkdocs_site

from vprbench.cli.main import main
from vprbench.evaluation import save_result
from vprbench.leaderboard import figures
from vprbench.leaderboard.escape import text


def links(page: str) -> list[tuple[str, str]]:
    """(text, target) of every link of the rendered Markdown, the text with its references decoded."""
    import html

    rendered = markdown.markdown(page, extensions=["tables"])
    return [(html.unescape(re.sub("<[^>]+>", "", t)), href) for href, t in re.findall(r'<a href="([^"]*)">(.*?)</a>', rendered)]


def test_a_lone_bracket_or_backslash_in_a_name_keeps_its_link_whole(make_record, tmp_path, capsys):
    names = ["br[acket", "br]acket", "ends\\", "*em*"]
    for seed, name in enumerate(names, 1):
        save_result(make_record("hog", name, kind="own", n_database=40, n_queries=30, seed=seed, fingerprint=f"fp-{seed}"))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    section = docs / "leaderboard"
    for page in ("SUMMARY.md", "index.md"):  # the navigation and the overview's list of datasets
        found = {t: href for t, href in links((section / page).read_text()) if href.startswith("own-")}
        assert {f"{name} (own data)" for name in names} <= set(found), (page, found)
        assert all((section / href).is_file() for href in found.values())
    assert links("[" + text("a\\") + "](x.md) [" + text("b[") + "](y.md)") == [("a\\", "x.md"), ("b[", "y.md")]
    assert text("hog [note=x]") == "hog [note=x]" and text("[x](javascript:y)") == "[x]\\(javascript:y)"  # pairs read as written
    import importlib.util

    if importlib.util.find_spec("mkdocs_literate_nav") is not None:  # a lone bracket once stopped the whole build
        done = mkdocs_site(docs, tmp_path / "site")
        assert done.returncode == 0, done.stdout + done.stderr


def test_rows_whose_names_share_a_file_name_get_a_mosaic_each(make_record, tmp_path, capsys, monkeypatch):
    def mosaic(cell, path, **options):  # the figure holds whose it is
        path.write_text(cell.row.name)
        return path

    monkeypatch.setattr(figures, "mosaic", mosaic)
    for seed, note in enumerate(["a/b", "a:b", "A:B"], 1):
        save_result(make_record("hog", options={"note": note}, seed=seed))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    page = (docs / "leaderboard" / "corridor.md").read_text()
    shown = re.findall(r"!\[(.*?): queries and their top \d+\]\((figures/[^)]+)\)", page)
    assert len(shown) == 3 and len({target.lower() for _, target in shown}) == 3, shown
    for caption, target in shown:  # each caption's figure is that row's, not the last one written by its name
        assert (docs / "leaderboard" / target).read_text() == caption


def test_bidi_and_zero_width_characters_are_written_out_on_pages_figures_and_terminal(make_record, tmp_path, capsys):
    """A right-to-left override reverses what follows it (a name's cell, a terminal line of numbers);
    a zero-width space makes two names read alike: both are shown as their escapes."""
    save_result(make_record("hog", options={"note": "a\u202e1.23\u200b"}, seed=1))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    shown = [p for p in (docs / "leaderboard").rglob("*") if p.suffix in (".md", ".svg")]
    assert len(shown) > 5
    for path in shown:
        assert not {"\u202e", "\u200b"} & set(path.read_text()), path
    assert "hog [note=a\\u202e1.23\\u200b]" in (docs / "leaderboard" / "corridor.md").read_text()
    capsys.readouterr()
    assert main(["leaderboard"]) == 0
    terminal = capsys.readouterr().out
    assert "a\\u202e1.23\\u200b" in terminal and "\u202e" not in terminal


def test_a_very_long_name_is_shortened_in_the_figures_not_on_the_page(make_record, tmp_path, capsys):
    """A 300-character name made the recall figure's legend wider than its plot, which it covered."""
    from xml.etree import ElementTree

    long = "L" * 290 + "END"
    save_result(make_record("hog", options={"note": long}, seed=1))
    save_result(make_record("hog", seed=2))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    assert f"hog [note={long}]" in (docs / "leaderboard" / "corridor.md").read_text()  # whole on the page
    svg = (docs / "leaderboard" / "figures" / "corridor-recall.svg").read_text()
    assert long not in svg and "END]" in svg and "…" in svg  # its start and end in the legend
    width = float(ElementTree.fromstring(svg).get("width").removesuffix("pt"))
    assert width < 800, width  # a plot and a legend of 100 characters, not a 300-character one
