"""What each figure plots, read back from the drawn figure (not the SVG's colours): the recall curve's
values and depth, the PR curve whose area the page gives, the efficiency plot's bytes and speed, the
radar's filled and dashed lines. Each was a mutant of figures.py no other test noticed."""
import numpy as np
import pytest

from vprbench.evaluation.metrics import successes
from vprbench.leaderboard import build_board, figures


@pytest.fixture
def drawn(monkeypatch):
    """The figures a drawing function saved, kept open to read their data."""
    kept = []
    monkeypatch.setattr(figures, "_save", lambda fig, path, dpi=110: kept.append(fig) or path)
    yield kept
    for fig in kept:
        figures._pyplot().close(fig)


def _one_cell(records):
    [cell] = build_board(records).cells.values()
    return cell


def test_the_recall_curve_is_in_percent_to_the_runs_depth(make_record, tmp_path, drawn):
    cell = _one_cell([make_record(k=20, quality=0.5, seed=1)])
    figures.recall_curves([cell], tmp_path / "r.svg")
    [line] = drawn[0].axes[0].get_lines()
    ks, values = line.get_xdata(), line.get_ydata()
    assert list(ks) == list(range(1, 21))
    first = cell.arrays["first_positive_rank"]
    assert values == pytest.approx([100 * successes(first, k).mean() for k in ks])
    assert (values[0], values[4]) == (pytest.approx(cell.recall(1)), pytest.approx(cell.recall(5)))


def test_the_pr_curve_drawn_is_the_one_whose_area_the_legend_gives(make_record, tmp_path, drawn):
    from sklearn.metrics import auc

    cell = _one_cell([make_record(quality=0.5, seed=2)])
    figures.pr_curves([cell], tmp_path / "pr.svg")
    [line] = drawn[0].axes[0].get_lines()
    recall, precision = line.get_xdata(), line.get_ydata()
    assert auc(recall, precision) == pytest.approx(cell.record["auc_pr"], abs=1e-6)
    assert line.get_label().endswith(f"(AUC {cell.record['auc_pr']:.3f})")
    # at every top-1 match kept, precision is the share of correct ones: R@1
    assert precision[np.argmax(recall)] == pytest.approx(cell.recall(1) / 100)


def test_the_efficiency_plot_gives_bytes_as_stored_and_the_speed_of_a_run_that_computed(make_record, tmp_path, drawn):
    measured = make_record(seed=1, created="2026-01-01T00:00:00+00:00", descriptor_dim=64)
    served = make_record(seed=1, created="2026-02-01T00:00:00+00:00", descriptor_dim=64)
    measured["images_per_second"] = 211.0
    served.update(served_from_store=True, images_per_second=None, descriptors_computed={"database": 0, "queries": 0})
    served["descriptor_bytes"] = measured["descriptor_bytes"] = 128  # as a float16 store records it
    cell = _one_cell([measured, served])
    assert cell.record["run_id"] == served["run_id"]
    figures.efficiency([cell], tmp_path / "e.svg")
    left, right = drawn[0].axes
    [[size, r1]] = left.collections[0].get_offsets().tolist()
    [[speed, r1_again]] = right.collections[0].get_offsets().tolist()
    assert (size, speed) == (128, 211.0) and r1 == r1_again == pytest.approx(cell.recall(1))


def test_the_radar_draws_a_line_only_through_complete_domains_and_the_paper_dashed(make_record, tmp_path, drawn):
    runs = [make_record("hog", name, seed=i) for i, name in enumerate(("17places", "baidu-mall", "gardens-point",
                                                                       "oxford"))]  # urban: 1 of its 3
    board = build_board(runs)
    figures.radar(board, tmp_path / "radar.svg", {"hog": "#d62728", figures.paper_key("AnyLoc-VLAD-DINOv2"): "#1f77b4"})
    lines = {line.get_label(): line for line in drawn[0].axes[0].get_lines()}
    assert set(lines) == {"hog", figures.paper_key("AnyLoc-VLAD-DINOv2")}
    assert lines["hog"].get_linestyle() == "-" and lines[figures.paper_key("AnyLoc-VLAD-DINOv2")].get_linestyle() == "--"
    domains = figures.radar_domains(board, figures.domain_datasets())
    values = dict(zip(domains, lines["hog"].get_ydata()))
    indoor = [board.cell(board.rows[0], c).recall(1) for c in board.columns if c.dataset != "oxford"]
    assert values["indoor"] == pytest.approx(np.mean(indoor))  # all three of the paper's indoor datasets
    assert np.isnan(values["urban"])  # oxford only: a hollow point, no line through it
    assert all(np.isnan(v) for d, v in values.items() if d not in ("indoor", "urban"))  # nothing measured there


def test_a_mosaic_frames_in_green_exactly_the_matches_that_are_positives(make_record, tmp_path, drawn, monkeypatch):
    from types import SimpleNamespace

    from PIL import Image

    cell = _one_cell([make_record(quality=0.5, seed=3)])
    top = cell.arrays["database_indices"]
    # each query's one positive: its second match (its first and the rest are wrong)
    dataset = SimpleNamespace(queries=[f"q{i}" for i in range(len(top))], database=list(range(int(top.max()) + 1)),
                              positives=[np.array([row[1]]) for row in top])
    monkeypatch.setattr(figures, "_dataset_of", lambda *args, **kwargs: dataset)
    monkeypatch.setattr(figures, "_run_image", lambda *args, **kwargs: Image.new("RGB", (8, 6)))
    figures.mosaic(cell, tmp_path / "m.png", queries=3, top=4)
    rows = np.array(drawn[0].axes).reshape(3, 5)
    for row in rows:
        q = int(row[0].get_title().split()[-1])
        frames = [tuple(np.round(ax.spines["top"].get_edgecolor()[:3], 3)) for ax in row[1:]]
        green, red = (0.102, 0.62, 0.227), (0.839, 0.153, 0.157)
        assert frames == [red, green, red, red], q
        assert [ax.get_title() for ax in row[1:]] == [f"#{rank} db {d}" for rank, d in enumerate(top[q, :4], 1)]


def test_a_dollar_in_a_name_is_shown_not_read_as_mathematics():
    assert figures._label("cost $5 and $10") == r"cost \$5 and \$10"


def test_the_pca_map_draws_the_gem_method_run_on_the_most_datasets(tmp_path, drawn, monkeypatch):
    def run(method, dataset, domain):
        return {"method": method, "dataset": dataset, "domain": domain, "run_id": f"{method}-{dataset}",
                "method_fingerprint": {"method": method, "aggregation": "gem"},
                "provenance": {"weights": {"source": "official"}}}

    records = [run("wide", "corridor", "indoor"), run("wide", "oxford", "urban"), run("wide", "hawkins", "degraded"),
               run("narrow", "sped", "outdoor"), run("narrow", "nordland", "outdoor")]
    rng = np.random.default_rng(0)
    monkeypatch.setattr(figures, "stored_descriptors", lambda record, **kwargs: rng.normal(size=(12, 8)))
    figures.pca_map(records, tmp_path / "pca.png")
    ax = drawn[0].axes[0]
    assert [c.get_label() for c in ax.collections] == ["degraded (hawkins)", "indoor (corridor)", "urban (oxford)"]
    assert ax.get_title() == "wide GeM descriptors (weights: official)"
