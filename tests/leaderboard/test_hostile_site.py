"""Names from records reach the published pages as text: no element, attribute or link of theirs
survives into the HTML (the Markdown rendered by python-markdown, and the whole site built by
mkdocs with the project's theme and navigation; the HTML is parsed, not grepped)."""
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
    record.setdefault("versions", {})["git"] = "`<b>x</b>"  # not a commit: a code span it could break out of
    save_result(record)
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    pages = list((docs / "leaderboard").rglob("*.md"))
    assert pages and any("onerror" in p.read_text() for p in pages), "the hostile label is on the pages"
    for page in pages:
        assert not hostile(elements(page.read_text())), page
    assert not any("<b>x" in page.read_text() for page in pages)
    assert "&lt;img" in text(HOSTILE) and "\\(" in text(LINK)


def test_a_records_protocol_and_ground_truth_publish_as_text(make_record, tmp_path, capsys):
    """Own data's page takes its protocol and ground-truth lines from a record (a benchmark's are what
    vprbench ships: test_page_protocol.py): its description, source, id and units can say anything."""
    record = make_record("hog", seed=1, kind="own", dataset="garden", n_database=40, n_queries=30, fingerprint="g1")
    record["protocol"].update(description=HOSTILE, source=LINK, id=f"x`{HOSTILE}")
    record["ground_truth"].update(unit=HOSTILE, radius_unit=HOSTILE)
    save_result(record)
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    pages = list((docs / "leaderboard").rglob("*.md"))
    assert any("onerror" in p.read_text() and "javascript" in p.read_text() for p in pages), "the attack is on a page"
    for page in pages:
        assert not hostile(elements(page.read_text())), page


class Parsed(HTMLParser):
    """Every element and every run of text of an HTML page."""

    def __init__(self):
        super().__init__()
        self.found, self.text, self.scripts, self.tag = [], [], [], None

    def handle_starttag(self, tag, attrs):
        self.found.append((tag, dict(attrs)))
        self.tag = tag

    def handle_data(self, data):
        (self.scripts if self.tag == "script" else self.text).append(data)


def live(parsed: Parsed) -> list:
    """What came alive from the hostile names: their image, an event handler, a javascript: link,
    a script that calls alert."""
    found = [(tag, attrs) for tag, attrs in parsed.found if hostile([(tag, attrs)])
             or any(name.startswith("on") for name in attrs)
             or any(str(attrs.get(a) or "").strip().lower().startswith("javascript:") for a in ("href", "src"))]
    return found + [("script", s) for s in parsed.scripts if "alert(" in s]


def mkdocs_site(docs, site):
    """The project's mkdocs.yml (theme, Markdown extensions, navigation plugin) over `docs`, which
    holds only the published section: the API reference (mkdocstrings) is left out, for speed."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[2]
    config = yaml.safe_load((root / "mkdocs.yml").read_text())
    config.update(docs_dir=str(docs), strict=False,
                  nav=[{"Home": "index.md"}, {"Leaderboard": [{"Results": "leaderboard/"}]}],
                  plugins=[p for p in config["plugins"] if not isinstance(p, dict) or "mkdocstrings" not in p])
    config["markdown_extensions"] = [e for e in config["markdown_extensions"]
                                     if not (isinstance(e, dict) and "pymdownx.snippets" in e)]
    (docs / "index.md").write_text("# Home\n")
    (docs.parent / "mkdocs.yml").write_text(yaml.safe_dump(config))
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "-f", str(docs.parent / "mkdocs.yml"), "-d", str(site)],
                          capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"}, timeout=300)


def test_hostile_names_build_with_mkdocs_into_no_live_element(make_record, tmp_path, capsys):
    import importlib.util

    import pytest

    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocs_literate_nav") is None:
        pytest.skip("mkdocs or mkdocs-literate-nav is not installed (pip install -e '.[docs]')")
    save_result(make_record("hog", options={"note": HOSTILE, "other": LINK}, seed=1))
    save_result(make_record(HOSTILE, seed=2))  # a method name from a record
    for seed, name in enumerate((HOSTILE, f"</title>{HOSTILE}"), 3):  # dataset names (the second one once went live)
        save_result(make_record("hog", name, kind="own", n_database=40, n_queries=30, seed=seed))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    assert HOSTILE in (docs / "leaderboard" / "downloads" / "leaderboard.csv").read_text()  # the attack is in the input
    done = mkdocs_site(docs, tmp_path / "site")
    assert done.returncode == 0, done.stdout + done.stderr
    pages = sorted((tmp_path / "site").rglob("*.html"))
    assert len([p for p in pages if "leaderboard" in p.parts]) >= 3  # overview, the own page, the paper's
    shown = 0
    for page in pages:
        parsed = Parsed()
        parsed.feed(page.read_text())
        assert not live(parsed), (page, live(parsed))
        shown += sum(HOSTILE in text for text in parsed.text)
    assert shown >= 3, "the hostile names are on the built pages, as text"


def test_pages_name_files_never_the_publishers_paths(make_record, tmp_path, capsys):
    """A row's vocabulary folder, a run's dataset folder and the cache file of a run left out are
    absolute paths of this machine: the pages, figures and downloads name them by their last name."""
    import json

    import pytest

    from vprbench.leaderboard.escape import public

    private = tmp_path / "home" / "me" / "images" / "tokyo247-pair"
    save_result(make_record("hog", options={"vocabulary": str(private)}, seed=1))
    damaged = save_result(make_record("hog", options={"resize": [64, 64]}, seed=2)).with_suffix(".npz")
    damaged.write_bytes(b"not an npz")
    docs = tmp_path / "docs"
    with pytest.warns(UserWarning) as caught:
        assert main(["leaderboard", "publish", "--to", str(docs)]) == 0
    # the attack is real: the records and the warning (for the person publishing) hold this machine's paths
    stored = "".join(p.read_text() for p in (tmp_path / "user-cache").rglob("*.json"))
    assert str(private) in stored and str(tmp_path / "no-images" / "corridor") in stored
    assert any(str(damaged) in str(w.message) for w in caught)

    written = [p for p in (docs / "leaderboard").rglob("*") if p.is_file()]
    assert len(written) > 10
    for path in written:
        assert str(tmp_path) not in path.name and str(tmp_path) not in path.read_text(errors="replace"), path
        assert "/home/me/" not in path.read_text(errors="replace"), path
    overview = (docs / "leaderboard" / "index.md").read_text()
    assert "| hog [vocabulary=tokyo247-pair] |" in overview  # the folder by its name
    assert f"Per-query data {damaged.name} of run" in overview  # the run left out, its file by its name
    assert "| hog [vocabulary=tokyo247-pair] |" in (docs / "leaderboard" / "corridor.md").read_text()
    download = json.loads((docs / "leaderboard" / "downloads" / "corridor.json").read_text())[0]
    assert download["dataset_root"] == "corridor" and download["spec"]["given"]["vocabulary"] == "tokyo247-pair"
    assert public("see https://example.org/a/b, 48.6 / 75.7, [bold]x[/bold]") == \
        "see https://example.org/a/b, 48.6 / 75.7, [bold]x[/bold]"  # no URL, number or markup is cut
    # A path after a label's colon is cut to its name; a URL's path after its scheme is not.
    assert public("weights:/home/me/w.pth, path:/root/a/b") == "weights:w.pth, path:b"
    assert public("hf:org/x and https://host/a/b") == "hf:org/x and https://host/a/b"
