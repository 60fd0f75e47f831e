"""Kill -9 and concurrency torture for the descriptor store, in real processes.

    python torture_driver.py kills DATA WORK [--spread N] [--timed N]
    python torture_driver.py concurrent DATA WORK

The driver imports vprbench once, then forks one child process per run (cheap, and each child
is a real process: its own file descriptors, locks and SIGKILL). Prints a JSON report.

kills: a clean run counts the "moments" of an evaluation (every HDF5 file open, flush, close,
dataset creation and write, os.replace, fsync, describe call and fit), marking those inside the
fit-state write. Then, each in a fresh cache, a child SIGKILLs itself at one moment (every
moment of the fit-state write, plus N spread over the rest), or is SIGKILLed from outside
after a random delay; a second child resumes. Reported per kill: rows done at the kill, rows
the resume described, whether it refitted, and whether stores and results equal the clean run
bit for bit.

concurrent: 3 identical and 4 different evaluations start at once on one cache; each result
is compared with the same evaluation run alone in a fresh cache.
"""
from __future__ import annotations

import os

# One thread everywhere: OpenMP and BLAS thread pools do not survive fork (a forked child would hang).
for variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[variable] = "1"

import json  # noqa: E402
import random  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import h5py  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import store_helpers  # noqa: E402
import vprbench  # noqa: E402
from vprbench.datasets import load_dataset  # noqa: E402
from vprbench.evaluation import evaluate  # noqa: E402
from vprbench.spec import RunSettings, spec_for  # noqa: E402
from vprbench.store import folder as store_folder  # noqa: E402

store_helpers.register_all()
cv2.setNumThreads(1)
torch.set_num_threads(1)


def run_child(work, data: Path, cache: Path, out: Path, *, method="fitted-test", options=None, ks=(1, 5, 10),
              kill_at=0, count_to: Path | None = None) -> int:
    """Fork a child that evaluates and writes {"record", "fits", "warnings"} to `out`; returns its pid."""
    pid = os.fork()
    if pid:
        return pid
    code = 0
    try:
        os.environ["VPRBENCH_CACHE"] = str(cache)
        events = _instrument(kill_at) if (kill_at or count_to) else None
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            m = vprbench.create_method(method, **(options or {}))
            dataset = load_dataset("corridor", data)
            record = evaluate(spec_for(m, dataset, ks=ks), RunSettings(cache_dir=cache), dataset=dataset, method=m)
        result = {"record": record, "fits": getattr(m, "fits", None), "warnings": [str(w.message) for w in caught]}
        out.write_text(json.dumps(result, default=str))
        if count_to is not None:
            count_to.write_text(json.dumps(events))
    except BaseException:  # the child reports everything, then leaves without running the parent's exit handlers
        out.write_text(json.dumps({"error": traceback.format_exc()}))
        code = 1
    os._exit(code)


def _instrument(kill_at: int) -> list:
    """Count every moment that touches the store; SIGKILL this process at moment `kill_at`."""
    events: list = []
    state = {"in_fit_write": False}

    def wrap(owner, name, label):
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            events.append([label, state["in_fit_write"]])
            if len(events) == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            return original(*args, **kwargs)

        setattr(owner, name, wrapper)

    for owner, name in ((h5py.File, "__init__"), (h5py.File, "flush"), (h5py.File, "close"),
                        (h5py.Group, "create_dataset"), (h5py.Dataset, "__setitem__"), (os, "replace"), (os, "fsync"),
                        (store_helpers.Thumb, "describe"), (store_helpers.Fitted, "fit")):
        wrap(owner, name, f"{getattr(owner, '__name__', owner)}.{name}")
    write_fit_state = store_folder.StoreFolder.write_fit_state

    def fit_write(self, fit_state):
        state["in_fit_write"] = True
        try:
            return write_fit_state(self, fit_state)
        finally:
            state["in_fit_write"] = False

    store_folder.StoreFolder.write_fit_state = fit_write
    return events


def wait(pid: int) -> int:
    """The child's exit status: its exit code, or -signal."""
    _, status = os.waitpid(pid, 0)
    return -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)


def store_files(cache: Path) -> dict[str, list[Path]]:
    return {"complete": sorted(cache.rglob("*.h5")), "partial": sorted(cache.rglob("*.partial.h5")),
            "temporary": sorted(p for p in cache.rglob(".*.tmp"))}


def read_stores(cache: Path) -> dict[str, np.ndarray]:
    found = {}
    for path in cache.rglob("*.h5"):
        if not path.name.endswith(".partial.h5"):
            with h5py.File(path) as f:
                found[path.name] = f["state"]["centre"][...] if path.name == "fit_state.h5" else f["descriptors"][...]
    return found


def done_rows(cache: Path) -> dict[str, int]:
    """Rows flagged done per split in whatever a killed run left (complete stores count fully)."""
    done = {"database": 0, "queries": 0}
    for path in cache.rglob("*.h5"):
        split = path.name.split(".")[0]
        if split in done:
            with h5py.File(path) as f:
                done[split] = int(f["done"][...].sum())
    return done


def kills(data: Path, work: Path, spread: int, timed: int) -> dict:
    clean_cache, clean_out, count = work / "clean", work / "clean.json", work / "events.json"
    started = time.perf_counter()
    assert wait(run_child(work, data, clean_cache, clean_out, count_to=count)) == 0, clean_out.read_text()
    clean_seconds = time.perf_counter() - started
    clean = json.loads(clean_out.read_text())["record"]
    reference = read_stores(clean_cache)
    events = json.loads(count.read_text())
    in_fit = [i + 1 for i, (_, fitting) in enumerate(events) if fitting]
    others = [i + 1 for i, (_, fitting) in enumerate(events) if not fitting]
    chosen = sorted(set(in_fit) | set(others[:: max(1, len(others) // spread)]))
    rng = random.Random(0)
    scenarios = [("moment", k) for k in chosen] + [("timed", rng.uniform(0.05, clean_seconds)) for _ in range(timed)]
    report = {"moments": len(events), "fit_write_moments": in_fit, "runs": []}
    for index, (kind, when) in enumerate(scenarios):
        cache, out = work / f"kill-{index}", work / f"kill-{index}.json"
        if kind == "moment":
            status = wait(run_child(work, data, cache, out, kill_at=when))
        else:
            pid = run_child(work, data, cache, out)
            time.sleep(when)
            os.kill(pid, signal.SIGKILL)
            status = wait(pid)
        done = done_rows(cache)
        fit_saved = (next(cache.rglob("fit_state.h5"), None) is not None) if cache.exists() else False
        resumed_out = work / f"resume-{index}.json"
        resumed_status = wait(run_child(work, data, cache, resumed_out))
        resumed = json.loads(resumed_out.read_text())
        run = {"kind": kind, "at": when, "event": events[when - 1][0] if kind == "moment" else None,
               "killed": status == -9, "done_at_kill": done, "fit_saved": fit_saved, "resume_exit": resumed_status}
        if resumed_status == 0:
            record = resumed["record"]
            stores = read_stores(cache)
            run.update({
                "computed": record["descriptors_computed"], "refitted": resumed["fits"] == 1,
                "same_result": record["recall"] == clean["recall"] and record["top_predictions"] == clean["top_predictions"],
                "bit_identical": stores.keys() == reference.keys() and all(np.array_equal(stores[k], reference[k]) for k in stores),
                "leftovers": [str(p.name) for p in store_files(cache)["partial"] + store_files(cache)["temporary"]],
                "warnings": resumed["warnings"],
            })
        else:
            run["error"] = resumed.get("error")
        report["runs"].append(run)
    return report


def kill_problems(report: dict) -> list[str]:
    """Every way a resumed run could be wrong, as readable lines (none is the pass)."""
    problems = []
    for run in report["runs"]:
        where = f"{run['kind']} kill at {run['at']} ({run['event']})"
        if run["resume_exit"] != 0:
            problems.append(f"{where}: the resumed run failed: {run.get('error')}")
            continue
        expected = {split: 111 - run["done_at_kill"][split] for split in ("database", "queries")}
        checks = {
            "stores or fit differ from the clean run's": not run["bit_identical"],
            "results differ from the clean run's": not run["same_result"],
            f"partial or temporary files left: {run['leftovers']}": bool(run["leftovers"]),
            f"described {run['computed']}, only the missing {expected} should be": run["computed"] != expected,
            "a saved fit was fitted again, or a lost one not refitted": run["refitted"] == run["fit_saved"],
            f"discarded work: {run['warnings']}": any("Discarding" in w for w in run["warnings"]),
        }
        problems += [f"{where}: {text}" for text, failed in checks.items() if failed]
    return problems


CONCURRENT = [  # (label, method, options, ks)
    ("same-1", "fitted-test", {}, (1, 5, 10)),
    ("same-2", "fitted-test", {}, (1, 5, 10)),
    ("same-3", "fitted-test", {}, (1, 5, 10)),
    ("other-k", "fitted-test", {}, (1, 3)),
    ("other-shift", "fitted-test", {"shift": 3.0}, (1, 5, 10)),
    ("other-thumb", "thumb-test", {"size": 6}, (1, 5, 10)),
    ("other-hog", "hog", {"resize": (32, 32)}, (1, 5, 10)),
]


def concurrent(data: Path, work: Path) -> dict:
    shared = work / "shared"
    pids = {label: run_child(work, data, shared, work / f"{label}.json", method=method, options=options, ks=ks)
            for label, method, options, ks in CONCURRENT}
    statuses = {label: wait(pid) for label, pid in pids.items()}
    report = {"statuses": statuses, "runs": {}}
    alone = {}
    for label, method, options, ks in CONCURRENT:
        key = json.dumps([method, options, ks])
        if key not in alone:  # the same evaluation run by itself, in a fresh cache
            out = work / f"alone-{len(alone)}.json"
            assert wait(run_child(work, data, work / f"alone-{len(alone)}", out, method=method, options=options, ks=ks)) == 0
            alone[key] = json.loads(out.read_text())["record"]
        expected = alone[key]
        got = json.loads((work / f"{label}.json").read_text())
        if "error" in got:
            report["runs"][label] = {"error": got["error"]}
            continue
        record = got["record"]
        report["runs"][label] = {
            "same_as_alone": all(record[k] == expected[k] for k in ("recall", "top_predictions", "descriptor_dim", "auc_pr")),
            "computed": record["descriptors_computed"], "fits": got["fits"], "warnings": got["warnings"],
        }
    files = store_files(shared)
    report["leftovers"] = [str(p.relative_to(shared)) for p in files["partial"] + files["temporary"]]
    report["complete_stores"] = len([p for p in files["complete"] if p.name in ("database.h5", "queries.h5")])
    return report


def warm_up(data: Path, work: Path) -> None:
    """One evaluation in the driver itself, so children start with everything imported (torch, faiss, sklearn, cv2)."""
    for method, options in (("fitted-test", {}), ("hog", {"resize": (32, 32)})):
        m, dataset = vprbench.create_method(method, **options), load_dataset("corridor", data)
        evaluate(spec_for(m, dataset), RunSettings(cache_dir=work / "warm-up"), dataset=dataset, method=m)


if __name__ == "__main__":
    mode, data, work = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
    options = dict(zip(sys.argv[4::2], sys.argv[5::2]))
    work.mkdir(parents=True, exist_ok=True)
    warm_up(data, work)
    if mode == "kills":
        result = kills(data, work, int(options.get("--spread", 20)), int(options.get("--timed", 8)))
        result["problems"] = kill_problems(result)
    else:
        result = concurrent(data, work)
    print(json.dumps(result, default=str))
