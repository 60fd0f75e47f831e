"""How a run goes, never what it computes: the device, the batch size, loader workers, the search's
memory budget, the lock timeout, and where the data and cache are. They are in no hash and no
label; `vprbench.spec` holds what a run is."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from .errors import VPRBenchError, require

#: options that change how a run goes, never what it computes: in no hash, no label
RUN_SETTINGS = ("device", "batch_size", "workers", "memory_budget", "lock_timeout")
#: the most loader processes: each is a copy of this one (a typo's 10**20 forked one per batch)
MAX_WORKERS = 1024


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """How a run goes, not what it computes; also where its data and cache are. Library code
    gets both folders from here (None: the user cache, the default data root), never from the
    environment. The batch size and device are checked, with the method's name, when the method is
    created (or, for a method given already built, when the run starts)."""

    cache_dir: Path | None = None
    data_dir: Path | None = None
    device: str = "auto"
    batch_size: int | None = None
    workers: int | None = None
    memory_budget: int | str | None = None
    lock_timeout: float | None = None
    #: fetch a missing dataset: None = only into the default data root
    download: bool | None = None
    strict: bool = False
    #: an exported candidates file a re-ranking run starts from instead of searching (vprbench candidates export)
    candidates: Path | None = None

    def __post_init__(self):
        from .methods.checks import flag, number, whole
        from .paths import folder_path
        from .row_sources import parse_memory

        for name in ("cache_dir", "data_dir"):
            object.__setattr__(self, name, folder_path(getattr(self, name), name))
        if self.candidates is not None:
            require(self.candidates, (str, os.PathLike), "candidates takes the path of an exported candidates file")
            object.__setattr__(self, "candidates", Path(self.candidates).expanduser())
        object.__setattr__(self, "download", flag("run", "download", self.download, "only into the default data root"))
        object.__setattr__(self, "strict", flag("run", "strict", self.strict))
        if self.workers is not None:
            object.__setattr__(self, "workers", whole("run", "workers", self.workers, 0, MAX_WORKERS, "loader processes"))
        if self.memory_budget is not None:
            object.__setattr__(self, "memory_budget", parse_memory(self.memory_budget, "--search-memory (memory_budget)"))
        if self.lock_timeout is not None:
            try:
                timeout = number("run", "lock_timeout", self.lock_timeout, minimum=0)
            except VPRBenchError:
                raise VPRBenchError(f"--lock-timeout (lock_timeout) takes a finite number of seconds >= 0, the longest "
                                    f"to wait for another run's lock; got {self.lock_timeout!r}.") from None
            object.__setattr__(self, "lock_timeout", timeout)

    def with_options(self, options: dict) -> "RunSettings":
        """These settings with the run settings found among a method's options (a plan entry's
        `batch_size = 4`) taking their place."""
        found = split_run_settings(options)[1]
        return dataclasses.replace(self, **found) if found else self

    def describe(self) -> dict:
        """For the record: how the run went (never part of its identity)."""
        return {"device": self.device, "batch_size": self.batch_size, "workers": self.workers,
                "memory_budget": self.memory_budget, "lock_timeout": self.lock_timeout, "download": self.download,
                "strict": self.strict, **({"candidates": str(self.candidates)} if self.candidates else {})}


def split_run_settings(options: dict) -> tuple[dict, dict]:
    """(the method options, the run settings given among them): a plan entry's or the command
    line's `batch_size = 4` goes to `RunSettings`, not to the spec."""
    options = options or {}
    require(options, dict, "run settings come from a dict of option name -> value, e.g. {'batch_size': 4}")
    return ({k: v for k, v in options.items() if k not in RUN_SETTINGS},
            {k: v for k, v in options.items() if k in RUN_SETTINGS and v is not None})
