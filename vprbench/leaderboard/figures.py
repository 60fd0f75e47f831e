"""The leaderboard's figures (matplotlib, written next to the pages): Recall@K and
precision-recall curves, the per-domain radar, the efficiency plot, retrieval mosaics and
the PCA map of GeM descriptors. A figure that cannot be drawn raises Skipped with the reason,
which the page prints in its place."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from .cells import STRUCTURED, UNSTRUCTURED, Board, Cell
from ..evaluation.metrics import successes

DOMAIN_COLOURS = {"indoor": "#1f77b4", "urban": "#ff7f0e", "outdoor": "#2ca02c", "aerial": "#d62728",
                  "subt": "#9467bd", "degraded": "#8c564b", "underwater": "#17becf"}
#: the paper rows drawn on the radar beside ours: the paper's headline method
RADAR_PAPER_ROWS = ("AnyLoc-VLAD-DINOv2",)


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


def recall_curves(cells: list[Cell], path: Path) -> Path:
    """Recall@K for K = 1 .. the search depth, one line per run (from its per-query ranks)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    drawn = 0
    for cell in cells:
        if cell.arrays is not None:
            first, depth = cell.arrays["first_positive_rank"], cell.record["per_query"]["k"]
            ks = np.arange(1, depth + 1)
            ax.plot(ks, [100 * successes(first, k).mean() for k in ks], marker=".", label=cell.row.name)
        else:
            points = sorted((int(k), v) for k, v in cell.record["recall"].items())
            ax.plot(*zip(*points), marker="o", linestyle="--", label=f"{cell.row.name} (recorded K only)")
        drawn += 1
    if not drawn:
        plt.close(fig)
        raise Skipped("no run to draw")
    ax.set(xlabel="K", ylabel="Recall@K (%)", ylim=(0, 101), xscale="log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    return _save(fig, path)


def pr_curves(cells: list[Cell], path: Path) -> Path:
    """VPR-Bench's precision-recall curve of the top-1 matches ranked by similarity, per run."""
    from sklearn.metrics import precision_recall_curve

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    drawn = 0
    for cell in cells:
        if cell.arrays is None:
            continue
        correct = cell.arrays["first_positive_rank"] == 1
        if not correct.any():
            continue
        precision, recall, _ = precision_recall_curve(correct, cell.arrays["similarities"][:, 0])
        ax.plot(recall, precision, label=f"{cell.row.name} (AUC {cell.record.get('auc_pr', float('nan')):.2f})")
        drawn += 1
    if not drawn:
        plt.close(fig)
        raise Skipped("no run with per-query data and a correct top-1 match")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.01))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    return _save(fig, path)


def efficiency(cells: list[Cell], path: Path) -> Path:
    """R@1 against descriptor bytes and against images described per second."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(7.5, 3.2), sharey=True)
    speeds = 0
    for cell in cells:
        r1 = cell.recall(1)
        size = cell.record.get("descriptor_bytes") or 4 * int(cell.record.get("descriptor_dim") or 0)
        left.scatter([size], [r1])
        left.annotate(cell.row.label, (size, r1), fontsize=7, xytext=(3, 3), textcoords="offset points")
        speed = cell.images_per_second  # from a run that computed its descriptors
        if speed:
            right.scatter([speed], [r1])
            right.annotate(cell.row.label, (speed, r1), fontsize=7, xytext=(3, 3), textcoords="offset points")
            speeds += 1
    left.set(xscale="log", xlabel="descriptor size (bytes, float32)", ylabel="R@1 (%)", ylim=(0, 101))
    right.set(xscale="log", xlabel="images described per second (this run's machine)")
    if not speeds:
        right.text(0.5, 0.5, "no run computed its descriptors\n(all served from the store)", ha="center",
                   va="center", transform=right.transAxes, fontsize=8)
    for ax in (left, right):
        ax.grid(alpha=0.3)
        _decades(ax)
    return _save(fig, path)


def _decades(ax) -> None:
    """Log axis with a decade of room around the points and plain labels at powers of ten."""
    from matplotlib.ticker import LogLocator, NullFormatter

    low, high = ax.dataLim.intervalx
    if np.isfinite([low, high]).all() and low > 0:
        ax.set_xlim(10 ** np.floor(np.log10(low) - 0.3), 10 ** np.ceil(np.log10(high) + 0.3))
    ax.xaxis.set_major_locator(LogLocator(base=10))
    ax.xaxis.set_minor_formatter(NullFormatter())


def domain_averages(board: Board) -> dict[str, dict[str, float]]:
    """Measured official rows: average R@1 per domain over the benchmarks measured in it."""
    found: dict[str, dict[str, list[float]]] = {}
    for row in board.rows:
        if not row.official:
            continue
        for column in board.columns:
            cell = board.cell(row, column)
            if cell and column.kind == "benchmark" and column.default and cell.recall(1) is not None:
                found.setdefault(row.label, {}).setdefault(column.domain, []).append(cell.recall(1))
    return {label: {d: float(np.mean(v)) for d, v in domains.items()} for label, domains in found.items()}


def paper_domain_averages() -> dict[str, dict[str, float]]:
    from ..datasets import dataset_manifests
    from .tables import reported

    domains = {name: m.domain for name, m in dataset_manifests().items()}
    frame = reported()
    frame = frame[frame["metric"] == "r1"].assign(domain=lambda f: f["column"].map(domains))
    return {row: part.groupby("domain")["value"].mean().to_dict() for row, part in frame.groupby("row", sort=False)}


#: the paper's names for domains whose short names are not words
DOMAIN_LABELS = {"subt": "Subterranean"}


def radar(board: Board, path: Path) -> Path:
    """Average R@1 per domain (AnyLoc Fig. 1, right): measured rows solid, the paper's dashed."""
    plt = _pyplot()
    measured = domain_averages(board)
    if not measured:
        raise Skipped("no official run on a benchmark yet")
    paper = paper_domain_averages()
    shown_paper = {f"{r} (paper, reported)": paper[r] for r in RADAR_PAPER_ROWS if r in paper}
    domains = [d for d in STRUCTURED + UNSTRUCTURED
               if any(d in v for v in [*measured.values(), *shown_paper.values()])]
    angles = np.linspace(0, 2 * np.pi, len(domains), endpoint=False)
    fig, ax = plt.subplots(figsize=(5.2, 5.2), subplot_kw={"projection": "polar"})
    for label, values, style in [*((k, v, "-") for k, v in measured.items()),
                                 *((k, v, "--") for k, v in shown_paper.items())]:
        r = np.array([values.get(d, np.nan) for d in domains])
        closed = np.append(r, r[0]), np.append(angles, angles[0])
        ax.plot(closed[1], closed[0], style, marker="o", label=label)
    ax.set_xticks(angles, [DOMAIN_LABELS.get(d, d.capitalize()) for d in domains])
    ax.tick_params(axis="x", pad=8)  # keep the labels off the outer ring
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, frameon=False)
    ax.set_title("Average R@1 (%) per domain\n(no point where a row was not measured)", fontsize=8)
    return _save(fig, path)


def _dataset_of(record: dict, data_dir=None):
    """The run's dataset loaded again, or Skipped when its images are gone or are not the run's."""
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
    return dataset


def mosaic(cell: Cell, path: Path, *, data_dir=None, seed: int = 0, queries: int = 4, top: int = 5) -> Path:
    """Seeded queries and their top matches: a green frame is a positive, a red one is not."""
    from ..images import load_image

    if cell.arrays is None:
        raise Skipped("the run has no per-query predictions")
    dataset = _dataset_of(cell.record, data_dir)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(len(dataset.queries), size=min(queries, len(dataset.queries)), replace=False))
    top = min(top, cell.arrays["database_indices"].shape[1])
    plt = _pyplot()
    fig, axes = plt.subplots(len(chosen), top + 1, figsize=(1.6 * (top + 1), 1.35 * len(chosen)), squeeze=False)
    try:
        for row, q in zip(axes, chosen):
            shown = [(dataset.queries[q], f"query {q}", "black")]
            for rank, d in enumerate(cell.arrays["database_indices"][q, :top], 1):
                right = int(d) in set(dataset.positives[q].tolist())
                shown.append((dataset.database[d], f"#{rank} db {d}", "#1a9e3a" if right else "#d62728"))
            for ax, (image_path, title, colour) in zip(row, shown):
                image = load_image(image_path)
                image.thumbnail((200, 150))
                ax.imshow(image)
                ax.set_title(title, fontsize=7)
                ax.set_xticks([]), ax.set_yticks([])
                for spine in ax.spines.values():
                    spine.set(edgecolor=colour, linewidth=3)
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
    for domain in sorted({d for d, _ in labels}):
        mask = np.array([d == domain for d, _ in labels])
        names = sorted({n for d, n in labels if d == domain})
        ax.scatter(*projected[mask].T, s=6, alpha=0.6, color=DOMAIN_COLOURS.get(domain),
                   label=f"{domain} ({', '.join(names)})")
    weights = ((record.get("provenance") or {}).get("weights") or {}).get("source", "undeclared")
    ax.set(xlabel="PC 1", ylabel="PC 2", title=f"{record['method']} GeM descriptors (weights: {weights})")
    ax.legend(fontsize=7)
    return _save(fig, path)
