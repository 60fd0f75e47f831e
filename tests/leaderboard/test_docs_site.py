"""The docs site: `mkdocs build --strict` of the repository's docs (README, guides, API reference,
the published leaderboard) and of a freshly published section; the built pages rendered in
headless Chromium with every figure loaded."""
import functools
import http.server
import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def mkdocs_build(config: Path, site: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
                          cwd=ROOT, capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})


@pytest.fixture(scope="module")
def built_site(tmp_path_factory) -> Path:
    site = tmp_path_factory.mktemp("site")
    done = mkdocs_build(ROOT / "mkdocs.yml", site)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "WARNING" not in done.stderr, done.stderr
    return site


def test_repository_docs_build_strict(built_site):
    assert "Set up (two commands" in (built_site / "index.html").read_text()  # the README is the home page
    assert "class=\"doc doc-heading\"" in (built_site / "api" / "index.html").read_text()  # from the docstrings
    overview = (built_site / "leaderboard" / "index.html").read_text()
    assert "Table II: Structured environments" in overview and "figures/radar.svg" in overview
    assert (built_site / "leaderboard" / "corridor" / "index.html").is_file()
    assert (built_site / "leaderboard" / "downloads" / "leaderboard.csv").is_file()


def test_a_fresh_publish_builds_strict(tmp_path, capsys, make_record, shared_data):
    from vprbench.cli.main import main
    from vprbench.evaluation import save_result

    save_result(make_record("hog", seed=1))
    save_result(make_record("hog", weights={"source": "random"}, seed=2))
    own = make_record("mine", kind="own", n_database=40, n_queries=30, dataset="garden", fingerprint="g1")
    save_result(own)
    docs = tmp_path / "docs"
    shutil.copytree(ROOT / "docs", docs, ignore=shutil.ignore_patterns("leaderboard"))
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    config["docs_dir"] = str(docs)
    config["plugins"][1]["mkdocstrings"]["handlers"]["python"]["paths"] = [str(ROOT)]
    (tmp_path / "mkdocs.yml").write_text(yaml.safe_dump(config))
    done = mkdocs_build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert done.returncode == 0, done.stdout + done.stderr
    page = (tmp_path / "site" / "leaderboard" / f"own-garden-{own['protocol']['hash'][:8]}" / "index.html").read_text()
    assert "garden (own data)" in page and "Marks" in page


HARNESS = """<!doctype html><html><body><pre id="result">pending</pre><script>
const pages = %s, found = {};
let left = pages.length;
for (const page of pages) {
  const frame = document.createElement("iframe");
  frame.style.width = "1400px"; frame.style.height = "900px";
  frame.onload = () => {
    const doc = frame.contentDocument;
    const images = [...doc.querySelectorAll("article img")];
    found[page] = {title: (doc.querySelector("article h1") || {}).textContent, tables: doc.querySelectorAll("article table").length,
                   images: images.map(i => [i.getAttribute("src"), i.complete && i.naturalWidth > 0]),
                   nav: [...doc.querySelectorAll(".md-nav--primary a.md-nav__link")].map(a => a.href)};
    if (--left === 0) document.getElementById("result").textContent = JSON.stringify(found);
  };
  frame.src = page;
  document.body.appendChild(frame);
}
</script></body></html>"""


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (Debian: apt-get install chromium)")
def test_pages_render_in_headless_chromium_with_their_figures(built_site):
    pages = ["/leaderboard/", "/leaderboard/corridor/", "/leaderboard/reported/", "/", "/record-schema/"]
    (built_site / "harness.html").write_text(HARNESS % json.dumps(pages))
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    handler = functools.partial(Quiet, directory=str(built_site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        done = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=20000",
                               "--dump-dom", f"http://127.0.0.1:{server.server_port}/harness.html"],
                              capture_output=True, text=True, timeout=90)
    finally:
        server.shutdown()
    text = done.stdout.split('<pre id="result">', 1)[1].split("</pre>", 1)[0]
    found = json.loads(text.replace("&quot;", '"').replace("&amp;", "&"))
    assert set(found) == set(pages)
    assert "Leaderboard" in found["/leaderboard/"]["title"] and found["/leaderboard/"]["tables"] >= 2
    overview = dict(found["/leaderboard/"]["images"])
    assert "figures/radar.svg" in overview
    corridor = dict(found["/leaderboard/corridor/"]["images"])
    assert any(href.endswith("/leaderboard/corridor/") for href in found["/"]["nav"])  # dataset pages in the navigation
    assert {"../figures/corridor-recall.svg", "../figures/corridor-pr.svg", "../figures/corridor-efficiency.svg"} <= set(corridor)
    assert any("mosaic" in src for src in corridor)
    for page, entry in found.items():
        assert all(loaded for _, loaded in entry["images"]), (page, entry["images"])
