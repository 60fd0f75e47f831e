"""vprbench run PLAN.toml: a plan's cells, each a run spec, shared by the processes on one cache."""
from __future__ import annotations

from .console import console
from ..errors import DESCRIBED
from .options import (add_location_options, add_method_flags, add_run_options, add_spec_options, add_sweep_options,
                      explicit_run_options, method_options, path_argument, progress, refuse_unused,
                      resolve_locations, run_settings, spec_overrides)


def add_parsers(commands) -> None:
    p = commands.add_parser("run", help="run a plan: methods x datasets (protocols) x K; several processes share the cells")
    p.add_argument("plan", type=path_argument, help="plan file (TOML; see docs/sweeps.md)")
    add_method_flags(p)
    add_spec_options(p)
    add_run_options(p)
    add_sweep_options(p)
    add_location_options(p)
    p.set_defaults(run=run_plan, kept=DESCRIBED)


def run_plan(args) -> int:
    from ..datasets import is_path
    from ..distributed import refuse_torchrun
    from ..sweep import run_cells
    from ..sweep.plan import read_entries

    refuse_torchrun("run")
    overrides = {**spec_overrides(args), "options": {**method_options(args), **explicit_run_options(args)}}
    entries = read_entries(args.plan, overrides=overrides)
    if all(is_path(name) for _, name, _ in entries.datasets):  # folders of your own are read where they are
        refuse_unused(args, "data_dir", "when every dataset of the plan is a folder of your own")
    resolve_locations(args)
    settings = run_settings(args)
    plan = entries.plan(settings.data_dir, settings.cache_dir)
    return report(plan.name, run_cells(plan.cells, settings, lease_s=args.lease, plan=plan.name, progress=progress(args)))


def report(title: str, outcomes) -> int:
    from ..sweep import summary_table
    from ..sweep.runner import FAILED

    console().print(summary_table(outcomes, title))
    return 1 if any(o.status == FAILED for o in outcomes) else 0
