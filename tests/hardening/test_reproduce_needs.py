"""What reproduce's dry run says a cell needs is what the run would refuse: a cached vocabulary it would not
take, a dataset folder without its layout."""
from __future__ import annotations

import pytest

from vprbench.cli.main import main
from vprbench.sweep.needs import missing_for, vocabulary_for

from test_reproduce_plans_audit import _cells


def test_a_cached_vocabulary_the_run_would_refuse_is_a_need_of_the_dry_run(tmp_path, capsys, monkeypatch):
    """A file in the cell's vocabulary folder counted as ready whatever it held: the dry run said nothing was
    missing and the run then refused it (here centres of block 30 copied into block 31's 'indoor' folder).
    The dry run now checks it as the run does and names the run's refusal."""
    import torch

    from vprbench import VPRBenchError, create_method
    from vprbench.aggregation.vocabulary import Vocabulary, vocabulary_dir

    cache = tmp_path / "cache"
    folder = vocabulary_dir("dinov2_vitg14", 31, "value", 32, "indoor", cache)
    folder.mkdir(parents=True)
    Vocabulary(torch.randn(32, 1536), {"backbone": "dinov2_vitg14", "layer": 30, "facet": "value", "stride": 14,
                                       "source": "indoor"}).save(folder / "vocabulary.pt")
    _, cells = _cells("2", "AnyLoc-VLAD-DINOv2", cache)
    refusal = "was fitted on backbone dinov2_vitg14 layer 30 facet value, but these features are backbone dinov2_vitg14 layer 31"
    with pytest.raises(VPRBenchError, match=refusal):  # the run
        create_method("anyloc-vlad-dinov2", cache_dir=cache).use_dataset("baidu-mall")
    what, how = vocabulary_for(cells["baidu-mall"].cells[0], cache)  # was None: "would run"
    assert what == "the cached vocabulary 'indoor' for dinov2_vitg14 layer 31 value with 32 clusters" and refusal in how
    assert vocabulary_for(cells["pitts30k"].cells[0], cache)[0] == "the authors' vocabulary 'urban'"  # others as before
    monkeypatch.setenv("COLUMNS", "400")
    assert main(["reproduce", "anyloc", "--table", "2", "--dry-run", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(cache)]) == 0
    assert refusal in " ".join(capsys.readouterr().out.split())


def test_a_dataset_folder_without_its_layout_is_a_need_of_the_dry_run(tmp_path):
    """A dataset counted as on disk when its folder existed: an unfinished extraction (gardens/ with day_right/
    only) left the cell 'would run' once its weights were there, and the run then failed reading it. The dry run
    now names what the run would: the layouts' missing folders and files, and how to get the data."""
    data = tmp_path / "data"
    (data / "gardens" / "day_right").mkdir(parents=True)
    _, cells = _cells("2", "DINO-CLS", tmp_path / "cache")
    needs = dict(missing_for(cells["gardens-point"].cells[0], None, data, tmp_path / "cache"))
    assert "layout 'folders' (the authors' release) is missing folder 'night_right', file 'gardens_gt.npy'" in \
        needs["dataset gardens-point"]
    assert "Place it at" in needs["dataset gardens-point"]
    assert "dataset baidu-mall" in dict(missing_for(cells["baidu-mall"].cells[0], None, data, tmp_path / "cache"))


def test_a_vocabulary_two_methods_share_is_listed_once(tmp_path, capsys, monkeypatch):
    """Table II's AnyLoc-VLAD-DINO and -PCA rows lack the same 'indoor' and 'urban' vocabularies (cached by their
    features, not by method): the notes said each twice, a fit per method, and following them fitted each twice."""
    import re

    monkeypatch.setenv("COLUMNS", "1000")  # a note a line
    code = main(["reproduce", "anyloc", "--table", "2", "--dry-run", "--data-dir", str(tmp_path / "data"),
                 "--cache-dir", str(tmp_path / "cache")])
    out = capsys.readouterr().out
    notes = re.findall(r"^\[\d+\] (.*)$", out, re.MULTILINE)
    assert code == 0
    for domain in ("indoor", "urban"):
        said = [note for note in notes if note.startswith(f"vocabulary '{domain}' for dino_vits8 layer 9 key c128: ")]
        assert len(said) == 1 and said[0].count("vprbench vocabulary fit") == 1, said
        assert said[0].endswith("(serves rows AnyLoc-VLAD-DINO, AnyLoc-VLAD-DINO-PCA)"), said
    things = [note.split(": ")[0] for note in notes]
    assert len(things) == len(set(things)), things  # no need said twice


def test_a_released_vocabulary_not_here_is_a_need_until_it_is(tmp_path, shared_data):
    """Before: a cell on the authors' released centres counted as ready (they download on first use), so a
    dry run on a machine without internet said 'would run' and the cell failed when run. Like weights,
    it is now a need until the file is where the run reads it."""
    import shutil

    from vprbench.methods.anyloc_vocabulary import released_path

    _, cells = _cells("2", "AnyLoc-VLAD-DINOv2", tmp_path)
    baidu = cells["baidu-mall"].cells[0]  # the paper's vocabulary there: indoor, released
    what, how = vocabulary_for(baidu, tmp_path)
    target = released_path("indoor", tmp_path)
    assert what == "the authors' vocabulary 'indoor'" and "vprbench vocabulary download" in how and str(target) in how
    target.parent.mkdir(parents=True)
    shutil.copy(shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / target.parent.name / "c_centers.pt",
                target)
    assert vocabulary_for(baidu, tmp_path) is None
