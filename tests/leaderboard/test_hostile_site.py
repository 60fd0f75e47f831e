"""Names from records reach the published pages as text: no element, attribute or link of theirs
survives into the HTML (the Markdown is rendered as mkdocs renders it, then parsed)."""
from html.parser import HTMLParser

import markdown

from vprbench.cli.main import main
from vprbench.evaluation import save_result
from vprbench.leaderboard.site import text

HOSTILE = "<img src=x onerror=alert(3)>"
LINK = "[x](javascript:alert(1))"


class Elements(HTMLParser):
    def __init__(self):
        super().__init__()
        self.found = []

    def handle_starttag(self, tag, attrs):
        self.found.append((tag, dict(attrs)))


def elements(page: str) -> list:
    parser = Elements()
    parser.feed(markdown.markdown(page, extensions=["tables"]))
    return parser.found


def hostile(found) -> list:
    return [(tag, attrs) for tag, attrs in found
            if tag == "img" and attrs.get("src") == "x" or "onerror" in attrs or "javascript:" in str(attrs.get("href"))]


def test_the_attack_is_real_unescaped():
    assert hostile(elements(f"| method |\n|--|\n| hog [note={HOSTILE}] |\n\n{LINK}\n"))


def test_hostile_option_values_publish_as_text(make_record, tmp_path, capsys):
    record = make_record("hog", options={"note": HOSTILE, "other": LINK}, seed=1)
    save_result(record)
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    pages = list((docs / "leaderboard").rglob("*.md"))
    assert pages and any("onerror" in p.read_text() for p in pages), "the hostile label is on the pages"
    for page in pages:
        assert not hostile(elements(page.read_text())), page
    assert "&lt;img" in text(HOSTILE) and "\\(" in text(LINK)
