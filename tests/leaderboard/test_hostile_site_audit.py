"""Hostile text from records and manifests that the first hostile tests (test_hostile_site.py) do
not reach: characters that end a Markdown line or a table cell,
a dataset named by a path, benchmark names that become link targets and file names, and the
labels of the figures. Each reaches the published pages as text, in its own cell."""
from html.parser import HTMLParser
from pathlib import Path
from xml.etree import ElementTree

import markdown
import pytest
from test_hostile_site import HOSTILE, elements, hostile

from vprbench.cli.main import main
from vprbench.evaluation import save_result


class Tables(HTMLParser):
    """Every table of an HTML page: its rows, each a list of its cells' text."""

    def __init__(self):
        super().__init__()
        self.tables, self.cell = [], None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self.cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.tables[-1][-1].append("".join(self.cell))
            self.cell = None

    def handle_data(self, data):
        if self.cell is not None:
            self.cell.append(data)


def column(page: str, heading: str) -> list[str]:
    """The cells under `heading` in every table of the rendered page that has that column."""
    parser = Tables()
    parser.feed(markdown.markdown(page, extensions=["tables"]))
    return [row[table[0].index(heading)] for table in parser.tables if heading in table[0] for row in table[1:]]


def publish(tmp_path, capsys) -> list[Path]:
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    return sorted((docs / "leaderboard").rglob("*.md"))


@pytest.mark.parametrize("value", ["see [a][r]\r\r[r]: javascript:alert(1)",  # a line of its own: a reference
                                   "MIT \\| GPL",  # a backslash that would cancel the pipe's escape
                                   "MIT `x"],  # a backtick that pairs with the run's code span
                         ids=["carriage-return", "backslash-pipe", "backtick"])
def test_a_value_stays_whole_in_its_cell_and_starts_no_line(make_record, tmp_path, capsys, value):
    """A licence (in the tables) and a protocol description (in a paragraph) that would start a new
    Markdown line or end their table cell early: one cell each, no link."""
    record = make_record("hog", "my-traverse", kind="own", n_database=40, n_queries=30, seed=1, fingerprint="fp-x")
    record["provenance"]["backbone"] = {"name": "x", "licence": value}
    record["protocol"]["description"] = value
    save_result(record)
    pages = publish(tmp_path, capsys)
    shown = [cell for page in pages for cell in column(page.read_text(), "Licence")]
    assert len(shown) == 2, shown  # the dataset page's table and the overview's other runs
    assert set(shown) == {value.replace("\r", " ")}
    for page in pages:
        assert not hostile(elements(page.read_text())), page


def test_a_dataset_named_by_a_path_is_published_by_its_last_name(make_record, tmp_path, capsys):
    """An own dataset whose name is a folder of this machine: its page's title and file name, its
    figures and downloads name the last folder only."""
    name = tmp_path / "home" / "me" / "secret-project" / "tokyo"
    save_result(make_record("hog", str(name), kind="own", n_database=40, n_queries=30, seed=1, fingerprint="fp-x"))
    publish(tmp_path, capsys)
    written = [p for p in (tmp_path / "docs").rglob("*") if p.is_file()]
    assert any("tokyo (own data)" in p.read_text() for p in written)
    assert {p.name.split("-")[1] for p in written if p.name.startswith("own-")} == {"tokyo"}  # page, figures, downloads
    for path in written:
        assert "secret-project" not in path.name and "secret-project" not in path.read_text(errors="replace"), path


@pytest.fixture
def hostile_benchmarks(tmp_path, monkeypatch):
    """The shipped dataset manifests and three more, copies of Corridor named by an attacker: an
    element, a javascript: URL, a path out of the published folder."""
    import shutil
    from importlib.resources import files

    from vprbench.leaderboard import domains

    folder = tmp_path / "manifests"
    shutil.copytree(str(files("vprbench.manifests") / "datasets"), folder)
    names = [HOSTILE, "javascript:alert(1)", "../../outside"]
    corridor = (folder / "corridor.toml").read_text()
    for number, name in enumerate(names):
        (folder / f"hostile-{number}.toml").write_text(corridor.replace('name = "corridor"', f"name = {name!r}", 1))
    monkeypatch.setattr("vprbench.datasets.manifest._manifest_dir", lambda: folder)
    domains._domains.cache_clear()  # each benchmark's domain, read from the manifests once per process
    yield names
    domains._domains.cache_clear()


def test_benchmark_names_from_manifests_are_text_links_and_file_names(hostile_benchmarks, make_record, tmp_path, capsys):
    """A benchmark's name heads its column in the paper-style tables, and names its page, figures and
    downloads (file names, link targets): text there, a safe name here."""
    for seed, name in enumerate(hostile_benchmarks):
        save_result(make_record("hog", name, seed=seed))
    pages = publish(tmp_path, capsys)
    for page in pages:
        assert not hostile(elements(page.read_text())), page
    overview = (tmp_path / "docs" / "leaderboard" / "index.md").read_text()
    assert column(overview, HOSTILE) and "javascript:alert(1)" in overview  # the names are on the page, as text
    assert not [p for p in tmp_path.rglob("outside*")], "a page written out of the published folder"
    assert {p.name for p in pages} >= {"index.md", "SUMMARY.md"} and len(pages) == 3 + len(hostile_benchmarks)


def test_figure_labels_from_records_are_svg_text(make_record, tmp_path, capsys):
    """Method names in the figures' legends (matplotlib SVG): no element or attribute of theirs."""
    name = f"--><svg onload=alert(1)>{HOSTILE}"
    save_result(make_record("hog", options={"note": name}, seed=1))
    publish(tmp_path, capsys)
    svgs = sorted((tmp_path / "docs" / "leaderboard" / "figures").glob("*.svg"))
    assert len(svgs) >= 3 and any("onload=alert" in p.read_text() for p in svgs)  # the attack is in the files
    for path in svgs:
        for element in ElementTree.parse(path).iter():  # well-formed: nothing unescaped closed or opened a tag
            assert element.tag.rpartition("}")[2] not in ("script", "foreignObject", "a", "img"), (path, element.tag)
            assert not [a for a in element.attrib if a.lower().startswith("on")], (path, element.attrib)
            assert all(v.startswith("#") for a, v in element.attrib.items() if a.endswith("href")), (path, element.attrib)



def test_control_characters_from_a_record_are_written_out_on_pages(make_record, tmp_path, capsys):
    """An escape sequence in a licence reached the pages as it was (only line breaks were replaced)."""
    record = make_record("hog", "my-traverse", kind="own", n_database=40, n_queries=30, seed=1, fingerprint="fp-x")
    record["provenance"]["backbone"] = {"name": "x", "licence": "MIT\x1b[2J\x07"}
    save_result(record)
    pages = publish(tmp_path, capsys)
    assert {cell for page in pages for cell in column(page.read_text(), "Licence")} == {"MIT\\x1b[2J\\x07"}
    assert not any(c in page.read_text() for page in pages for c in "\x1b\x07")
