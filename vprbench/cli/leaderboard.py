"""vprbench leaderboard [show] / publish --to DIR / compare A B --dataset D."""
from __future__ import annotations


from ..errors import VPRBenchError
from .console import console, say
from .options import check_new_folder, path_argument, resolve_locations

FORMATS = ("table", "markdown", "csv", "json")

def add_parsers(commands) -> None:
    p = commands.add_parser("leaderboard", help="leaderboard of all evaluations: show, publish to the docs, compare two methods")
    p.add_argument("action", nargs="?", choices=("show", "publish", "compare"), default="show")
    p.add_argument("methods", nargs="*", metavar="METHOD", help="with 'compare': the two method rows to compare")
    p.add_argument("--format", choices=FORMATS,
                   help="with 'show': how the table is printed (default table; csv and json for other tools)")
    p.add_argument("--to", type=path_argument, help="with 'publish': the docs folder; the section goes to <folder>/leaderboard/")
    p.add_argument("--dataset", help="with 'compare': the dataset both were run on")
    p.add_argument("--k", type=int, help="with 'compare': the K of Recall@K compared (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default 0)")
    p.add_argument("--track", choices=("single-image", "re-ranked", "sequence"),
                   help="with 'show': which track's table (default single-image; each track is a table of its own)")
    p.add_argument("--cache-dir", help="where the results store lives")
    p.add_argument("--results", type=path_argument, metavar="DIR",
                   help="a results repository (vprbench results import --into DIR) whose runs join this cache's, "
                        "each cell marked as the site marks it (a run in both counts once, as this machine's): "
                        "'show' and 'compare' preview what 'publish --results DIR' publishes")
    p.add_argument("--data-dir", help="where the datasets are: their ground truth re-scores every cell's run (and "
                                      "'publish' draws its retrieval mosaics from their images)")
    p.set_defaults(run=run)


def run(args) -> int:
    from rich.table import Table

    from ..bundles.repository import no_runs, read_runs
    from ..leaderboard import build_board, grid, publish, render
    from ..leaderboard.stats import check_k_and_seed
    from ..leaderboard.tables import marks_legend
    from ..leaderboard.truth import LocalTruth, truth_note

    resolve_locations(args)
    for flag, value, action in (("--to", args.to, "publish"), ("--dataset", args.dataset, "compare"),
                                ("--k", args.k, "compare"), ("--format", args.format, "show"),
                                ("--track", args.track, "show")):
        if value is not None and args.action != action:  # ignored, it would let a user think it took effect
            raise VPRBenchError(f"{flag} is for 'leaderboard {action}'; 'leaderboard {args.action}' does not use it: "
                                "drop it.")
    args.format, args.track = args.format or "table", args.track or "single-image"
    args.k, args.seed = check_k_and_seed(1 if args.k is None else args.k, args.seed)  # before any record is read
    if args.action == "publish":
        if args.to is None:
            raise VPRBenchError("leaderboard publish needs --to FOLDER (e.g. --to docs/)")
        check_new_folder(args.to, "--to")
        skipped: list = []
        refused: list = []
        say(f"Wrote {publish(args.to, args.cache_dir, data_dir=args.data_dir, seed=args.seed, skipped=skipped, results=args.results, refused=refused)}")
        return unread(skipped, refused)
    skipped, refused = [], []
    records = read_runs(args.cache_dir, args.results, skipped)  # the very runs 'publish --results DIR' would use
    if not records:
        raise VPRBenchError(no_runs(args.cache_dir))
    board = build_board(records, LocalTruth(args.data_dir, args.cache_dir), refused)
    if args.action == "compare":
        from ..leaderboard.compare import compare, describe

        if len(args.methods) != 2 or not args.dataset:
            raise VPRBenchError("leaderboard compare needs two methods and a dataset: "
                                "vprbench leaderboard compare A B --dataset D")
        say(describe(compare(board, *args.methods, args.dataset, k=args.k, seed=args.seed)))
        return unread(skipped, refused)
    if args.methods:
        raise VPRBenchError(f"'leaderboard {args.action}' takes no method names (got {' '.join(args.methods)}); "
                            "did you mean 'leaderboard compare A B --dataset D'?")
    everything, board = board, board.of_track(args.track)
    if not board.cells and everything.cells and not board.excluded:
        raise VPRBenchError(f"No run in the {args.track} track yet; the stored runs are in: {', '.join(everything.tracks)} "
                            "(--track).")
    if not board.cells:
        runs = f"No run in the {args.track} track" if everything.cells else f"None of the {len(records)} stored run(s)"
        raise VPRBenchError(f"{runs} can fill a cell: " + "; ".join(sum(named_left_out(board.excluded), []))
                            if board.excluded else no_runs(args.cache_dir))
    table = grid(board)
    sources = [cell.source for cell in board.cells.values()]
    if args.format != "table":
        # Markdown for a page: the legend of its marks below it, as on the site (CSV and JSON stay data)
        legend = marks_legend(sources, "markdown") if args.format == "markdown" else ""
        say(render(table, args.format, board) + (f"\n\nMarks:{legend}" if legend else ""))
        return unread(skipped, refused)
    view = Table(title=f"R@1 / R@5 (%), {args.track} track: one run per cell")
    view.add_column("method")
    for column in table.columns:
        view.add_column(str(column), justify="left" if column in ("weights", "licence") else "right")
    for method, row in table.iterrows():
        view.add_row(str(method), *[str(v) for v in row.tolist()])
    out = console()
    out.print(view)
    if legend := marks_legend(sources, "terminal"):
        out.print(f"Marks:{legend}", highlight=False, soft_wrap=True)
    if board.excluded:
        out.print(left_out_lines(board.excluded), highlight=False)
    if note := truth_note(board):
        out.print(note, highlight=False, soft_wrap=True)
    return unread(skipped, refused)


#: left-out runs named one by one on the terminal; the rest are counted (the site lists them all)
NAMED = 5


def named_left_out(excluded: list) -> tuple[list[str], list[str]]:
    """The runs left out of every cell as the site's "Runs left out" names them, the first NAMED of
    them: run id (its time first), row label, dataset and why; then how many more. The console
    writes control characters out."""
    from ..leaderboard.shown import left_out

    named = [f"run {run}, {label} on {dataset}: {why}"
             for (run, label, dataset), why in ((left_out(record), why) for record, why in excluded[:NAMED])]
    more = len(excluded) - NAMED
    return named, ([f"and {more} more (all under \"Runs left out\" in 'vprbench leaderboard publish')."]
                   if more > 0 else [])


def left_out_lines(excluded: list) -> str:
    named, more = named_left_out(excluded)
    return "\n".join([f"{len(excluded)} run(s) left out of every cell:", *(f"- {line}" for line in named), *more])


def unread(skipped: list, refused: list = ()) -> int:
    """Exit 1 when stored files could not be read, or hold runs that do not re-score to their numbers
    against the ground truth (each named in a warning above); they are kept."""
    if refused:
        console(stderr=True).print(f"error: {len(refused)} run(s) do not re-score to their numbers against the ground "
                                   "truth (named above) and fill no cell; nothing was deleted. Check them with "
                                   "'vprbench results verify', or rerun those evaluations.", highlight=False, soft_wrap=True)
    if not skipped:
        return 1 if refused else 0
    console(stderr=True).print(f"error: {len(skipped)} stored file(s) could not be read (named above) and are left out; "
                               "nothing was deleted. Fix or move them, or rerun those evaluations.", highlight=False,
                               soft_wrap=True)  # one line, however narrow the terminal
    return 1
