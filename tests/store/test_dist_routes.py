"""torchrun and one process as routes of one run: each is served by the stores the other wrote (computing nothing,
giving the same record), another option computes anew, ranks started with other run settings are refused, and
bad input is one line said by rank 0."""
import json
import os
import subprocess
import sys

import pytest

import vprbench
from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.evaluation.extract import describe_splits
from test_dist_served import RankZeroOfTwo
from test_distributed import DRIVER, record_of, torchrun


class RankOneOfTwo(RankZeroOfTwo):
    """Rank 1 of a 2-rank job in one process: rank 0 found the stores complete."""

    def __init__(self):
        super().__init__()
        self.rank = 1

    def broadcast(self, value):
        return True  # rank 0's answer: complete


def test_a_rank_other_than_zero_is_served_by_stores_rank_zero_found_complete(shared_data, tmp_path):
    """Rank 1 crashed (AttributeError: 'NoneType' object has no attribute 'items') whenever rank 0 found
    the stores complete: every torchrun over stores already made failed."""
    dataset = load_dataset("corridor", shared_data)
    splits = {"database": dataset.database[:20], "queries": dataset.queries[:10]}
    method = vprbench.create_method("thumb-test")
    describe_splits(method, splits, root=dataset.root, label="corridor", cache_dir=tmp_path)
    served = describe_splits(method, splits, root=dataset.root, label="corridor", cache_dir=tmp_path,
                             ranks=RankOneOfTwo())
    assert served.stores is None and served.computed == {"database": 0, "queries": 0}


def test_torchrun_and_one_process_serve_each_other_and_another_option_computes_anew(shared_data, tmp_path, capsys):
    args = ["--method", "fitted-test", "--dataset", "corridor", "--data-dir", str(shared_data), "--k", "1", "3"]
    one = tmp_path / "one"
    assert main(["evaluate", *args, "--cache-dir", str(one), "--json", "--quiet"]) == 0
    alone = json.loads(capsys.readouterr().out)
    served = record_of(torchrun(shared_data, one, "--k", "1", "3"))  # over the stores one process wrote
    assert served["descriptors_computed"] == {"database": 0, "queries": 0}
    assert served["spec_key"] == alone["spec_key"] and served["recall"] == alone["recall"]
    two = tmp_path / "two"
    sharded = record_of(torchrun(shared_data, two, "--k", "1", "3"))
    assert sharded["descriptors_computed"] == {"database": 111, "queries": 111}
    assert main(["evaluate", *args, "--cache-dir", str(two), "--json", "--quiet"]) == 0
    again = json.loads(capsys.readouterr().out)  # one process over the stores torchrun merged
    assert again["descriptors_computed"] == {"database": 0, "queries": 0} and again["recall"] == sharded["recall"]
    other = record_of(torchrun(shared_data, two, "--k", "1", "3", "-o", "shift=1"))
    assert other["descriptors_computed"] == {"database": 111, "queries": 111}
    assert other["spec_key"] != sharded["spec_key"]


def test_ranks_started_with_other_run_settings_are_refused_before_any_work(shared_data, tmp_path):
    """A rank started with another --batch-size or --workers ran with it unsaid: the record named rank 0's
    settings for rows the other rank described otherwise."""
    for flag, value in (("--batch-size", "{rank}3"), ("--workers", "{rank}")):
        done = torchrun(shared_data, tmp_path, flag, value)
        assert done.returncode != 0, flag
        assert "error: torchrun ranks disagree on the run (spec, cache folder, data root, run settings)" in done.stderr
        said = {"--batch-size": ('"batch_size": 3', '"batch_size": 13'), "--workers": ('"workers": 0', '"workers": 1')}
        assert all(text in done.stderr for text in said[flag]), done.stderr[-2000:]
        assert "VPRBenchError" not in done.stderr and not list(tmp_path.rglob("*.h5"))  # refused before any work


def test_bad_input_under_torchrun_is_one_line_said_by_rank_zero(shared_data, tmp_path):
    """Every rank printed the same error line (a missing dataset, an unknown option: one per rank)."""
    for bad in (["--dataset", "nordland"], ["--dataset", "corridor", "-o", "size=banana"]):
        command = ["--method", "thumb-test", *bad]
        done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2",
                               str(DRIVER), "evaluate", *command, "--data-dir", str(shared_data), "--cache-dir",
                               str(tmp_path)], capture_output=True, text=True, cwd=DRIVER.parent, timeout=120,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert done.returncode != 0 and done.stderr.count("error: ") == 1, done.stderr[-2000:]
        assert "[rank" not in done.stderr  # no rank's traceback


class FakeStore:
    def __init__(self, held=None):
        self.held = dict(held or {})

    def set(self, key, value):
        self.held[key] = value.encode()

    def check(self, keys):
        return all(key in self.held for key in keys)

    def get(self, key):
        return self.held[key]


def test_rank_zero_says_what_every_rank_met_and_another_rank_its_own(monkeypatch):
    import torch.distributed.distributed_c10d as c10d

    import vprbench.distributed as distributed
    from vprbench.distributed import Ranks

    store = FakeStore()
    monkeypatch.setattr(c10d, "_get_default_store", lambda: store)
    monkeypatch.setattr(distributed, "SAID_WAIT_S", 0.1)
    met = VPRBenchError("Unknown dataset 'x'.")
    Ranks(rank=0, world_size=2).said_once(met)
    assert not getattr(met, "said", False)  # rank 0 says it
    same, own = VPRBenchError("Unknown dataset 'x'."), VPRBenchError("rank 1's own trouble")
    Ranks(rank=1, world_size=2).said_once(same)
    Ranks(rank=1, world_size=2).said_once(own)
    assert same.said and not own.said
    alone = VPRBenchError("Unknown dataset 'x'.")
    Ranks().said_once(alone)  # one process: it says its own
    assert not getattr(alone, "said", False)


def test_rank_zero_says_an_error_before_it_posts_it(monkeypatch):
    """Rank 1 found rank 0's message and exited; torchrun then stopped rank 0 before it had said it (the
    command line prints after the group is left): under load no rank said the error at all."""
    import torch.distributed.distributed_c10d as c10d

    from vprbench.distributed import SAID_KEY, Ranks

    store, posted_when_said = FakeStore(), []
    monkeypatch.setattr(c10d, "_get_default_store", lambda: store)
    met = VPRBenchError("Unknown dataset 'x'.")
    Ranks(rank=0, world_size=2).said_once(met, say=lambda error: posted_when_said.append(store.check([SAID_KEY])))
    assert posted_when_said == [False] and met.said and store.get(SAID_KEY) == b"Unknown dataset 'x'."


@pytest.mark.parametrize("local_rank, rank, said, own", [
    ("0", "0", "warning: layer 31 is another backbone's\n", "warning (rank 0): Image a.png: Pillow warns\n"),
    ("1", "1", "", "warning (rank 1): Image a.png: Pillow warns\n"),  # was: every rank said the first again
    (None, None, "warning: layer 31 is another backbone's\n", "warning: Image a.png: Pillow warns\n"),  # one process
])
def test_a_warning_every_rank_meets_is_said_once_a_node_and_one_about_a_rank_s_share_by_that_rank(
        monkeypatch, local_rank, rank, said, own):
    from vprbench.cli.main import warning_format
    from vprbench.errors import ShardWarning

    for name, value in (("WORLD_SIZE", "2" if rank else None), ("RANK", rank), ("LOCAL_RANK", local_rank)):
        monkeypatch.setenv(name, value) if value else monkeypatch.delenv(name, raising=False)
    shown = warning_format()
    assert shown("layer 31 is another backbone's", UserWarning, "x.py", 1) == said
    assert shown("Image a.png: Pillow warns", ShardWarning, "x.py", 1) == own


def test_what_the_backend_prints_while_ranks_join_goes_to_stderr():
    """gloo in torch 2.8 printed '[Gloo] Rank 0 is connected to 1 peer ranks...' on stdout while the group was
    made: under torchrun, --json's record was no JSON."""
    script = ("import os\nfrom vprbench.distributed import _stdout_to_stderr\nprint('before', flush=True)\n"
              "with _stdout_to_stderr():\n    os.write(1, b'[Gloo] Rank 0 is connected\\n')\nprint('record')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr) == (0, "before\nrecord\n", "[Gloo] Rank 0 is connected\n")
