"""Multi-run machinery fed by a hostile or careless user: plan files, reproduce's paper name and
torchrun ranks. Each gets one clear line, exit 1, no traceback, and nothing runs or is stored."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vprbench.distributed import Ranks
from vprbench.errors import VPRBenchError

PLAN_HEAD = 'k = [1]\n'


def run_plan(cli, tmp_path, text: str, *, data_dir: bool = True):
    """`data_dir=False` for a plan of folders of one's own only (a data root is refused there)."""
    plan = tmp_path / "plan.toml"
    plan.write_text(text)
    cache = tmp_path / "cache"
    code, out, err = cli("run", plan, "--cache-dir", cache, *(["--data-dir", tmp_path / "no-data"] if data_dir else []))
    return code, out + err, cache


# ---------------------------------------------------------------- plan files: wrong types
@pytest.mark.parametrize("entry, expected", [
    # a list where a name is expected: TypeError: unhashable type: 'list'
    ('[[methods]]\nname = ["hog"]\n', "plan.toml:4: unknown method ['hog']. Did you mean: hog?"),
    ('[[methods]]\nname = 5\n', "plan.toml:4: unknown method 5."),
])
def test_a_method_name_that_is_not_a_text_is_one_line(cli, tmp_path, entry, expected):
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + 'datasets = ["corridor"]\n' + entry)
    assert code == 1 and "has 1 problem(s); nothing was run" in output and expected in output
    assert "Traceback" not in output and not (cache / "results").exists()


@pytest.mark.parametrize("key, expected", [
    # one text: was read letter by letter, one "has no protocol 'v'" line per letter
    ('protocols = "vpr-bench"', "protocols of dataset 'corridor' must be a list of names, e.g. ['vpr-bench']; got 'vpr-bench'"),
    # not names: TypeError: unhashable type: 'dict'
    ('protocols = [1, {a = 1}]', "protocols of dataset 'corridor' must be a list of names, e.g. ['vpr-bench']; got [1, {'a': 1}]"),
    ('protocol = ["vpr-bench"]', "protocol of dataset 'corridor' must be a name; got ['vpr-bench']"),
    # no protocol at all: the plan had no cells and exited 0, having run nothing
    ('protocols = []', "protocols of dataset 'corridor' must be a list of names, e.g. ['vpr-bench']; got []"),
    # both: protocol was dropped, silently, and the run not the one asked for
    ('protocol = "nope"\nprotocols = ["vpr-bench"]', "dataset 'corridor' gives both protocol and protocols; give one"),
])
def test_protocols_of_the_wrong_type_are_one_line(cli, tmp_path, key, expected):
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + f'methods = ["hog"]\n[[datasets]]\nname = "corridor"\n{key}\n')
    assert code == 1 and "has 1 problem(s); nothing was run" in output
    assert f"plan.toml:5: {expected}" in output and "no protocol 'v'" not in output and "Traceback" not in output


@pytest.mark.parametrize("text, expected", [
    # each was shown as its Python spelling (a row named "['a', {'b': 1}]"), the plan run all the same
    ('name = ["x"]\nmethods = ["hog"]\n', "plan.toml:3: the plan's name must be a text; got ['x']"),
    ('description = { a = 1 }\nmethods = ["hog"]\n', "plan.toml:3: the plan's description must be a text; got {'a': 1}"),
    ('[[methods]]\nname = "hog"\nlabel = ["a", 1]\n', "plan.toml:5: label of method 'hog' must be a text (the row's name); "
                                                     "got ['a', 1]"),
])
def test_a_plan_name_or_label_that_is_not_a_text_is_one_line(cli, tmp_path, text, expected):
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + 'datasets = ["corridor"]\n' + text)
    assert code == 1 and "has 1 problem(s); nothing was run" in output and expected in output
    assert "Traceback" not in output and not (cache / "results").exists()


def test_a_plan_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Was: "Plan ... is not valid TOML: Invalid statement (at line 1, column 1)", of a plan that looked right."""
    from vprbench.sweep.plan import read_entries

    plan = tmp_path / "plan.toml"
    plan.write_text('\ufeffk = [1]\nmethods = ["hog"]\ndatasets = ["corridor"]\n', encoding="utf-8")
    entries = read_entries(plan)
    assert [name for _, name, *_ in entries.methods] == ["hog"] and entries.shared["ks"] == [1]


def test_a_very_long_name_is_shortened_in_the_message(cli, tmp_path):
    code, output, _ = run_plan(cli, tmp_path, PLAN_HEAD + f'methods = ["{"a" * 5000}"]\ndatasets = ["corridor"]\n')
    assert code == 1 and "unknown method 'aaaaaaaaaaaa...aaaaaaaaaaaaa'" in output and len(output) < 1000


# ---------------------------------------------------------------- plan files: run settings of an entry
@pytest.mark.parametrize("options, expected", [
    ("batch_size = 2.5", "plan.toml:5: hog: option batch_size takes a whole number >= 1 (images per batch); got 2.5."),
    ("batch_size = 0", "plan.toml:5: hog: option batch_size takes a whole number >= 1 (images per batch); got 0."),
    ('device = "bogus"', "plan.toml:5: hog: option device takes a torch device such as cpu, cuda or cuda:1; got 'bogus'."),
    ("workers = -1", "plan.toml:5: run: option workers takes a whole number from 0 to 1024 (loader processes); got -1."),
    # was: run, with a loader process forked for each batch of images
    ("workers = 100000", "plan.toml:5: run: option workers takes a whole number from 0 to 1024 (loader processes); got 100000."),
    ('memory_budget = "x"', "plan.toml:5: --search-memory (memory_budget) 'x' is not understood"),
    ("lock_timeout = -1", "plan.toml:5: --lock-timeout (lock_timeout) takes a finite number of seconds >= 0"),
])
def test_a_bad_run_setting_stops_the_plan_before_any_cell(cli, tmp_path, options, expected):
    """Was: the plan started, and every cell of the entry failed at run time with the same line."""
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + 'datasets = ["corridor"]\n'
                                   f'[[methods]]\nname = "hog"\noptions = {{ {options} }}\n')
    assert code == 1 and "has 1 problem(s); nothing was run" in output and expected in output
    assert not (cache / "results").exists() and not (cache / "stores").exists() and not (cache / "sweeps").exists()


def test_good_run_settings_still_make_cells(tmp_path):
    from vprbench.sweep.plan import build_plan

    plan = build_plan({"k": [1], "datasets": ["corridor"], "methods": [
        {"name": "hog", "options": {"batch_size": 4, "workers": 0, "device": "cpu", "memory_budget": "1GB", "lock_timeout": 5}}]},
        "plan", cache_dir=tmp_path)
    assert [c.settings for c in plan.cells] == [{"batch_size": 4, "workers": 0, "device": "cpu", "memory_budget": "1GB",
                                                 "lock_timeout": 5}]


# ---------------------------------------------------------------- reproduce: the paper is a name
def test_reproduce_paper_is_a_shipped_name_not_a_path(cli, tmp_path):
    """Was: '../../x' read any x.toml (here one that is not TOML: TOMLDecodeError traceback)."""
    from importlib.resources import files

    hostile = tmp_path / "hostile.toml"
    hostile.write_text("this is not toml [")
    relative = os.path.relpath(hostile.with_suffix(""), Path(str(files("vprbench.manifests") / "reproduce")))
    code, out, err = cli("reproduce", relative, "--table", "2", "--dry-run", "--cache-dir", tmp_path / "cache")
    assert code == 1 and f"error: No reproduction plans for paper {relative!r}. Available: anyloc." in err
    code, out, err = cli("reproduce", "anylo", "--table", "2", "--dry-run", "--cache-dir", tmp_path / "cache")
    assert code == 1 and "No reproduction plans for paper 'anylo'. Did you mean: anyloc? Available: anyloc." in err


# ---------------------------------------------------------------- torch.distributed: the environment
@pytest.mark.parametrize("environment, expected", [
    ({"WORLD_SIZE": "abc"}, "$WORLD_SIZE is 'abc', not a whole number from 0 to 2147483647: start the ranks with torchrun"),
    ({"WORLD_SIZE": "²"}, "$WORLD_SIZE is '²', not a whole number from 0 to 2147483647"),
    # was: TypeError: incompatible constructor arguments (TCPStore's world_size is a C int)
    ({"WORLD_SIZE": "99999999999999999999999"}, "$WORLD_SIZE is '99999999999999999999999', not a whole number from 0"),
    # was: ValueError: Exceeds the limit (4300 digits) for integer string conversion
    ({"WORLD_SIZE": "1" * 5000}, "not a whole number from 0 to 2147483647: start the ranks with torchrun"),
    ({"WORLD_SIZE": "2"}, "$RANK is not set: start the ranks with torchrun"),
    ({"WORLD_SIZE": "2", "RANK": "5"}, "$RANK is 5 but $WORLD_SIZE is 2"),
    ({"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "-1"}, "$LOCAL_RANK is '-1', not a whole number from 0 to 2147483647"),
    ({"WORLD_SIZE": "2", "RANK": "0", "VPRBENCH_DIST_TIMEOUT": "soon"}, "$VPRBENCH_DIST_TIMEOUT is 'soon'; it takes the seconds"),
    ({"WORLD_SIZE": "2", "RANK": "0", "VPRBENCH_DIST_TIMEOUT": "nan"}, "$VPRBENCH_DIST_TIMEOUT is 'nan'"),
    # was: OverflowError: Python int too large to convert to C int (from timedelta)
    ({"WORLD_SIZE": "2", "RANK": "0", "VPRBENCH_DIST_TIMEOUT": "1e20"}, "$VPRBENCH_DIST_TIMEOUT is '1e20'; it takes the "
                                                                        "seconds ranks wait for each other, a number > 0 and at most 1e+09."),
    # was: ValueError: Error initializing torch.distributed using env:// rendezvous ...
    ({"WORLD_SIZE": "2", "RANK": "0"}, "torchrun rank 0 could not join the other ranks (Error initializing torch.distributed "
                                       "using env:// rendezvous: environment variable MASTER_ADDR expected, but not set)"),
])
def test_a_broken_torchrun_environment_is_one_line(monkeypatch, environment, expected):
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT", "VPRBENCH_DIST_TIMEOUT"):
        monkeypatch.delenv(name, raising=False)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(VPRBenchError) as caught:
        Ranks.from_environment("cpu")
    assert expected in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("device, backend, gpu", [("auto", "nccl", 1), ("cuda", "nccl", 1), ("cpu", "gloo", None)])
def test_ranks_on_a_gpu_machine_talk_over_nccl_each_on_its_own_gpu(monkeypatch, device, backend, gpu):
    """--device auto (the default) finds the GPU for the process group as for the method (was: gloo, every rank on cuda:0)."""
    import torch
    import torch.distributed as dist

    for name, value in {"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1"}.items():
        monkeypatch.setenv(name, value)
    joined, chosen = [], []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_device", chosen.append)
    monkeypatch.setattr(dist, "is_initialized", lambda: False)
    monkeypatch.setattr(dist, "init_process_group", lambda backend, **_: joined.append(backend))
    ranks = Ranks.from_environment(device)
    assert (ranks.backend, joined, chosen) == (backend, [backend], [gpu] if gpu is not None else [])


# ---------------------------------------------------------------- torch.distributed: a rank that dies or stalls
RANK_SCRIPT = """
import os, signal, sys, time
from vprbench.distributed import Ranks
from vprbench.errors import VPRBenchError
ranks = Ranks.from_environment("cpu")
assert ranks.broadcast("joined") == "joined"
if ranks.rank == 1:
    if os.environ["FATE"] == "killed":
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(60)  # stalled: never joins the next collective
try:
    ranks.all_gather("my share")
except VPRBenchError as error:
    print(error)
    sys.exit(1)
finally:
    ranks.close()
"""


@pytest.mark.parametrize("fate, reason", [("killed", "by peer"), ("stalled", "Timed out waiting 3000ms")])
def test_when_a_rank_dies_or_stalls_the_other_says_so_in_one_line(tmp_path, fate, reason):
    """Two gloo ranks on CPU, as torchrun starts them; rank 1 is SIGKILLed, or stops answering, after
    joining. Was: rank 0 printed a traceback ending 'RuntimeError: [...pair.cc:561] Connection closed
    by peer' (or '... Timed out waiting ...'), and on a timeout aborted (exit 134, 'terminate called')."""
    import socket

    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    environment = {**os.environ, "OMP_NUM_THREADS": "1", "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "FATE": fate,
                   "MASTER_PORT": str(port), "VPRBENCH_DIST_TIMEOUT": "3", "PYTHONPATH": os.pathsep.join(sys.path)}
    started = [subprocess.Popen([sys.executable, "-c", RANK_SCRIPT], cwd=tmp_path, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env={**environment, "RANK": str(rank), "LOCAL_RANK": str(rank)})
               for rank in (0, 1)]
    try:
        out, err = started[0].communicate(timeout=90)
    finally:
        for p in started:
            p.kill()
            p.communicate()
    assert started[0].returncode == 1 and "Traceback" not in err and "terminate called" not in err, err
    assert out.startswith("torchrun rank 0 lost the other ranks (") and reason in out and out.count("\n") == 1
    assert "$VPRBENCH_DIST_TIMEOUT = 3 s" in out and "run the same command again to resume" in out


@pytest.mark.parametrize("nested", ["[" * 100000 + "]" * 100000, "{a=" * 5000 + "1" + "}" * 5000])
def test_a_plan_nested_too_deeply_is_one_line(cli, tmp_path, nested):
    """Was: RecursionError: maximum recursion depth exceeded (a traceback)."""
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + f'methods = ["hog"]\ndatasets = ["corridor"]\nx = {nested}\n')
    assert code == 1 and "plan.toml nests arrays or tables too deeply to be read; check its brackets." in output
    assert "Traceback" not in output and not cache.exists()


# ---------------------------------------------------------------- stage flags
@pytest.mark.parametrize("flags, expected", [
    # was: seqslam ran (a sequence-track record) though --rerank named aqe, past the track check
    (["--rerank", "aqe", "--rerank-option", "name=seqslam"],
     "error: --rerank-option name=seqslam would replace the stage; give the stage with --rerank STAGE."),
    # was: --rerank-k silently won
    (["--rerank", "aqe", "--rerank-k", "50", "--rerank-option", "k=10"],
     "error: --rerank-k 50 and --rerank-option k=10 disagree; give k once."),
    (["--sequence", "seqslam", "--sequence-length", "5", "--sequence-option", "length=7"],
     "error: --sequence-length 5 and --sequence-option length=7 disagree; give length once."),
])
def test_stage_options_cannot_contradict_the_stage_flags(cli, tmp_path, flags, expected):
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--k", "1", *flags,
                         "--cache-dir", tmp_path / "cache", "--data-dir", tmp_path / "no-data")
    assert code == 1 and expected in err and "Traceback" not in err and not (tmp_path / "cache" / "results").exists()


def test_reproduce_refuses_a_publish_folder_it_cannot_make_before_running(cli, tmp_path):
    """Was: every cell of the table ran (or was looked for), the tables were printed, then 'Not a directory'."""
    (tmp_path / "a-file").write_text("")
    code, out, err = cli("reproduce", "anyloc", "--table", "layer", "--publish", tmp_path / "a-file" / "pages",
                         "--cache-dir", tmp_path / "cache", "--data-dir", tmp_path / "no-data")
    assert code == 1 and "a-file/pages: Not a directory; a part of the path is a file" in err
    assert out == "" and not (tmp_path / "cache" / "sweeps").exists()


def test_the_protocols_of_a_folder_of_ones_own_are_not_ignored(cli, tmp_path):
    """Was: `protocols = ["bogus"]` on a folder dataset was dropped and its cells made with 'own'."""
    from PIL import Image

    for split in ("database", "queries"):
        (tmp_path / "mine" / split).mkdir(parents=True)
        Image.new("RGB", (32, 24)).save(tmp_path / "mine" / split / "0.png")
    code, output, cache = run_plan(cli, tmp_path, PLAN_HEAD + f'methods = ["hog"]\n[[datasets]]\nname = "{tmp_path / "mine"}"\n'
                                   'protocols = ["bogus"]\n', data_dir=False)
    assert code == 1 and "nothing was run" in output
    assert "A folder of your own has one protocol, 'own' (its positions and radius); got 'bogus'." in output


def test_a_problem_every_cell_of_a_matrix_has_is_counted_once(cli, tmp_path):
    """Was: 'The command line has 2 problem(s)' above the one line it listed (each cell's copy of it counted)."""
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "17places", "--rerank", "aqe",
                         "--rerank-k", "0", "--cache-dir", tmp_path / "cache", "--data-dir", tmp_path / "no-data")
    assert code == 1 and err.splitlines() == [
        "error: The command line has 1 problem(s); nothing was run:",
        "  the command line: Stage 'aqe' option k: Input should be greater than or equal to 1 (got 0)."]
