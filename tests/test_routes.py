"""Every option means the same in every route: a single evaluation, --protocol, a matrix, a plan,
reproduce and torchrun with 2 gloo ranks each build the same run spec and the same record.

One command per route carries every option at once (the table's columns); each option is then
checked in each route's record (the table's rows). Options that change what is computed are
refused by reproduce, with the reason, and never dropped."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from runs import register_weighted_grey

METHOD = ["--method", "hog", "--resize", "32", "32"]
SPEC = ["--index", "hnsw", "--index-option", "hnsw_m=16", "--k", "1", "3", "--store-dtype", "float16"]
RUN = ["--search-memory", "200MB", "--workers", "2", "--lock-timeout", "30", "--batch-size", "7", "--device", "cpu",
       "--strict", "--download", "--quiet"]
#: option -> (where in the record, the value every route must give)
TABLE = {
    "--resize": (lambda r: r["spec"]["options"]["resize"], [32, 32]),
    "--index": (lambda r: (r["spec"]["search"]["index"], r["search"]["index"]), ("hnsw", "hnsw")),
    "--index-option": (lambda r: r["spec"]["search"]["options"], {"hnsw_m": 16}),
    "--k": (lambda r: (r["spec"]["ks"], sorted(r["recall"])), ([1, 3], ["1", "3"])),
    "--store-dtype": (lambda r: (r["spec"]["store_dtype"], r["method_fingerprint"]["store_dtype"]), ("float16", "float16")),
    "--search-memory": (lambda r: (r["run"]["memory_budget"], r["search"]["memory_budget"]), (200_000_000, 200_000_000)),
    "--workers": (lambda r: r["run"]["workers"], 2),
    "--lock-timeout": (lambda r: r["run"]["lock_timeout"], 30.0),
    "--batch-size": (lambda r: r["run"]["batch_size"], 7),
    "--device": (lambda r: r["run"]["device"], "cpu"),
    "--strict": (lambda r: r["run"]["strict"], True),
    "--download": (lambda r: r["run"]["download"], True),
}
ROUTES = ("single", "protocol", "matrix", "plan", "torchrun")


def cli(capsys, *args) -> str:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert code == 0, err
    return out


def the_record(cache, dataset="corridor") -> dict:
    [record] = [r for r in read_results(cache) if r["dataset"] == dataset]
    return record


def own_folder(shared_data, own):
    """A folder of one's own: Corridor's first 12 images of each split, 'corridor-own'."""
    rows = ["image,frame"]
    for split, folder in (("database", "ref"), ("queries", "query")):
        (own / split).mkdir(parents=True)
        for i in range(12):
            shutil.copyfile(shared_data / "corridor" / folder / f"{i:07d}.jpg", own / split / f"{i:07d}.jpg")
            rows.append(f"{split}/{i:07d}.jpg,{i}")
    (own / "positions.csv").write_text("\n".join(rows) + "\n")
    (own / "dataset.toml").write_text('radius = 2\nname = "corridor-own"\n')
    return own


@pytest.fixture(scope="module")
def records(shared_data, tmp_path_factory):
    """The record of the same run through every route (each with its own cache)."""
    base = tmp_path_factory.mktemp("routes")
    where = lambda route: ["--data-dir", shared_data, "--cache-dir", base / route]  # noqa: E731
    own = own_folder(shared_data, base / "own")
    plan = base / "plan.toml"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')
    found = {}
    with pytest.MonkeyPatch.context() as patch, _capture() as capsys:
        patch.setenv("COLUMNS", "200")
        found["single"] = json.loads(cli(capsys, "evaluate", *METHOD, "--dataset", "corridor", *SPEC, *RUN,
                                         *where("single"), "--json"))
        found["protocol"] = json.loads(cli(capsys, "evaluate", *METHOD, "--dataset", "corridor", "--protocol",
                                           "vpr-bench", *SPEC, *RUN, *where("protocol"), "--json"))
        cli(capsys, "evaluate", *METHOD, "--dataset", "corridor", own, *SPEC, *RUN, *where("matrix"))
        found["matrix"] = the_record(base / "matrix")
        cli(capsys, "run", plan, *SPEC, *RUN, *where("plan"))
        found["plan"] = the_record(base / "plan")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2", "-m", "vprbench",
               "evaluate", *METHOD, "--dataset", "corridor", *SPEC, *RUN, *where("torchrun"), "--json"]
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    found["torchrun"] = json.loads(done.stdout)
    return found


class _capture:
    """capsys for a module fixture: stdout and stderr of in-process CLI calls."""

    def __enter__(self):
        import io
        from contextlib import redirect_stderr, redirect_stdout

        self.out, self.err = io.StringIO(), io.StringIO()
        self._stack = [redirect_stdout(self.out), redirect_stderr(self.err)]
        for c in self._stack:
            c.__enter__()
        return self

    def __exit__(self, *exc):
        for c in reversed(self._stack):
            c.__exit__(*exc)

    def readouterr(self):
        out, err = self.out.getvalue(), self.err.getvalue()
        self.out.seek(0), self.out.truncate(0), self.err.seek(0), self.err.truncate(0)
        return out, err


@pytest.mark.parametrize("route", ROUTES)
@pytest.mark.parametrize("option", TABLE)
def test_every_option_means_the_same_in_every_route(records, option, route):
    where, expected = TABLE[option]
    assert where(records[route]) == expected, f"{option} in the {route} route"


@pytest.mark.parametrize("route", ROUTES[1:])
def test_every_route_gives_the_single_runs_spec_and_results(records, route):
    single, other = records["single"], records[route]
    assert other["spec"] == single["spec"] and other["spec_key"] == single["spec_key"]
    assert other["recall"] == single["recall"] and other["top_predictions"] == single["top_predictions"]


def test_torchrun_really_ran_two_ranks(records):
    assert records["torchrun"]["context"]["distributed"]["world_size"] == 2


def test_reproduce_takes_the_run_settings_and_refuses_what_would_change_the_table(shared_data, tmp_path, capsys,
                                                                                  monkeypatch):
    import vprbench.sweep.reproduce as reproduce

    table = {"t": {"paper": "t", "title": "a table of hog on Corridor", "metrics": ["r1", "r5"],
                   "columns": {"corridor": ["corridor"]},
                   "rows": [{"row": "HOG", "method": "hog", "options": {"resize": [32, 32]}}]}}
    monkeypatch.setattr(reproduce, "reproduce_tables", lambda paper: table)
    monkeypatch.setenv("COLUMNS", "200")
    where = ["--data-dir", shared_data, "--cache-dir", tmp_path / "r"]
    cli(capsys, "reproduce", "anyloc", "--table", "t", *RUN, *where)
    record = the_record(tmp_path / "r")
    for option in ("--search-memory", "--workers", "--lock-timeout", "--batch-size", "--device", "--strict", "--download"):
        where_, expected = TABLE[option]
        assert where_(record) == expected, option
    single = json.loads(cli(capsys, "evaluate", *METHOD, "--dataset", "corridor", "--k", "1", "5",
                            "--data-dir", shared_data, "--cache-dir", tmp_path / "s", "--json"))
    assert record["spec"] == single["spec"] and record["recall"] == single["recall"]
    for changes in (["--index", "hnsw"], ["--k", "1"], ["--store-dtype", "float16"], ["--layer", "3"], ["-o", "cell=8"]):
        code = main([str(a) for a in ("reproduce", "anyloc", "--table", "t", *changes, *where)])
        err = capsys.readouterr().err
        assert code == 1 and "would change what is computed" in err and "Traceback" not in err, changes
    with pytest.raises(SystemExit):  # so its --help lists none of them: only what it takes
        main(["reproduce", "--help"])
    shown = capsys.readouterr().out
    assert "--search-memory" in shown and not any(flag in shown for flag in ("--weights", "--layer", "--index", "--k "))


def test_options_a_route_cannot_use_are_refused_with_the_reason(shared_data, capsys):
    for args, reason in (
        (["--method", "hog", "dense-vlad", "--dataset", "corridor", "--json"], "--json prints one run's record"),
        (["--method", "hog", "--dataset", "corridor", "hawkins", "--json"], "this command makes 2 runs"),
    ):
        code = main(["evaluate", *args, "--data-dir", str(shared_data)])
        err = capsys.readouterr().err
        assert code == 1 and reason in err, err


@pytest.mark.parametrize("written", [["-o", "resize=64,64"], ["-o", "resize=64x64"], ["-o", "resize=64"],
                                     ["-o", "resize=64.0"]])
def test_one_option_written_several_ways_is_one_spec(written, shared_data):
    """`-o resize=64,64` and `--resize 64 64` made two leaderboard rows (and two stores) for one computation."""
    from vprbench.cli.options import method_options
    from vprbench.cli.main import build_parser
    from vprbench.spec import resolve_spec

    def spec(*flags):
        args = build_parser().parse_args(["evaluate", "--method", "hog", "--dataset", "corridor", *flags])
        return resolve_spec("hog", "corridor", options=method_options(args), data_dir=shared_data)

    flagged = spec("--resize", "64", "64")
    assert spec(*written).key == flagged.key and flagged.given == {"resize": [64, 64]}
    assert resolve_spec("hog", "corridor", options={"resize": (64.0, "64")}, data_dir=shared_data).key == flagged.key


def test_run_settings_given_with_o_count_in_every_route_and_flags_win(shared_data, tmp_path, capsys):
    """One evaluation dropped `-o workers=...` unchecked (a matrix checked and used it), and a plan
    entry's `workers` won over the --workers flag."""
    where = ["--data-dir", shared_data, "--cache-dir", tmp_path / "c", "--k", "1", "--quiet"]
    record = json.loads(cli(capsys, "evaluate", *METHOD, "--dataset", "corridor", "-o", "workers=0",
                            "-o", "memory_budget=100MB", *where, "--json"))
    assert (record["run"]["workers"], record["run"]["memory_budget"]) == (0, 100_000_000)
    assert record["run"]["device"] == "cpu"  # where hog runs; it said 'auto', the setting, not the device
    code = main([str(a) for a in ("evaluate", *METHOD, "--dataset", "corridor", "-o", "workers=banana", *where)])
    err = capsys.readouterr().err
    assert code == 1 and "option workers takes a whole number from 0 to 1024 (loader processes); got 'banana'" in err, err
    plan = tmp_path / "plan.toml"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32], workers = 1, batch_size = 3 }\n\n'
                    '[[datasets]]\nname = "corridor"\n')
    cli(capsys, "run", plan, "--workers", "0", *where[:3], tmp_path / "p", *where[4:])
    record = the_record(tmp_path / "p")
    assert (record["run"]["workers"], record["run"]["batch_size"]) == (0, 3)


def test_a_protocol_asked_of_a_dataset_already_loaded_is_the_one_it_was_loaded_under(shared_data, tmp_path):
    """The Python API's protocol was dropped, unsaid, for a Dataset already loaded: the spec named (and the run
    computed) the protocol it was loaded under, whatever protocol asked; by name it is applied or refused."""
    from vprbench import VPRBenchError, create_method
    from vprbench.datasets import load_dataset
    from vprbench.spec import resolve_spec, spec_for

    hog, cache = create_method("hog"), tmp_path / "cache"
    corridor = load_dataset("corridor", shared_data)
    for protocol in (None, "default", "vpr-bench"):
        assert spec_for(hog, corridor, protocol=protocol).key == resolve_spec("hog", "corridor", protocol=protocol).key
    with pytest.raises(VPRBenchError, match="Dataset 'corridor' has no protocol 'tolerance-10'. Its protocols: "):
        spec_for(hog, corridor, protocol="tolerance-10")  # as by name
    own = own_folder(shared_data, tmp_path / "own")
    mine = load_dataset(own, cache_dir=cache)
    for protocol in (None, "default", "own"):
        assert resolve_spec("hog", mine, protocol=protocol, cache_dir=cache).key == \
            resolve_spec("hog", own, protocol=protocol, cache_dir=cache).key
    one = r"The dataset given has one protocol, corridor-own:own \(its own positions and radius\), not 'vpr-bench'"
    with pytest.raises(VPRBenchError, match=one):
        spec_for(hog, mine, protocol="vpr-bench", cache_dir=cache)


def test_a_search_given_as_a_searchspec_is_the_search_given_as_a_table():
    """resolve_spec took a SearchSpec as it was: a default written out (hnsw_m=32) made another run and leaderboard
    row than the same search as a table or --index-option, and an option the index does not take (exact search's
    nprobe) was kept, unused, in the run's identity."""
    from vprbench import VPRBenchError
    from vprbench.spec import SearchSpec, resolve_spec

    table = resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {"hnsw_m": 32}})
    given = resolve_spec("hog", "corridor", search=SearchSpec(index="hnsw", options={"hnsw_m": 32}))
    assert given.key == table.key == resolve_spec("hog", "corridor", search="hnsw").key and given.search.options == {}
    deep = resolve_spec("hog", "corridor", search="hnsw", ks=(1, 5, 111))  # a spec's own search, handed on
    assert resolve_spec("hog", "corridor", search=deep.search, ks=(1, 5, 111)).key == deep.key
    for search, message in ((SearchSpec(index="exact", options={"nprobe": 3}), "Exact search takes no index options"),
                            (SearchSpec(index="hnsw", options={"nprobe": 3}), "--index hnsw does not take nprobe")):
        with pytest.raises(VPRBenchError, match=message):
            resolve_spec("hog", "corridor", search=search)


def test_a_file_edited_after_a_sweep_planned_its_cell_is_not_recorded_under_the_old_bytes(shared_data, tmp_path,
                                                                                           scratch_methods):
    """A sweep makes every spec first: a file an option names, written again before its cell ran, was read anew
    (its store keyed by the new bytes) while the record's spec, key and leaderboard row named the old ones."""
    import numpy as np

    from vprbench.evaluation import read_results
    from vprbench.spec import RunSettings
    from vprbench.sweep import build_plan, run_cells
    from vprbench.sweep.runner import FAILED

    register_weighted_grey(scratch_methods)  # a method whose one option names a file
    table, cache = tmp_path / "table.npy", tmp_path / "cache"
    settings = RunSettings(data_dir=shared_data, cache_dir=cache)
    data = {"methods": [{"name": "weighted-grey", "options": {"table": str(table)}}], "datasets": ["corridor"],
            "k": [1]}
    np.save(table, np.ones(16))
    planned = build_plan(data, "a plan", data_dir=shared_data, cache_dir=cache).cells
    np.save(table, np.arange(1.0, 17.0))  # written again while the sweep ran other cells
    [outcome] = run_cells(planned, settings)
    assert outcome.status == FAILED and outcome.detail.startswith(
        "weighted-grey: the file option table names changed after this run was planned (sha256:"), outcome.detail
    assert outcome.detail.endswith("written again meanwhile): run it again.") and read_results(cache) == []
    [again] = run_cells(build_plan(data, "a plan", data_dir=shared_data, cache_dir=cache).cells, settings)
    [record] = read_results(cache)  # planned again: named by the bytes it read
    assert again.status == "ran"
    assert record["spec"]["files"] == {"table": record["method_fingerprint"]["settings"]["table"]}
