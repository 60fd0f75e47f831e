"""Names from data show on the site exactly as written, in each place a page puts one (a table
cell, a heading, a link's text, a caption in emphasis, an image's text, a code element): no
emphasis from '_x_', no heading's closing '#' dropped, no '&lt;' shown for '<' inside code. Rendered
with the Markdown extensions of the project's mkdocs.yml, and by mkdocs itself."""
import importlib.util
from html.parser import HTMLParser
from pathlib import Path

import markdown
import pytest
import yaml
from test_hostile_site import mkdocs_site

from vprbench.cli.main import main
from vprbench.evaluation import save_result
from vprbench.leaderboard.escape import code, text

ROOT = Path(__file__).resolve().parents[2]
#: Markdown-active characters of plain Markdown and of extensions a site could enable (strikethrough,
#: mark, caret, emoji, arithmatex): each must read as written with the extensions this site has
NAMES = ["my_x_net", "_x_", "__dunder__", "a_b_c d_e_", "a__b", "x_ y", "_a_b", "c#", "#hash", "a<b&c", "p|q", "tick`s", "[br", "br]", "st*r*",
         "**b**", "~~del~~", "==mark==", "a^b^", ":smile:", "$x$", "> quote", "1. list", "- dash", "x\\", "a\\_b",
         "&amp;", "&#60;", "<!-- c -->", "<http://x.y/z>", "{: .cls}", "!x", "[a](b)", "L" * 300]


def site_extensions() -> tuple[list, dict]:
    """The Markdown extensions of mkdocs.yml with their settings (snippets without its paths: no
    name from data is a line of its own, the only place a snippet is read from)."""
    names, configs = [], {}
    for entry in yaml.safe_load((ROOT / "mkdocs.yml").read_text())["markdown_extensions"]:
        name, config = next(iter(entry.items())) if isinstance(entry, dict) else (entry, None)
        names.append(name)
        if config and name != "pymdownx.snippets":
            configs[name] = config
    return names, configs


class Shown(HTMLParser):
    """The text of each element of interest (table cells, headings, links, emphasis, code,
    paragraphs), white space trimmed and a heading's '¶' link left out, and the alt text of images."""

    KINDS = ("td", "h1", "h2", "a", "em", "code", "p")

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.open, self.found = [], []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.found.append(("img", dict(attrs).get("alt")))
        elif tag in self.KINDS and dict(attrs).get("class") != "headerlink":
            self.open.append([tag, ""])

    def handle_endtag(self, tag):
        at = next((i for i in range(len(self.open) - 1, -1, -1) if self.open[i][0] == tag), None)
        if at is not None:
            self.found.append((tag, self.open.pop(at)[1].replace("¶", "").strip()))

    def handle_data(self, data):
        for element in self.open:
            element[1] += data


def rendered(page: str) -> dict[str, str]:
    names, configs = site_extensions()
    parser = Shown()
    parser.feed(markdown.markdown(page, extensions=names, extension_configs=configs))
    return {tag: value for tag, value in reversed(parser.found)}  # the first of each kind


@pytest.mark.parametrize("name", NAMES)
def test_a_name_reads_as_written_in_every_place_of_a_page(name):
    page = "\n".join([f"# {text(name)} (own data)", "", f"## {text(name)}", "", "| Method | Run |", "|:--|:--|",
                      f"| {text(name)} | {code(name)} |", "", f"[{text(name)}](x.md)", "",
                      f"![{text(name)}](figures/x.svg)", "", f"*{text(name)}*", ""])
    shown = rendered(page)
    assert shown == {"h1": f"{name} (own data)", "h2": name, "td": name, "code": name, "a": name, "img": name,
                     "em": name, "p": shown["p"]}, page
    assert rendered(f"Protocol {code(name)}: {text(name)}.")["p"] == f"Protocol {name}: {name}."


def test_names_read_as_written_on_the_site_mkdocs_builds(make_record, tmp_path, capsys):
    """A method's option values, a dataset's name and its protocol id (a code element) from records,
    through `leaderboard publish` and mkdocs with the project's theme and extensions."""
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocs_literate_nav") is None:
        pytest.skip("mkdocs or mkdocs-literate-nav is not installed (pip install -e '.[docs]')")
    options = {"a": "_x_", "b": "__d__ c#", "c": "a<b&c `t` p|q"}
    save_result(make_record("hog", options=options, seed=1))
    own = make_record("hog", "_x_ c#", kind="own", n_database=40, n_queries=30, seed=2)
    own["protocol"].update(id="p_x_<b>&c", description="__d__ <i>")
    save_result(own)
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    done = mkdocs_site(docs, tmp_path / "site")
    assert done.returncode == 0, done.stdout + done.stderr
    site = tmp_path / "site" / "leaderboard"
    overview = Shown()
    overview.feed((site / "index.html").read_text())
    assert ("td", "hog [a=_x_ b=__d__ c# c=a<b&c `t` p|q]") in overview.found
    page = Shown()
    page.feed(next(site.glob("own-*/index.html")).read_text())
    assert ("h1", "_x_ c# (own data)") in page.found
    assert ("a", "_x_ c# (own data)") in overview.found  # the navigation's and the list's link
    assert ("code", "p_x_<b>&c") in page.found
    assert any(tag == "p" and value.startswith("Protocol p_x_<b>&c: __d__ <i>.") for tag, value in page.found)
