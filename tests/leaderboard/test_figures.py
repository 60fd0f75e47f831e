"""The site's figures: one colour per method everywhere, a radar that draws an axis only over all
its datasets, and mosaics that read only the images a run evaluated (by content)."""
import re
import shutil

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from vprbench.evaluation import read_results, save_result
from vprbench.leaderboard import domains, figures
from vprbench.leaderboard.cells import build_board
from vprbench.leaderboard.figures import Skipped, mosaic


def hog_on_a_copy(capsys, tmp_path, shared_data):
    """A real hog run on Corridor, evaluated from a copy of its folder (the record names the copy)."""
    data = tmp_path / "data"
    shutil.copytree(shared_data / "corridor", data / "corridor")
    code = main(["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", str(data),
                 "--resize", "32", "32"])
    assert code == 0, capsys.readouterr().err
    [record] = read_results()
    [cell] = build_board([record]).cells.values()
    return data / "corridor", cell


def test_a_mosaic_refuses_a_folder_whose_images_are_not_the_runs(capsys, tmp_path, shared_data):
    folder, cell = hog_on_a_copy(capsys, tmp_path, shared_data)
    mosaic(cell, tmp_path / "before.png")  # the run's own images: drawn
    references = sorted((folder / "ref").iterdir())
    first, second = references[0].read_bytes(), references[1].read_bytes()
    references[0].write_bytes(second)  # the same files, counts and ground truth; other pictures
    references[1].write_bytes(first)
    # the attack is real: the folder still passes every check but content (counts, positives)
    dataset = load_dataset("corridor", folder.parent, fetch=False)
    assert (len(dataset.database), len(dataset.queries)) == (111, 111)
    assert [len(p) for p in dataset.positives] == cell.arrays["positives"].tolist()
    assert dataset.fingerprint() != cell.record["dataset_fingerprint"]
    with pytest.raises(Skipped, match="images .* differ from the ones this run evaluated"):
        mosaic(cell, tmp_path / "after.png")
    assert not (tmp_path / "after.png").exists()


def test_a_file_replaced_after_the_check_is_not_shown(capsys, tmp_path, shared_data):
    folder, cell = hog_on_a_copy(capsys, tmp_path, shared_data)
    dataset = figures._dataset_of(cell.record)  # the run's images, checked by content
    figures._run_image(dataset, "database", 0)
    references = sorted((folder / "ref").iterdir())
    references[0].write_bytes(references[1].read_bytes())
    with pytest.raises(Skipped, match="changed after its content was checked"):
        figures._run_image(dataset, "database", 0)


def test_method_colours_are_one_per_method_whatever_the_order():
    names = ["hog", "dense-vlad", "netvlad", "AnyLoc-VLAD-DINOv2 (paper, reported)"]
    colours = figures.method_colours(names)
    assert colours == figures.method_colours(list(reversed(names)))
    assert len(set(colours.values())) == len(names) and set(colours.values()) <= set(figures.PALETTE[:10])
    many = figures.method_colours([f"m{i}" for i in range(20)])
    assert len(set(many.values())) == 20  # collisions moved to free slots


def svg_colours(path) -> set[str]:
    """The line and marker colours an SVG uses, without the axes' greys, black and white."""
    found = set(re.findall(r"(?:stroke|fill): (#[0-9a-f]{6})", path.read_text()))
    return {c for c in found if len({c[1:3], c[3:5], c[5:7]}) > 1}


def test_every_figure_of_a_publish_gives_a_method_one_colour(make_record, tmp_path, capsys):
    # hog is first on corridor and second on hawkins: a colour cycle would swap their colours
    for dataset, qualities in (("corridor", (0.9, 0.3)), ("hawkins", (0.2, 0.8))):
        for method, quality in zip(("hog", "dense-vlad"), qualities):
            save_result(make_record(method, dataset, quality=quality, seed=len(method)))
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    [hog, vlad] = [build_board(read_results()).find_row(m)[0].name for m in ("hog", "dense-vlad")]
    colours = figures.method_colours([hog, vlad, figures.paper_key("AnyLoc-VLAD-DINOv2")])
    shown = docs / "leaderboard" / "figures"
    for name in ("corridor-recall.svg", "hawkins-recall.svg", "corridor-pr.svg", "hawkins-pr.svg",
                 "corridor-efficiency.svg", "hawkins-efficiency.svg"):
        assert svg_colours(shown / name) == {colours[hog], colours[vlad]}, name
    assert colours[hog] in svg_colours(shown / "radar.svg")


def board_of(make_record, runs):
    return build_board([make_record(method, dataset, seed=i) for i, (method, dataset) in enumerate(runs)])


def test_the_radar_fills_a_domain_only_over_all_its_datasets(make_record):
    axes = domains.domain_datasets()
    assert axes["indoor"] == ["17places", "baidu-mall", "gardens-point"]  # the paper's: corridor is not one
    assert axes["outdoor"] == ["nordland", "sped"]  # the paper has none: every benchmark of the domain
    only_corridor = domains.domain_averages(board_of(make_record, [("hog", "corridor")]))["hog"]
    assert only_corridor["indoor"].datasets == ("corridor",) and not only_corridor["indoor"].complete
    board = board_of(make_record, [("hog", name) for name in ("corridor", "17places", "baidu-mall", "gardens-point")])
    indoor = domains.domain_averages(board)["hog"]["indoor"]
    assert indoor.complete and indoor.datasets == ("17places", "baidu-mall", "gardens-point")
    r1 = [board.cell(board.rows[0], c).recall(1) for c in board.columns if c.dataset in indoor.datasets]
    assert indoor.value == pytest.approx(np.mean(r1), abs=1e-9)  # corridor left out of the paper's axis
    paper = domains.paper_domain_averages()["AnyLoc-VLAD-DINOv2"]
    assert all(m.complete for m in paper.values())


def test_the_radar_marks_a_partial_domain_hollow_and_names_its_datasets(make_record, tmp_path):
    path = figures.radar(board_of(make_record, [("hog", "corridor")]), tmp_path / "radar.svg",
                         {"hog": "#d62728", figures.paper_key("AnyLoc-VLAD-DINOv2"): "#1f77b4"})
    hollow = set(re.findall(r'style="fill: #ffffff; stroke: (#[0-9a-f]{6})', path.read_text()))
    assert hollow == {"#d62728"}  # hog's corridor-only indoor point, and no other
    complete = board_of(make_record, [("hog", name) for name in ("17places", "baidu-mall", "gardens-point")])
    path = figures.radar(complete, tmp_path / "full.svg", {"hog": "#d62728", figures.paper_key("AnyLoc-VLAD-DINOv2"): "#1f77b4"})
    assert not re.findall(r'style="fill: #ffffff; stroke: ', path.read_text())  # every dataset of the axis: filled


def test_the_pca_map_draws_no_run_the_board_leaves_out(shared_data, tmp_path, capsys):
    """Before: the overview's PCA map was drawn from every stored GeM run, here one on random weights
    (a pipeline check, in no cell), under the title '... GeM descriptors (weights: random)'."""
    common = ["--dataset", "corridor", "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "cache")]
    for method in (["--method", "hog", "--resize", "32", "32"],
                   ["--method", "anyloc-gem-dinov2", "--option", "backbone=dinov2_vits14", "--option", "weights=random",
                    "--option", "resize=28,28", "--option", "layer=9"]):
        assert main(["evaluate", *method, *common]) == 0, capsys.readouterr().err
    assert main(["leaderboard", "publish", "--to", str(tmp_path / "site"), *common[2:]]) == 0, capsys.readouterr().err
    overview = (tmp_path / "site" / "leaderboard" / "index.md").read_text()
    assert "PCA map of GeM descriptors: not drawn, no GeM descriptors" in overview, overview
    assert not (tmp_path / "site" / "leaderboard" / "figures" / "pca-gem.png").exists()


def test_a_name_starting_with_an_underscore_has_its_legend_entry(make_record, tmp_path):
    """matplotlib leaves '_'-labels out of a legend it gathers itself: a record's method '_x_' had none."""
    board = board_of(make_record, [("_x_", "corridor"), ("hog", "corridor")])
    cells = list(board.cells.values())
    shown = {}
    for draw in (figures.recall_curves, figures.pr_curves, figures.efficiency):
        svg = draw(cells, tmp_path / f"{draw.__name__}.svg").read_text()
        shown[draw.__name__] = sorted(set(re.findall(r"<!-- (_x_|hog)\b", svg)))  # the text's comment
    assert shown == dict.fromkeys(("recall_curves", "pr_curves", "efficiency"), ["_x_", "hog"])
