"""Sweeps: resume, failures, bad plans, two processes sharing one plan and cache, a killed runner."""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results

PLAN = """name = "two-by-two"
k = [1, 5]

[[methods]]
name = "hog"
options = {{ resize = [64, 64] }}

[[methods]]
name = "hog"
options = {{ resize = [32, 32] }}

[[datasets]]
name = "corridor"

[[datasets]]
name = "{own}"
"""


@pytest.fixture
def own(shared_data, tmp_path):
    """A folder of one's own from 40 Corridor frames: positions are frame numbers, radius 2."""
    root = tmp_path / "corridor-own"
    rows = ["image,frame"]
    for split, folder in (("database", "ref"), ("queries", "query")):
        (root / split).mkdir(parents=True)
        for i in range(40):
            shutil.copyfile(shared_data / "corridor" / folder / f"{i:07d}.jpg", root / split / f"{i:07d}.jpg")
            rows.append(f"{split}/{i:07d}.jpg,{i}")
    (root / "positions.csv").write_text("\n".join(rows) + "\n")
    (root / "dataset.toml").write_text('radius = 2\nname = "corridor-own"\n')
    return root


@pytest.fixture
def plan(tmp_path, own):
    path = tmp_path / "plan.toml"
    path.write_text(PLAN.format(own=own))
    return path


def records(cache: Path) -> list[dict]:
    return read_results(cache)


def vprbench(*args, cache: Path, data: Path):
    env = {**os.environ, "VPRBENCH_CACHE": str(cache), "VPRBENCH_DATA": str(data), "COLUMNS": "200"}
    return subprocess.Popen([sys.executable, "-m", "vprbench.cli.main", *args], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def comparable(record: dict) -> tuple:
    return (record["method_options"]["resize"], record["protocol"]["id"], record["recall"], record["top_predictions"])


def test_two_processes_share_the_cells_each_once_and_match_a_sequential_run(plan, shared_data, tmp_path, capsys):
    sequential = tmp_path / "sequential"
    assert main(["run", str(plan), "--cache-dir", str(sequential), "--data-dir", str(shared_data)]) == 0
    alone = sorted(comparable(r) for r in records(sequential))
    assert len(alone) == 4 and len({r[1] for r in alone}) == 2 and "two-by-two: 4 ran" in capsys.readouterr().out
    # again: every cell complete, nothing recomputed
    assert main(["run", str(plan), "--cache-dir", str(sequential), "--data-dir", str(shared_data)]) == 0
    assert "two-by-two: 4 skipped" in capsys.readouterr().out and len(records(sequential)) == 4

    shared = tmp_path / "shared-cache"
    runs = [vprbench("run", str(plan), cache=shared, data=shared_data) for _ in range(2)]
    outputs = [r.communicate(timeout=240) for r in runs]
    assert [r.returncode for r in runs] == [0, 0], outputs
    together = records(shared)
    assert len(together) == 4 and len({r["context"]["sweep"]["cell"] for r in together}) == 4  # each cell once
    assert sorted(comparable(r) for r in together) == alone  # identical to the sequential run
    def counted(status):  # from each process's table title, e.g. "two-by-two: 2 ran, 2 done elsewhere"
        return sum(int(n) for out, _ in outputs for n in re.findall(rf"(\d+) {status}\b", out.splitlines()[0]))

    assert counted("ran") == 4 and counted("done elsewhere") + counted("skipped") == 4, outputs


def test_a_killed_runner_s_cell_is_resumed_by_another(shared_data, tmp_path):
    plan = tmp_path / "one.toml"
    plan.write_text('[[methods]]\nname = "hog"\n\n[[datasets]]\nname = "corridor"\n')
    cache = tmp_path / "cache"
    first = vprbench("run", str(plan), "--lease", "1", cache=cache, data=shared_data)
    deadline = time.time() + 120
    while not list(cache.glob("stores/*/*/*.partial.h5")) and time.time() < deadline and first.poll() is None:
        time.sleep(0.05)
    assert first.poll() is None, first.communicate()
    os.kill(first.pid, signal.SIGKILL)
    first.wait()
    assert list(cache.glob("sweeps/claims/*.lease")), "the dead runner's claim is left behind"
    second = vprbench("run", str(plan), "--lease", "1", cache=cache, data=shared_data)
    out, err = second.communicate(timeout=240)
    assert second.returncode == 0, err
    (record,) = records(cache)
    assert "taken over from" in record["context"]["sweep"]["resumed"]
    assert "resumed" in out and not list(cache.glob("sweeps/claims/*.lease"))
    assert record["counts"]["queries"] == 111 and record["descriptors_computed"]["queries"] <= 111


def refused_plan(tmp_path, capsys, monkeypatch, text: str) -> str:
    """The one-line-per-problem refusal of the plan `text` (bad.toml), unwrapped, whitespace folded."""
    monkeypatch.setenv("COLUMNS", "1000")
    plan = tmp_path / "bad.toml"
    plan.write_text(text)
    assert main(["run", str(plan)]) == 1
    return " ".join(capsys.readouterr().err.split())


def test_bad_plan_lists_every_problem_with_lines_and_runs_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")  # one problem per line, unwrapped
    plan = tmp_path / "bad.toml"
    plan.write_text('name = "bad"\nkk = [1]\n\n[[methods]]\nname = "hogg"\n\n[[methods]]\nname = "hog"\n'
                    'options = { layer = 3 }\ncolour = "red"\n\n[[datasets]]\nname = "coridor"\n\n'
                    '[[datasets]]\nname = "nordland"\nprotocols = ["tolerance-5"]\n')
    assert main(["run", str(plan)]) == 1
    err = capsys.readouterr().err
    for expected in ("6 problem(s)", "bad.toml:2: unknown key 'kk'", "bad.toml:5: unknown method 'hogg'",
                     "bad.toml:9: method 'hog' does not take option 'layer'", "bad.toml:10: method entry 2 has unknown key 'colour'",
                     "bad.toml:13: unknown dataset 'coridor'", "bad.toml:17: dataset 'nordland' has no protocol 'tolerance-5'",
                     "vpr-bench, tolerance-10, swapped"):
        assert expected in " ".join(err.split()), err
    assert not read_results(tmp_path / "user-cache" / "vprbench")
    plan.write_text("[[methods]\n")
    assert main(["run", str(plan)]) == 1 and "not valid TOML" in capsys.readouterr().err


def test_bad_k_search_and_store_dtype_of_a_plan_are_listed_with_the_rest_at_their_lines(tmp_path, capsys, monkeypatch):
    err = refused_plan(tmp_path, capsys, monkeypatch,
                       'name = "bad"\nk = [1, 0]\nsearch = { index = "foo" }\nstore_dtype = "int8"\n\n'
                       '[[methods]]\nname = "hogg"\n\n[[datasets]]\nname = "corridor"\n')
    for expected in ("4 problem(s)", "bad.toml:2: --k (ks) takes whole numbers >= 1", "got 1 0",
                     "bad.toml:3: --index takes one of exact, ivf-pq, hnsw; got 'foo'",
                     "bad.toml:4: --store-dtype takes one of float32, float16; got 'int8'", "bad.toml:7: unknown method 'hogg'"):
        assert expected in err, err


def test_a_dataset_folder_at_fault_is_named_once_at_its_own_line(tmp_path, capsys, monkeypatch):
    """Was: the folder's error given once per method, at each method entry's line."""
    err = refused_plan(tmp_path, capsys, monkeypatch,
                       '[[methods]]\nname = "hog"\n\n[[methods]]\nname = "sad"\n\n'
                       f'[[datasets]]\nname = "{tmp_path / "no-such-folder"}"\n')
    assert "1 problem(s)" in err and "bad.toml:8: Dataset folder" in err and "does not exist" in err, err


def test_stages_at_fault_are_named_once_at_the_line_they_are_written_on(tmp_path, capsys, monkeypatch):
    """Was: the plan's stages' error given once per method, at each method entry's line."""
    err = refused_plan(tmp_path, capsys, monkeypatch,
                       'k = [1, 5]\nstages = [{ name = "aqe", k = 10 }, { name = "dba", k = 50 }]\n\n'
                       '[[methods]]\nname = "hog"\n\n[[methods]]\nname = "dense-vlad"\n\n'
                       '[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\nstages = [{ name = "aqe", n = "x" }]\n\n'
                       '[[datasets]]\nname = "corridor"\n')
    assert "2 problem(s)" in err, err
    assert "bad.toml:2: Stage 'dba' re-ranks the top 50, but stage 'aqe' before it hands over only its top 10" in err, err
    assert "bad.toml:13: Stage 'aqe' option n:" in err, err


def test_a_stage_that_cannot_use_a_methods_comparison_is_refused_with_the_plan(tmp_path, capsys, monkeypatch):
    """Was: 'sad + aqe' in a plan passed its check and failed when its cell ran (the single run
    refuses it before any work)."""
    err = refused_plan(tmp_path, capsys, monkeypatch,
                       'stages = [{ name = "aqe", k = 20 }]\n\n[[methods]]\nname = "hog"\n\n[[methods]]\nname = "sad"\n\n'
                       '[[datasets]]\nname = "corridor"\n')
    assert "1 problem(s)" in err and "bad.toml:7: Method 'sad': Stage 'aqe' expands descriptors compared by cosine" in err, err
    assert "'mean-absolute-difference': use a method compared by cosine" in err, err


def test_evaluate_matrix_continues_past_a_failing_cell(shared_data, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")
    code = main(["evaluate", "--method", "hog", "--dataset", "corridor", "hawkins", "--data-dir", str(shared_data),
                 "--resize", "32", "32", "--k", "1"])
    out = " ".join(capsys.readouterr().out.split())
    assert code == 1 and "1 ran" in out and "1 failed" in out and "'hawkins' is not in the data root" in out
    assert [r["dataset"] for r in records(tmp_path / "user-cache" / "vprbench")] == ["corridor"]
    code = main(["evaluate", "--method", "hog", "--dataset", "corridor", "--protocol", "swapped"])
    assert code == 1 and "has no protocol 'swapped'" in capsys.readouterr().err


def test_missing_benchmarks_of_a_sweep_are_said_once_below_the_table(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    code = main(["evaluate", "--method", "hog", "dense-vlad", "--dataset", "hawkins", "nordland", "--data-dir", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1 and "4 failed" in out
    table, notes = out[:out.index("\n[1] ")], out[out.index("\n[1] "):]
    assert table.count("[1]") == 2 and table.count("[2]") == 2 and "not in the data root" not in table
    assert "│" not in notes  # plain text, not a paragraph folded into a column
    text = " ".join(notes.split())
    assert text.startswith("[1] Dataset 'hawkins' is not in the data root") and "[2] Dataset 'nordland' is not" in text
    assert "[3]" not in text and text.lower().count("place it") == 2  # once per dataset
    # a path longer than the line is folded inside it (a long temporary folder, as under pytest-xdist)
    unwrapped = "".join(notes.split())
    assert f"Placeitat{tmp_path / 'Nordland'},orrun'vprbenchdatasetsimportnordlandPATH--data-dir{tmp_path}'" in unwrapped


def test_reproduce_dry_run_and_bad_table(shared_data, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["reproduce", "anyloc", "--table", "2", "--dry-run", "--data-dir", str(shared_data)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    # one line per cell (66) and each need said once below the table (about 130 lines of needs, the
    # authors' vocabularies among them): it printed 2,707 lines when every cell repeated its needs' instructions
    assert len(lines) < 250 and sum("│ CosPlace " in line for line in lines) == 6, out
    text = " ".join(out.split())
    assert "60 cells to evaluate, 6 not runnable as the paper ran them (NetVLAD)" in text
    # the -PCA cells fit on their domain's databases stacked (pca_on = "domain"), 1,295 or 11,762 images
    assert "PCA to 512" not in text and text.count("not runnable [") == 6
    assert text.count("not runnable [1]") == 6 and text.count("[1] the authors ran a NetVLAD checkpoint of their own") == 1
    for need in ("dataset baidu-mall: Download baidu_datasets.tar.gz",
                 "weights dinov2_vitg14_pretrain.pth: let vprbench download https://dl.fbaipublicfiles.com/dinov2/dinov2_vitg14/",
                 "weights ResNet101_2048_cosplace.pth: let vprbench download https://github.com/gmberton/CosPlace/"):
        assert text.count(need) == 1, need
    number = re.search(r"\[(\d+)\] dataset baidu-mall:", text).group(1)
    # the ten runnable rows on baidu-mall refer to it, and the two -PCA rows on the other indoor datasets
    assert sum(f"[{number}] " in line for line in lines if "│" in line) == 14
    assert not (shared_data.parent / "cache").exists()
    assert main(["reproduce", "anyloc", "--table", "9"]) == 1
    assert "no table '9' here; tables: 2, 3, 4, 5, 6, 7, layer, facet" in capsys.readouterr().err
    from vprbench.sweep.reproduce import table_cells

    spec, cells = table_cells("anyloc", "layer")  # one row per released run, options from its setting
    assert len(cells) == 165 and cells[0].cells[0].spec.options["facet"] == "key"


NAMED_VOCABULARY_PLAN = """name = "named-vocabulary"
k = [1]

[[methods]]
name = "anyloc"
options = {{ backbone = "dinov2_vits14", weights = "random", layer = 1, clusters = 4, vocabulary = "indoor", resize = [56, 56] }}

[[datasets]]
name = "{own}"
"""


def test_a_refitted_named_vocabulary_is_another_run_of_the_same_row(tmp_path, own, capsys):
    """AnyLoc's `vocabulary = "indoor"` names centres in the cache: a sweep never serves the record made
    with the centres before they were fitted again, and both runs stay one leaderboard row."""
    import torch

    from vprbench.aggregation.vocabulary import Vocabulary
    from vprbench.methods.anyloc_vocabulary import save_to_cache
    from vprbench.spec import resolve_spec

    plan, cache = tmp_path / "named.toml", tmp_path / "cache"
    plan.write_text(NAMED_VOCABULARY_PLAN.format(own=own))
    options = {"backbone": "dinov2_vits14", "weights": "random", "layer": 1, "clusters": 4, "vocabulary": "indoor",
               "resize": [56, 56]}

    def fit(seed):  # as `vocabulary fit --domain indoor` leaves it, for these random-weight features
        centres = torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(seed)), dim=1)
        save_to_cache(Vocabulary(centres, {}), "dinov2_vits14@random", 1, "value", "indoor", cache)

    def sweep() -> str:
        assert main(["run", str(plan), "--cache-dir", str(cache)]) == 0
        return capsys.readouterr().out

    before = resolve_spec("anyloc", own, options=options, cache_dir=cache)
    assert before.found == {} and "found" not in before.to_json()  # nothing yet; written as before `found` existed
    fit(0)
    first = resolve_spec("anyloc", own, options=options, cache_dir=cache)
    assert first.found["vocabulary"].startswith("sha256:") and first.key != before.key
    assert first.to_json()["found"] == first.found
    assert "1 ran" in sweep() and "1 skipped" in sweep()
    fit(1)
    second = resolve_spec("anyloc", own, options=options, cache_dir=cache)
    assert second.found != first.found and second.key != first.key and second.row_key == first.row_key
    assert "1 ran" in sweep()
    runs = records(cache)
    assert len(runs) == 2 and len({r["row_key"] for r in runs}) == 1
    assert runs[0]["method_fingerprint"]["vocabulary"] != runs[1]["method_fingerprint"]["vocabulary"]
    assert [r["spec"]["found"] for r in runs] == [first.found, second.found]


def test_a_vocabulary_refitted_after_the_run_was_planned_is_refused(tmp_path, own):
    """A sweep makes its specs first: a vocabulary fitted again before a cell runs would give a record
    naming the earlier centres (its key) while holding results of the new ones. Refused, one line."""
    import torch

    from vprbench import VPRBenchError
    from vprbench.aggregation.vocabulary import Vocabulary
    from vprbench.evaluation import evaluate
    from vprbench.methods.anyloc_vocabulary import save_to_cache
    from vprbench.spec import RunSettings, resolve_spec

    cache = tmp_path / "cache"
    options = {"backbone": "dinov2_vits14", "weights": "random", "layer": 1, "clusters": 4, "vocabulary": "indoor",
               "resize": [56, 56]}
    def fit(seed):
        centres = torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(seed)), dim=1)
        save_to_cache(Vocabulary(centres, {}), "dinov2_vits14@random", 1, "value", "indoor", cache)

    fit(0)
    planned = resolve_spec("anyloc", own, options=options, cache_dir=cache)
    fit(1)
    with pytest.raises(VPRBenchError, match=r"anyloc: the vocabulary it names changed in the cache after this "
                                            r"run was planned \(sha256:\w+ then, sha256:\w+ now"):
        evaluate(planned, RunSettings(cache_dir=cache))
    assert evaluate(resolve_spec("anyloc", own, options=options, cache_dir=cache), RunSettings(cache_dir=cache))


@pytest.mark.parametrize("flags, expected", [
    # was: refused as "Exact search takes no index options", the plan's own index being hnsw
    (["--index-option", "ef_search=128"], {"index": "hnsw", "options": {"hnsw_m": 8, "ef_search": 128}}),
    # was: the plan's hnsw_m = 8 dropped, silently (the run used the default 32)
    (["--index", "hnsw", "--index-option", "ef_search=128"], {"index": "hnsw", "options": {"hnsw_m": 8, "ef_search": 128}}),
    (["--index", "hnsw"], {"index": "hnsw", "options": {"hnsw_m": 8}}),
    (["--index-option", "hnsw_m=16"], {"index": "hnsw", "options": {"hnsw_m": 16}}),  # the command line wins
    (["--index", "exact"], {"index": "exact", "options": {}}),  # another index: the plan's options are not its own
])
def test_the_command_lines_index_options_go_over_the_plans_as_its_method_options_do(tmp_path, flags, expected):
    from vprbench.cli.main import build_parser
    from vprbench.cli.options import spec_overrides
    from vprbench.sweep.plan import read_entries

    plan = tmp_path / "plan.toml"
    plan.write_text('search = { index = "hnsw", options = { hnsw_m = 8 } }\nmethods = ["hog"]\ndatasets = ["corridor"]\n')
    args = build_parser().parse_args(["run", str(plan), *flags])
    [cell] = read_entries(plan, overrides=spec_overrides(args)).plan().cells
    assert cell.spec.search.model_dump() == expected
