"""`vprbench leaderboard publish`: the pages, figures and downloads from real and synthetic runs,
and every bad input (no results, a file, read-only, full disk, a kill, images gone)."""
import json
from types import SimpleNamespace
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results, save_result
from vprbench.paths import cache_root
from vprbench.spec import canonical_hash
from vprbench.store import RowsIdentity, RowWriter, create_rows_file


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, " ".join(err.split())  # the terminal wraps long messages


def real_runs(capsys, shared_data, *resizes):
    for size in resizes:
        code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(shared_data),
                           "--resize", str(size), str(size))
        assert code == 0, err
    return read_results()


def with_gem_store(record):
    """A GeM run's database descriptors in a complete store the record names (for the PCA map)."""
    folder = f"{record['method']}-{canonical_hash(record['method_fingerprint'])}/{record['dataset']}-test"
    record.setdefault("context", {})["store"] = {"folder": folder}
    n = record["counts"]["database"]
    identity = RowsIdentity(store=f"{folder}/database", start=0, stop=n, total=n, fit_id="none", dtype="float32",
                            fingerprint="{}", names=[f"db{i}.jpg" for i in range(n)])
    path = cache_root() / "stores" / folder / "database.h5"
    create_rows_file(path, identity, 16)
    writer = RowWriter(path, identity)
    rng = np.random.default_rng(len(record["dataset"]))
    writer.write(np.arange(n), rng.normal(len(record["dataset"]) % 3, 1, (n, 16)).astype("float32"))
    writer.finish()
    return record


@pytest.fixture
def full_board(capsys, shared_data, make_record):
    """Real HOG runs on Corridor plus synthetic ones covering every kind of row and column."""
    real = real_runs(capsys, shared_data, 64, 128)
    corridor_fp = real[0]["dataset_fingerprint"]
    save_result(make_record("hog", weights={"source": "user", "sha256": "ab" * 32}, fingerprint=corridor_fp, seed=3))
    own = make_record("hog", kind="own", n_database=111, n_queries=111, fingerprint="mine0001", seed=4)
    save_result(own)
    save_result(make_record("anyloc-vlad-dinov2", "hawkins", weights={"source": "official", "url": "https://x"},
                            quality=0.65, seed=5))
    for name in ("hawkins", "laurel-caverns", "baidu-mall"):
        save_result(with_gem_store(make_record("anyloc-gem-dinov2", name, options={"aggregation": "gem"},
                                               weights={"source": "official", "url": "https://x"}, seed=6)))
    (cache_root() / "results" / "broken.json").write_text("{not json")
    return SimpleNamespace(real=real, own_page=f"own-corridor-{own['protocol']['hash'][:8]}.md")


def test_publish_writes_every_page_figure_and_download(capsys, tmp_path, shared_data, full_board):
    docs = tmp_path / "docs"
    with pytest.warns(UserWarning, match="broken.json"):
        code, out, err = run(capsys, "leaderboard", "publish", "--to", str(docs), "--data-dir", str(shared_data))
    assert code == 0, err
    section = docs / "leaderboard"
    pages = {p.name for p in section.glob("*.md")}
    assert pages == {"index.md", "reported.md", "corridor.md", "hawkins.md", "laurel-caverns.md", "baidu-mall.md",
                     full_board.own_page, "SUMMARY.md"}
    navigation = (section / "SUMMARY.md").read_text()  # every page in the site's navigation
    assert all(f"]({page})" in navigation for page in pages - {"SUMMARY.md"}), navigation
    overview = (section / "index.md").read_text()
    assert "### Table II: Structured environments" in overview and "### Table III: Unstructured environments" in overview
    assert "| hog [resize=64x64] |" in overview and "*AnyLoc-VLAD-DINOv2* (paper)" in overview
    assert "| anyloc-vlad-dinov2 | hawkins | R@1 |" in overview and "*65.2* (Table III)" in overview  # paper beside
    assert "hog † user weights sha256:abababababab" not in overview.split("## Other runs")[0], "never in a paper table"
    assert "| hog † | user weights sha256:abababababab | – | [corridor](corridor.md)" in overview
    assert f"[corridor (own data)]({full_board.own_page})" in overview
    for page in pages - {"reported.md", "SUMMARY.md"}:
        assert '!!! note "Marks"' in (section / page).read_text(), page
    assert "1 cell(s) are on rows marked †" in overview
    corridor = (section / "corridor.md").read_text()
    assert "| hog † | user weights sha256:abababababab |" in corridor
    assert "| hog [resize=64x64] | none (nothing learnt) |" in corridor  # HOG has no weights to call official
    figures = section / "figures"
    for name in ("radar.svg", "pca-gem.png", "corridor-recall.svg", "corridor-pr.svg", "corridor-efficiency.svg",
                 "corridor-mosaic-hog_resize_64x64_.png", "corridor-mosaic-hog_user_weights_sha256_abababababab.png"):
        assert (figures / name).stat().st_size > 1000, name
    assert corridor.count("queries and their top 5](figures/corridor-mosaic-") == 3
    own = (section / full_board.own_page).read_text()
    assert "*Mosaic of hog: not drawn, the images of corridor are no longer at" in own
    hawkins = (section / "hawkins.md").read_text()
    assert "*Mosaic of anyloc-vlad-dinov2: not drawn, the images of hawkins are not on disk here" in hawkins
    assert (figures / "hawkins-recall.svg").is_file(), "the rest of the page is still written"
    assert "| anyloc-vlad-dinov2 | official |" in hawkins
    table = pd.read_csv(section / "downloads" / "corridor.csv")
    assert set(table["method"]) == {"hog [resize=64x64]", "hog [resize=128x128]", "hog"}
    records = json.loads((section / "downloads" / "corridor.json").read_text())
    assert {len(r["per_query"]["first_positive_rank"]) for r in records} == {111}
    summary = json.loads((section / "downloads" / "leaderboard.json").read_text())
    assert len(summary) == 8 and all(0 <= e["r1_ci_low"] <= e["r1"] <= e["r1_ci_high"] <= 100 for e in summary)
    downloads_say_what_the_pages_say(section, summary)


def page_rows(page: str) -> dict[str, list[str]]:
    """The Results table of a dataset page: row name (without †) -> its cells."""
    text = page.split("## Results", 1)[1].split("The runs in the cells above", 1)[0]
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| ") and not line.startswith("| Method")]
    return {cells[0].removesuffix(" †"): cells for cells in rows}


def downloads_say_what_the_pages_say(section, summary):
    """Every download entry (CSV and JSON) has the weights, R@1 and interval its page shows."""
    csv = pd.read_csv(section / "downloads" / "leaderboard.csv").to_dict("records")
    assert len(csv) == len(summary)
    pages = {}
    for entry, row in zip(summary, csv):
        assert row["weights"] == entry["weights"] and row["method"] == entry["method"]
        slug = entry["page"].removesuffix(".md")
        pages.setdefault(slug, page_rows((section / entry["page"]).read_text()))
        cells = pages[slug][entry["method"]]
        assert cells[1] == entry["weights"] and cells[2] == entry["licence"] == row["licence"], (entry["method"], slug)
        assert cells[3] == f"{entry['r1']:.1f} [{entry['r1_ci_low']:.1f}, {entry['r1_ci_high']:.1f}]"
        # R@100%P in percent like the R@K beside it, not a fraction
        assert cells[8] == f"{100 * entry['recall_at_100_precision']:.1f}", (entry["method"], cells)


def test_publish_again_replaces_the_section_and_leaves_no_temporary_folder(capsys, tmp_path, shared_data):
    real_runs(capsys, shared_data, 64)
    docs = tmp_path / "docs"
    assert run(capsys, "leaderboard", "publish", "--to", str(docs))[0] == 0
    (docs / "leaderboard" / "stale-page.md").write_text("from an older publish")
    (docs / ".leaderboard-old-x1").mkdir()  # what a publish killed during its swap would leave
    assert run(capsys, "leaderboard", "publish", "--to", str(docs))[0] == 0
    assert not (docs / "leaderboard" / "stale-page.md").exists()
    assert sorted(p.name for p in docs.iterdir()) == [".leaderboard.lock", ".leaderboard.read-at", "leaderboard"]


def test_no_results_writes_nothing(capsys, tmp_path):
    code, _, err = run(capsys, "leaderboard", "publish", "--to", str(tmp_path / "docs"))
    assert code == 1 and "No results" in err and "Nothing was written" in err and "Traceback" not in err
    assert not (tmp_path / "docs").exists()
    code, _, err = run(capsys, "leaderboard", "compare", "a", "b", "--dataset", "corridor")
    assert code == 1 and "No results" in err


def test_only_old_records_say_why_nothing_is_shown(capsys):
    line = {"method": "hog", "dataset": "corridor", "recall": {"1": 48.6}, "counts": {"queries": 111}}
    cache_root().mkdir(parents=True, exist_ok=True)
    (cache_root() / "results.jsonl").write_text(json.dumps(line) + "\n")
    with pytest.warns(UserWarning, match="holds vprbench 0.1 records"):
        code, _, err = run(capsys, "leaderboard")
    assert code == 1 and "No results yet" in err


def test_compare_names_what_is_missing(capsys, make_record):
    save_result(make_record("hog", seed=1))
    save_result(make_record("dense-vlad", seed=2))
    code, _, err = run(capsys, "leaderboard", "compare", "hogg", "dense-vlad", "--dataset", "corridor")
    assert code == 1 and "No run of 'hogg' on corridor. Did you mean: hog?" in err
    code, _, err = run(capsys, "leaderboard", "compare", "hog", "dense-vlad", "--dataset", "coridor")
    assert code == 1 and "No run on dataset 'coridor' fills a cell. Did you mean: corridor?" in err
    code, _, err = run(capsys, "leaderboard", "compare", "hog", "--dataset", "corridor")
    assert code == 1 and "needs two methods and a dataset" in err
    code, _, err = run(capsys, "leaderboard", "compare", "hog", "dense-vlad", "--dataset", "corridor", "--k", "50")
    assert code == 1 and "searched only the top 20" in err
    code, out, _ = run(capsys, "leaderboard", "compare", "hog", "dense-vlad", "--dataset", "corridor")
    assert code == 0 and "difference (hog - dense-vlad)" in out and "McNemar exact test" in out


def test_to_a_file_is_refused(capsys, tmp_path, make_record):
    save_result(make_record())
    target = tmp_path / "docs.md"
    target.write_text("mine")
    code, _, err = run(capsys, "leaderboard", "publish", "--to", str(target))
    assert code == 1 and "is a file, not a folder" in err and target.read_text() == "mine"


def test_read_only_folder_is_refused_and_the_old_section_kept(capsys, tmp_path, make_record, read_only):
    save_result(make_record())
    docs = tmp_path / "docs"
    assert run(capsys, "leaderboard", "publish", "--to", str(docs))[0] == 0
    before = (docs / "leaderboard" / "index.md").read_text()
    save_result(make_record("other"))
    view = read_only(docs)
    code, _, err = run(capsys, "leaderboard", "publish", "--to", str(view))
    assert code == 1 and "Read-only file system" in err and "nothing was written" in err
    assert (view / "leaderboard" / "index.md").read_text() == before


def test_full_disk_keeps_the_old_section_whole(capsys, tmp_path, shared_data, make_record, small_disk):
    real_runs(capsys, shared_data, 64)
    first = tmp_path / "first"
    assert run(capsys, "leaderboard", "publish", "--to", str(first), "--data-dir", str(shared_data))[0] == 0
    size = sum(p.stat().st_size for p in first.rglob("*") if p.is_file())
    disk = small_disk(size // 1024 + 64)  # room for the old section, not for a second copy beside it
    shutil.copytree(first / "leaderboard", disk / "leaderboard")
    before = {p.relative_to(disk): p.read_bytes() for p in (disk / "leaderboard").rglob("*") if p.is_file()}
    code, _, err = run(capsys, "leaderboard", "publish", "--to", str(disk), "--data-dir", str(shared_data))
    assert code == 1 and "No space left on device" in err and "is unchanged" in err
    after = {p.relative_to(disk): p.read_bytes() for p in (disk / "leaderboard").rglob("*") if p.is_file()}
    assert after == before
    assert not [p for p in disk.iterdir() if p.name.startswith(".leaderboard-")]


def test_kill_9_during_publish_never_leaves_a_partial_section(capsys, tmp_path, shared_data):
    real_runs(capsys, shared_data, 64, 128)
    docs = tmp_path / "docs"
    assert run(capsys, "leaderboard", "publish", "--to", str(docs), "--data-dir", str(shared_data))[0] == 0
    whole = sorted(p.relative_to(docs / "leaderboard").as_posix() for p in (docs / "leaderboard").rglob("*"))
    command = [sys.executable, "-m", "vprbench.cli.main", "leaderboard", "publish", "--to", str(docs),
               "--data-dir", str(shared_data)]
    rng = np.random.default_rng(1)
    for _ in range(3):
        proc = subprocess.Popen(command, env=dict(os.environ), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(float(rng.uniform(1.0, 3.0)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        found = sorted(p.relative_to(docs / "leaderboard").as_posix() for p in (docs / "leaderboard").rglob("*"))
        assert found == whole, "the section is the whole old one or the whole new one"
    assert run(capsys, "leaderboard", "publish", "--to", str(docs), "--data-dir", str(shared_data))[0] == 0


def test_mosaic_refuses_a_copy_that_is_not_the_runs(shared_data, capsys):
    from vprbench.leaderboard.cells import build_board
    from vprbench.leaderboard.figures import Skipped, mosaic

    [record] = real_runs(capsys, shared_data, 64)
    record["per_query"] = {**record["per_query"]}
    [cell] = build_board([record]).cells.values()
    cell.record = {**record, "per_query": {"k": 20, **{k: v.tolist() for k, v in cell.arrays.items()}}}
    cell.record["per_query"]["positives"] = [1] * 111  # the run saw other ground truth
    with pytest.raises(Skipped, match="not the copy this run evaluated"):
        mosaic(cell, shared_data / "x.png")


def test_two_publishes_at_once_leave_one_whole_section(capsys, tmp_path, shared_data):
    real_runs(capsys, shared_data, 64)
    docs = tmp_path / "docs"
    command = [sys.executable, "-m", "vprbench.cli.main", "leaderboard", "publish", "--to", str(docs),
               "--data-dir", str(shared_data)]
    procs = [subprocess.Popen(command, env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outputs = [p.communicate(timeout=240) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    assert all("Traceback" not in err for _, err in outputs)
    section = docs / "leaderboard"
    assert (section / "index.md").is_file() and (section / "corridor.md").is_file()
    assert sorted(p.name for p in docs.iterdir() if p.name.startswith(".leaderboard-")) == []  # no staging left
    together = sorted(p.relative_to(section).as_posix() for p in section.rglob("*"))
    assert run(capsys, "leaderboard", "publish", "--to", str(docs), "--data-dir", str(shared_data))[0] == 0
    assert sorted(p.relative_to(section).as_posix() for p in section.rglob("*")) == together  # one publish's whole set
