"""The leaderboard's figures (matplotlib, written next to the pages): Recall@K and
precision-recall curves, the per-domain radar, the efficiency plot, retrieval mosaics and
the PCA map of GeM descriptors. A figure that cannot be drawn raises Skipped with the reason,
which the page prints in its place."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from .cells import STRUCTURED, UNSTRUCTURED, Board, Cell
from .domains import DomainMean, domain_averages, domain_datasets, paper_domain_averages
from .escape import public
from .shown import descriptor_bytes
from ..evaluation.metrics import recall_at_k
from ..hashing import canonical_hash
from ..text import literal

DOMAIN_COLOURS = {"indoor": "#1f77b4", "urban": "#ff7f0e", "outdoor": "#2ca02c", "aerial": "#d62728",
                  "subt": "#9467bd", "degraded": "#8c564b", "underwater": "#17becf"}
#: the paper rows drawn on the radar beside ours: the paper's headline method
RADAR_PAPER_ROWS = ("AnyLoc-VLAD-DINOv2",)


#: method colours: tab10, then the lighter halves of tab20 (distinct before they are similar)
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#c7c7c7",
           "#dbdb8d", "#9edae5")


def method_colours(names) -> dict[str, str]:
    """One colour per method name for every figure of a site: each name's hash picks its palette
    slot, a taken slot passes to the next free one (names placed in sorted order, so the same set
    of methods always gets the same colours). Up to ten methods use only the strong first ten
    colours; past twenty, colours repeat."""
    names = sorted(set(names))
    size = 10 if len(names) <= 10 else len(PALETTE)
    taken: set[int] = set()
    found = {}
    for name in names:
        slot = int(canonical_hash(name), 16) % size
        free = [(slot + step) % size for step in range(size) if (slot + step) % size not in taken]
        slot = free[0] if free else slot
        taken.add(slot)
        found[name] = PALETTE[slot]
    return found


def _colours(colours, names) -> dict[str, str]:
    return colours if colours is not None else method_colours(names)


#: the longest name a figure's legend or title shows whole
LABEL_CHARS = 100


def _label(value: str) -> str:
    """A name as literal matplotlib text (a '$' from data would start mathtext), without absolute
    paths (escape.public), control characters written out (one is no XML: the SVG would not open),
    at most LABEL_CHARS long: a longer one keeps its start and end (a legend as wide as a 300-character
    name hid the plot; the page beside the figure gives it whole)."""
    shown = literal(public(value))
    if len(shown) > LABEL_CHARS:
        shown = f"{shown[:LABEL_CHARS * 2 // 3]}…{shown[-(LABEL_CHARS // 3 - 1):]}"
    return shown.replace("$", r"\$")


def _legend(where, artists: list, **options) -> None:
    """A legend of exactly `artists`, each under its label: matplotlib leaves out of a legend it
    gathers itself every label that starts with '_' (a method named '_x_' had no entry)."""
    where.legend(artists, [a.get_label() for a in artists], **options)


class Skipped(Exception):
    """A figure that cannot be drawn; the message says why (shown on the page)."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"svg.hashsalt": "vprbench", "svg.fonttype": "path", "font.size": 9})
    return plt


def _save(fig, path: Path, dpi: int = 110) -> Path:
    metadata = {"Date": None} if path.suffix == ".svg" else {}
    fig.savefig(path, bbox_inches="tight", metadata=metadata, dpi=dpi)
    _pyplot().close(fig)
    return path


def recall_curves(cells: list[Cell], path: Path, colours: dict[str, str] | None = None) -> Path:
    """Recall@K for K = 1 .. the search depth, one line per run (from its per-query ranks)."""
    colours = _colours(colours, [c.row.name for c in cells])
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    drawn = []
    for cell in cells:
        if cell.arrays is not None:
            first, depth = cell.arrays["first_positive_rank"], cell.record["per_query"]["k"]
            ks = np.arange(1, depth + 1)
            drawn += ax.plot(ks, list(recall_at_k(first, ks).values()), marker=".",
                             label=_label(cell.row.name), color=colours[cell.row.name])
        else:
            points = sorted((int(k), v) for k, v in cell.record["recall"].items())
            drawn += ax.plot(*zip(*points), marker="o", linestyle="--",
                             label=_label(f"{cell.row.name} (recorded K only)"), color=colours[cell.row.name])
    if not drawn:
        plt.close(fig)
        raise Skipped("no run to draw")
    ax.set(xlabel="K", ylabel="Recall@K (%)", ylim=(0, 101), xscale="log")
    ax.grid(alpha=0.3)
    _legend(ax, drawn, fontsize=7, loc="lower right")
    return _save(fig, path)


def pr_curves(cells: list[Cell], path: Path, colours: dict[str, str] | None = None) -> Path:
    """VPR-Bench's precision-recall curve of the top-1 matches ranked by similarity, per run."""
    from sklearn.metrics import precision_recall_curve

    colours = _colours(colours, [c.row.name for c in cells])
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    drawn = []
    for cell in cells:
        if cell.arrays is None:
            continue
        correct = cell.arrays["first_positive_rank"] == 1
        if not correct.any():
            continue
        precision, recall, _ = precision_recall_curve(correct, cell.arrays["similarities"][:, 0])
        drawn += ax.plot(recall, precision, color=colours[cell.row.name],  # AUC as the page gives it
                         label=_label(f"{cell.row.name} (AUC {cell.record.get('auc_pr', float('nan')):.3f})"))
    if not drawn:
        plt.close(fig)
        raise Skipped("no run with per-query data and a correct top-1 match")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.01))
    ax.grid(alpha=0.3)
    _legend(ax, drawn, fontsize=7, loc="lower left")
    return _save(fig, path)


def efficiency(cells: list[Cell], path: Path, colours: dict[str, str] | None = None) -> Path:
    """R@1 against descriptor bytes and against images described per second."""
    colours = _colours(colours, [c.row.name for c in cells])
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(7.5, 3.2), sharey=True)
    speeds, points = 0, []
    for cell in cells:
        r1 = cell.recall(1)
        size = descriptor_bytes(cell.record) or 0
        colour = colours[cell.row.name]
        points.append(left.scatter([size], [r1], color=colour, label=_label(cell.row.name)))
        speed = cell.images_per_second  # from a run that computed its descriptors
        if speed:
            right.scatter([speed], [r1], color=colour)
            speeds += 1
    left.set(xscale="log", xlabel="descriptor size (bytes as stored)", ylabel="R@1 (%)", ylim=(0, 101))
    right.set(xscale="log", xlabel="images described per second (this run's machine)")
    if not speeds:
        right.text(0.5, 0.5, "no run computed its descriptors\n(all served from the store)", ha="center",
                   va="center", transform=right.transAxes, fontsize=8)
    for ax in (left, right):
        ax.grid(alpha=0.3)
        _decades(ax)
    _legend(fig, points, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2, frameon=False)
    return _save(fig, path)


def _decades(ax) -> None:
    """Log axis with a decade of room around the points and plain labels at powers of ten."""
    from matplotlib.ticker import LogLocator, NullFormatter

    low, high = ax.dataLim.intervalx
    if np.isfinite([low, high]).all() and low > 0:
        ax.set_xlim(10 ** np.floor(np.log10(low) - 0.3), 10 ** np.ceil(np.log10(high) + 0.3))
    ax.xaxis.set_major_locator(LogLocator(base=10))
    ax.xaxis.set_minor_formatter(NullFormatter())


#: the paper's names for domains whose short names are not words
DOMAIN_LABELS = {"subt": "Subterranean"}


def paper_key(row: str) -> str:
    """A paper row's name on the figures (and in the colour map)."""
    return f"{row} (paper, reported)"


def _radar_series(board: Board, axes) -> list[tuple[str, dict[str, DomainMean], str]]:
    """(name, means, line style) of every row on the radar: measured official rows, the paper's shown."""
    paper = paper_domain_averages(axes)
    return [*((name, means, "-") for name, means in domain_averages(board, axes).items()),
            *((paper_key(r), paper[r], "--") for r in RADAR_PAPER_ROWS if r in paper)]


def radar_domains(board: Board, axes: dict[str, list[str]]) -> list[str]:
    """The radar's axes, in the paper's order: every domain some row on it has a dataset of."""
    series = _radar_series(board, axes)
    return [d for d in STRUCTURED + UNSTRUCTURED if any(d in means for _, means, _ in series)]


def radar(board: Board, path: Path, colours: dict[str, str] | None = None) -> Path:
    """Average R@1 per domain (AnyLoc Fig. 1, right): measured rows solid, the paper's dashed. A
    point is filled only where the row has every dataset of that axis; a row with some of them
    gets a hollow point, with the datasets it averages written beside it, and no line through it."""
    plt = _pyplot()
    axes = domain_datasets()
    if not domain_averages(board, axes):
        raise Skipped("no official run on a benchmark yet")
    series = _radar_series(board, axes)
    colours = _colours(colours, [name for name, _, _ in series])
    domains = radar_domains(board, axes)
    angles = np.linspace(0, 2 * np.pi, len(domains), endpoint=False)
    fig, ax = plt.subplots(figsize=(5.6, 5.6), subplot_kw={"projection": "polar"})
    notes: dict[str, int] = {}  # partial points already written beside each axis: stack the next below
    lines = []
    for name, means, style in series:
        colour = colours[name]
        full = np.array([means[d].value if d in means and means[d].complete else np.nan for d in domains])
        lines += ax.plot(np.append(angles, angles[0]), np.append(full, full[0]), style, marker="o", color=colour,
                         label=_label(name))
        for angle, domain in zip(angles, domains):
            part = means.get(domain)
            if part is not None and not part.complete:
                ax.scatter([angle], [part.value], s=55, facecolors="white", edgecolors=colour, linewidths=2, zorder=3)
                shown = ", ".join(part.datasets) if len(part.datasets) <= 2 else f"{len(part.datasets)} datasets"
                below = notes[domain] = notes.get(domain, -1) + 1
                ax.annotate(_label(f"{shown} only"), (angle, part.value), fontsize=7.5, color=colour, weight="bold",
                            xytext=(-7, -12 - 11 * below), textcoords="offset points", ha="right", zorder=4,
                            bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.8})
    ax.set_xticks(angles, [f"{DOMAIN_LABELS.get(d, d.capitalize())}\n({len(axes[d])} dataset{'s' * (len(axes[d]) > 1)})"
                           for d in domains])
    ax.tick_params(axis="x", pad=10)  # keep the labels off the outer ring
    ax.set_ylim(0, 100)
    _legend(ax, lines, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
    ax.set_title("Average R@1 (%) per domain\nfilled: over every dataset of the axis; hollow: only the datasets named",
                 fontsize=8)
    return _save(fig, path)


def _dataset_of(record: dict, data_dir=None, cache_dir=None):
    """The run's dataset loaded again, or Skipped when its images are gone or are not the run's:
    the same counts and positives, and the same content (the record's dataset fingerprint: every
    image's name and sha256, and the ground truth)."""
    from ..datasets import apply_protocol, dataset_manifest, find_protocol, load_dataset
    from ..datasets.layouts import read_layout
    from ..datasets.layouts.own_data import own_manifest

    root = Path(record["dataset_root"]) if record.get("dataset_root") else None
    protocol = (record.get("protocol") or {}).get("name")
    try:
        if root is not None and root.is_dir() and record.get("dataset_kind") == "own":
            dataset = read_layout(root, own_manifest(root))
        elif root is not None and root.is_dir():
            manifest = dataset_manifest(record["dataset"])
            dataset = apply_protocol(read_layout(root, manifest), find_protocol(manifest, protocol))
        elif record.get("dataset_kind") == "benchmark":
            dataset = load_dataset(record["dataset"], data_dir, fetch=False, protocol=protocol)
        else:
            raise Skipped(f"the images of {record['dataset']} are no longer at {root}")
        positives = [len(p) for p in dataset.positives]
    except VPRBenchError as error:
        raise Skipped(f"the images of {record['dataset']} are not on disk here ({error})") from None
    counts = record["counts"]
    expected = (record.get("per_query") or {}).get("positives")
    if (len(dataset.database), len(dataset.queries)) != (counts["database"], counts["queries"]) or \
            (expected is not None and list(expected) != positives):
        raise Skipped(f"the {record['dataset']} found on disk is not the copy this run evaluated")
    try:
        same = dataset.fingerprint(cache_dir) == record.get("dataset_fingerprint")
        images = dataset.images_fingerprint(cache_dir)
    except VPRBenchError as error:
        raise Skipped(f"the images of {record['dataset']} cannot be read here ({error})") from None
    if not same:
        recorded = (record.get("dataset_fingerprints") or {}).get("images")
        changed = [split for split in ("database", "queries") if recorded and images.get(split) != recorded.get(split)]
        what = f"the {' and '.join(changed)} images" if changed or not recorded else "the images or ground truth"
        raise Skipped(f"{what} of {record['dataset']} at {dataset.root} differ from the ones this run evaluated "
                      "(by content: names and sha256)")
    return dataset


def _run_image(dataset, split: str, index: int, cache_dir=None):
    """An image of the run, decoded from bytes whose sha256 is the one its dataset fingerprint holds
    (a file replaced after the check is refused, not shown)."""
    from ..images import load_image, reads_seen

    path = getattr(dataset, split)[index]
    with reads_seen() as seen:
        image = load_image(path)
    if seen.get(os.path.abspath(path)) != dataset.image_digests(cache_dir)[split][index]:
        raise Skipped(f"image {path} changed after its content was checked")
    return image


def mosaic(cell: Cell, path: Path, *, data_dir=None, seed: int = 0, queries: int = 4, top: int = 5,
           cache_dir=None) -> Path:
    """Seeded queries and their top matches: a green frame is a positive, a red one is not (nor any match of
    a query whose descriptor was all zero: it matched nothing, its list is the tie rule's). Only images whose
    content is the run's are read (_dataset_of, _run_image)."""
    if cell.arrays is None:
        raise Skipped("the run has no per-query predictions")
    dataset = _dataset_of(cell.record, data_dir, cache_dir)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(len(dataset.queries), size=min(queries, len(dataset.queries)), replace=False))
    top = min(top, cell.arrays["database_indices"].shape[1])
    plt = _pyplot()
    fig, axes = plt.subplots(len(chosen), top + 1, figsize=(1.6 * (top + 1), 1.35 * len(chosen)), squeeze=False)
    try:
        blank = cell.arrays.get("all_zero")
        for row, q in zip(axes, chosen):
            nothing = blank is not None and blank[q] != 0
            shown = [(("queries", int(q)), f"query {q}" + (" (all zero)" if nothing else ""), "black")]
            for rank, d in enumerate(cell.arrays["database_indices"][q, :top], 1):
                right = not nothing and int(d) in set(dataset.positives[q].tolist())
                shown.append((("database", int(d)), f"#{rank} db {d}", "#1a9e3a" if right else "#d62728"))
            for ax, ((split, index), title, colour) in zip(row, shown):
                image = _run_image(dataset, split, index, cache_dir)
                image.thumbnail((200, 150))
                ax.imshow(image)
                ax.set_title(title, fontsize=7)
                ax.set_xticks([]), ax.set_yticks([])
                for spine in ax.spines.values():
                    spine.set(edgecolor=colour, linewidth=3)
    except Skipped:
        plt.close(fig)
        raise
    except VPRBenchError as error:
        plt.close(fig)
        raise Skipped(f"an image of {cell.record['dataset']} is unreadable ({error})") from None
    return _save(fig, path, dpi=80)  # photographs: keep the PNG small


def stored_descriptors(record: dict, split: str = "database", cache_dir=None) -> np.ndarray | None:
    """The run's descriptors from its complete store (vprbench.store.run_store), or None."""
    from ..store import run_store

    store = run_store(record, split, cache_dir)
    return None if store is None else store.read_rows(0, store.row_count)


def pca_map(records: list[dict], path: Path, *, cache_dir=None, seed: int = 0, per_dataset: int = 400) -> Path:
    """Database descriptors of one GeM method on every dataset it was run on, projected on their
    first two principal components and coloured by domain (AnyLoc Fig. 1, middle)."""
    from ..spec import canonical_hash

    gem = [r for r in records if (r.get("method_fingerprint") or {}).get("aggregation") == "gem"]
    by_method: dict[str, dict[str, dict]] = {}
    for record in gem:
        by_method.setdefault(canonical_hash(record["method_fingerprint"]), {})[record["dataset"]] = record
    found = {}
    for key, runs in sorted(by_method.items(), key=lambda kv: -len(kv[1])):
        loaded = {name: (r, d) for name, r in runs.items() if (d := stored_descriptors(r, cache_dir=cache_dir)) is not None}
        if len(loaded) > len(found):
            found = loaded
    if not found:
        raise Skipped("no GeM descriptors in the store (run a GeM method, e.g. anyloc-gem-dinov2, on some datasets)")
    rng = np.random.default_rng(seed)
    parts, labels = [], []
    for name, (record, descriptors) in sorted(found.items()):
        take = rng.choice(len(descriptors), size=min(per_dataset, len(descriptors)), replace=False)
        parts.append(descriptors[np.sort(take)])
        labels += [(record.get("domain") or "other", name)] * len(take)
    points = np.concatenate(parts)
    centred = points - points.mean(axis=0)
    _, _, basis = np.linalg.svd(centred, full_matrices=False)
    projected = centred @ basis[:2].T
    record = next(iter(found.values()))[0]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    points = []
    for domain in sorted({d for d, _ in labels}):
        mask = np.array([d == domain for d, _ in labels])
        names = sorted({n for d, n in labels if d == domain})
        points.append(ax.scatter(*projected[mask].T, s=6, alpha=0.6, color=DOMAIN_COLOURS.get(domain),
                                 label=_label(f"{domain} ({', '.join(names)})")))
    weights = ((record.get("provenance") or {}).get("weights") or {}).get("source", "undeclared")
    ax.set(xlabel="PC 1", ylabel="PC 2", title=_label(f"{record['method']} GeM descriptors (weights: {weights})"))
    _legend(ax, points, fontsize=7)
    return _save(fig, path)
