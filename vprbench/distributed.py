"""Ranks of a torch.distributed run (torchrun, or torchrun under srun), or one process alone.

`Ranks.from_environment()` joins the process group torchrun describes in the environment
(RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT): gloo on CPU, nccl on CUDA. A
single process gets `Ranks()` (rank 0 of 1) whose collectives do nothing, so the pipeline
has one code path. See docs/distributed.md.
"""
from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from contextlib import contextmanager
from datetime import timedelta

from .errors import VPRBenchError
from .text import shortened

#: how long a rank waits for the others (rank 0 may be waiting for another run's lock)
TIMEOUT_ENV = "VPRBENCH_DIST_TIMEOUT"


class Ranks:
    """rank / world size, and the few collectives the pipeline needs (objects, not tensors)."""

    def __init__(self, rank: int = 0, world_size: int = 1, local_rank: int = 0, backend: str | None = None):
        self.rank, self.world_size, self.local_rank, self.backend = rank, world_size, local_rank, backend

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @classmethod
    def from_environment(cls, device: str = "cpu") -> "Ranks":
        """The process group torchrun set up, or a single process when WORLD_SIZE is unset or 1."""
        world = _whole_from_environment("WORLD_SIZE", "1")
        if world <= 1:
            return cls()
        import torch
        import torch.distributed as dist

        rank, local_rank = _whole_from_environment("RANK"), _whole_from_environment("LOCAL_RANK", "0")
        if rank >= world:
            raise VPRBenchError(f"$RANK is {rank} but $WORLD_SIZE is {world}: start the ranks with torchrun, which sets both.")
        from .loader import resolve_device

        backend = "nccl" if resolve_device(device).startswith("cuda") else "gloo"  # "auto" finds a GPU as the method will
        if not dist.is_initialized():
            kwargs = {}
            if backend == "nccl":
                torch.cuda.set_device(local_rank)
                kwargs["device_id"] = torch.device("cuda", local_rank)
            try:
                with _stdout_to_stderr():
                    dist.init_process_group(backend, timeout=timedelta(seconds=_timeout_s()), **kwargs)
            except (RuntimeError, ValueError) as error:  # no MASTER_ADDR, a rendezvous that timed out
                failed = VPRBenchError(f"torchrun rank {rank} could not join the other ranks ({_first_line(error)}). "
                                       "Start every rank with torchrun and the same --rdzv-endpoint.")
                failed.said = False  # this rank's own: every rank says it
                raise failed from None
        return cls(rank, world, local_rank, backend)

    def all_gather(self, value) -> list:
        if not self.distributed:
            return [value]
        import torch.distributed as dist

        found = [None] * self.world_size
        with self._talking():
            dist.all_gather_object(found, value)
        return found

    def broadcast(self, value):
        """Rank 0's `value` on every rank."""
        if not self.distributed:
            return value
        import torch.distributed as dist

        box = [value if self.rank == 0 else None]
        with self._talking():
            dist.broadcast_object_list(box, src=0)
        return box[0]

    @contextmanager
    def _talking(self):
        """A collective whose peer died (killed, or failed and exited) or never answered: one line
        on this rank instead of the backend's traceback (close() still ends the group: a process
        leaving a timed-out gloo group behind aborts on exit)."""
        try:
            yield
        except RuntimeError as error:  # torch.distributed's errors (DistBackendError...) are RuntimeErrors
            raise VPRBenchError(
                f"torchrun rank {self.rank} lost the other ranks ({_first_line(error)}): one of them stopped (its own "
                f"message says why) or did not answer within ${TIMEOUT_ENV} = {_timeout_s():g} s. Finished descriptors "
                "are kept; fix that and run the same command again to resume.") from None

    def on_zero(self, work: Callable[[], object]):
        """`work()` on rank 0, its result on every rank; a `VPRBenchError` there is raised on all
        ranks (so none waits for a rank that has given up)."""
        outcome, failure = None, None
        if self.rank == 0:
            try:
                outcome = ("ok", work())
            except VPRBenchError as error:
                outcome, failure = ("error", str(error)), error
        outcome = self.broadcast(outcome)
        if failure is not None:
            raise failure
        if outcome[0] == "error":
            raise VPRBenchError(outcome[1])
        return outcome[1]

    def agree(self, value, what: str) -> None:
        """Every rank must hold the same `value` (JSON-able) before any work starts."""
        if not self.distributed:
            return
        found = [json.dumps(v, sort_keys=True, default=str) for v in self.all_gather(value)]
        differ = [rank for rank, text in enumerate(found) if text != found[0]]
        if differ:
            raise VPRBenchError(
                f"torchrun ranks disagree on {what}: rank 0 has {found[0]}, rank {differ[0]} has {found[differ[0]]}. "
                "Start every rank with the same command, options, --cache-dir and data."
            )

    def said_once(self, error: VPRBenchError, say: Callable[[VPRBenchError], None] | None = None) -> None:
        """An error every rank meets alike (bad input: a missing dataset, an unknown option) is said by rank 0
        alone: rank 0 posts its message in torchrun's key-value store, and another rank holding the same one
        marks it `said` (the command line then prints nothing). A rank's own error is still said, after waiting
        `SAID_WAIT_S` for rank 0's. Given `say`, rank 0 says it before it posts it: a rank that found it exits,
        and torchrun then stops rank 0, which had not said it yet."""
        if not self.distributed:
            return
        error.said = False  # known to the ranks' exchange: never taken for an error met before the ranks joined
        import time

        import torch.distributed as dist

        if self.rank == 0 and say is not None:
            say(error)
            error.said = True
        try:
            store = dist.distributed_c10d._get_default_store()
            if self.rank == 0:
                store.set(SAID_KEY, str(error))
                return
            deadline = time.monotonic() + SAID_WAIT_S
            while not store.check([SAID_KEY]) and time.monotonic() < deadline:
                time.sleep(0.05)
            error.said = store.check([SAID_KEY]) and store.get(SAID_KEY).decode() == str(error)
        except Exception:  # noqa: BLE001 - no store (rank 0 gone, a group never joined): this rank says its own
            return

    @contextmanager
    def working(self, say: Callable[[VPRBenchError], None] | None = None):
        """The ranks' work: an error every rank meets is said once (`said_once`, by `say`), and the group is
        left at the end, whatever happened (`close`)."""
        try:
            yield
        except VPRBenchError as error:
            self.said_once(error, say)  # while the group stands
            raise
        finally:
            self.close()

    def close(self) -> None:
        if self.distributed:
            import torch.distributed as dist

            if dist.is_initialized():
                dist.destroy_process_group()

    def describe(self) -> dict:
        return {"world_size": self.world_size, "backend": self.backend}


#: where rank 0 posts the error it says, and how long another rank waits for it before saying its own
SAID_KEY, SAID_WAIT_S = "vprbench/error", 5.0

#: the most ranks (or the highest rank) taken: torch's process group holds them in a C int
MAX_RANKS = 2**31 - 1


def _whole_from_environment(name: str, default: str | None = None) -> int:
    """A whole number >= 0 torchrun puts in the environment; one line when it is missing or not one."""
    value = os.environ.get(name, default)
    digits = (value or "").strip()  # a long one is no count of ranks (and int() refuses 4,300 digits)
    if value is None or not (digits.isascii() and digits.isdigit() and len(digits) <= 10 and int(digits) <= MAX_RANKS):
        shown = "not set" if value is None else f"{shortened(repr(value))}, not a whole number from 0 to {MAX_RANKS}"
        raise VPRBenchError(f"${name} is {shown}: start the ranks with torchrun, "
                            "which sets RANK, WORLD_SIZE and LOCAL_RANK (or unset WORLD_SIZE to run one process).")
    return int(value)


MAX_TIMEOUT_S = 1e9  # about 31 years; past about 2700 years timedelta overflows


def _timeout_s() -> float:
    value = os.environ.get(TIMEOUT_ENV, "86400")
    try:
        seconds = float(value)
    except ValueError:
        seconds = math.nan
    if not (math.isfinite(seconds) and 0 < seconds <= MAX_TIMEOUT_S):  # a longer one overflowed timedelta
        raise VPRBenchError(f"${TIMEOUT_ENV} is {value!r}; it takes the seconds ranks wait for each other, a number > 0 "
                            f"and at most {MAX_TIMEOUT_S:.0e}.")
    return seconds


def _first_line(error: BaseException) -> str:
    """The backend's first line, without its source location ('[.../pair.cc:561] ...') and advice."""
    text = (str(error).strip().splitlines() or [type(error).__name__])[0]
    text = text.split("] ", 1)[1] if text.startswith("[") and "] " in text else text
    return text.split(". ", 1)[0].rstrip(".")


@contextmanager
def _stdout_to_stderr():
    """What is written to file descriptor 1 meanwhile goes to 2: gloo in torch 2.8 prints which peers a rank
    joined on stdout, where --json writes the record (it was no JSON then)."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
        os.dup2(2, 1)
    except OSError:  # no descriptor 1 or 2 (a daemon's): nothing to keep apart
        saved = None
    try:
        yield
    finally:
        if saved is not None:
            os.dup2(saved, 1)
            os.close(saved)


def said_elsewhere(error: VPRBenchError) -> bool:
    """Under torchrun, whether another rank says `error`: rank 0 when the ranks exchanged it (`Ranks.said_once`,
    `refuse_torchrun`), else, for an error met before the ranks joined (bad input: the same command read on the
    same files by every rank of a node, e.g. --k 0 or a missing image), the node's first rank."""
    said = getattr(error, "said", None)
    return not_first_of_node() if said is None else said


def not_first_of_node() -> bool:
    """Under torchrun, whether this process is a rank other than its node's first (which says what every
    rank meets alike: an error before the ranks joined, a warning that is not a `ShardWarning`)."""
    local = os.environ.get("LOCAL_RANK", "0").strip()
    return torchrun_rank() is not None and local.isdigit() and int(local) != 0


def torchrun_rank() -> str | None:
    """This process's rank as torchrun names it, when it started several (None for one process)."""
    world, rank = os.environ.get("WORLD_SIZE", "1").strip(), os.environ.get("RANK", "").strip()
    return rank if world.isdigit() and int(world) > 1 and rank.isdigit() else None


def refuse_torchrun(command: str) -> None:
    """Plans' cells are shared by plain processes (claims on the cache); torchrun shards one evaluation.
    Under torchrun each rank would run cells of its own, each printing a table: refused, saying both ways."""
    if _whole_from_environment("WORLD_SIZE", "1") > 1:
        error = VPRBenchError(f"'vprbench {command}' runs under torchrun as independent copies, not sharded: start it "
                              "without torchrun (several plain processes on one --cache-dir share the cells), or "
                              "torchrun one 'vprbench evaluate' at a time.")
        error.said = _whole_from_environment("RANK", "0") != 0  # every rank meets it alike: rank 0 says it
        raise error
