"""vprbench run PLAN.toml, and the matrix form of vprbench evaluate (several methods/datasets)."""
from __future__ import annotations

from ..sweep import build_plan, read_plan, run_cells, summary_table
from ..sweep.runner import FAILED
from .console import console
from .options import add_location_options, apply_locations

DEFAULT_LEASE_S = 120.0


def add_sweep_options(parser) -> None:
    parser.add_argument("--lease", type=float, default=DEFAULT_LEASE_S, metavar="SECONDS",
                        help="a claim without heartbeat for this long belonged to a dead process and is taken over "
                             f"(default {DEFAULT_LEASE_S:g})")


def add_parsers(commands) -> None:
    p = commands.add_parser("run", help="run a plan: methods x datasets (protocols) x K; several processes share the cells")
    p.add_argument("plan", help="plan file (TOML; see docs/sweeps.md)")
    p.add_argument("--device", help="torch device for every method that takes one (e.g. cuda:1)")
    p.add_argument("--strict", action="store_true", help="fail cells whose image counts differ from the manifest")
    add_sweep_options(p)
    add_location_options(p)
    p.set_defaults(run=run_plan)


def run_plan(args) -> int:
    apply_locations(args)
    plan = read_plan(args.plan, device=args.device)  # every problem listed before anything runs
    return report(plan.name, run_cells(plan.cells, data_dir=args.data_dir, cache_dir=args.cache_dir, strict=args.strict,
                                       lease_s=args.lease, plan=plan.name))


def run_matrix(args, options: dict) -> int:
    """`vprbench evaluate --method A B --dataset X Y [--protocol P]`: the same, from the command line."""
    options = dict(options)
    device = options.pop("device", None)  # given only to methods that take one
    data = {"methods": [{"name": m, "options": {k: v for k, v in options.items() if v is not None}} for m in args.method],
            "datasets": [{"name": d, **({"protocol": args.protocol} if args.protocol else {})} for d in args.dataset]}
    if args.k:
        from .options import parse_ks

        data["k"] = list(parse_ks(args.k))
    plan = build_plan(data, "the command line", device=device)
    return report("evaluate", run_cells(plan.cells, data_dir=args.data_dir, cache_dir=args.cache_dir, strict=args.strict,
                                        lease_s=args.lease, plan="evaluate"))


def report(title: str, outcomes) -> int:
    console().print(summary_table(outcomes, title))
    return 1 if any(o.status == FAILED for o in outcomes) else 0
