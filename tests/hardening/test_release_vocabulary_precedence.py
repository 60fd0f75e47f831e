"""Centres fitted or imported under a name of the authors' release (at their setting) never pass for it: the
release is read first where it is in the cache, and without it the run, `vocabulary list` and the dry run say
the cached centres are not the release (was: an import of the release with one value changed by 1e-3 ran as the
paper's 'urban', its record saying only 'cache', and the dry run no longer asked for the release)."""
from __future__ import annotations

import shutil

import torch

from vprbench import create_method
from vprbench.cli.main import main
from vprbench.methods.anyloc_vocabulary import release, released_path
from vprbench.sweep.needs import vocabulary_for

from test_reproduce_plans_audit import _cells


def _edited_urban(tmp_path, shared_data):
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    centres = torch.load(released).clone()
    centres[0, 0] += 1e-3
    torch.save(centres, tmp_path / "urban_edit.pt")
    return released, tmp_path / "urban_edit.pt"


def test_centres_of_ones_own_under_the_release_name_are_marked_and_the_release_read_first(tmp_path, shared_data,
                                                                                           capsys):
    cache = tmp_path / "cache"
    released, edited = _edited_urban(tmp_path, shared_data)
    assert main(["vocabulary", "import", str(edited), "--source", "urban", "--cache-dir", str(cache)]) == 0
    assert "names the authors' released centres" in capsys.readouterr().out
    method = create_method("anyloc-vlad-dinov2", cache_dir=cache)
    method.use_dataset("pitts30k")
    vocabulary = method.provenance()["vocabulary"]
    assert vocabulary["authors_release"] is False and vocabulary["made_by"] == "imported"
    assert main(["vocabulary", "list", "--cache-dir", str(cache)]) == 0
    assert "NOT the authors' release" in capsys.readouterr().out
    _, cells = _cells("2", "AnyLoc-VLAD-DINOv2", cache)
    what, how = vocabulary_for(cells["pitts30k"].cells[0], cache)  # was None: 'urban' counted as cached
    assert what == "the authors' vocabulary 'urban'" and "are not the authors' release" in how

    target = released_path("urban", cache)  # where `vocabulary download` puts it: read first from now on
    shutil.copyfile(released, target)
    method = create_method("anyloc-vlad-dinov2", cache_dir=cache)
    method.use_dataset("pitts30k")
    vocabulary = method.provenance()["vocabulary"]
    assert vocabulary["source"] == "released" and vocabulary["authors_release"] is True
    assert vocabulary["sha256"] == release()["sha256"]["urban"]
    assert vocabulary_for(cells["pitts30k"].cells[0], cache) is None
    assert main(["vocabulary", "list", "--cache-dir", str(cache)]) == 0
    listed = capsys.readouterr().out
    assert "urban (vocabulary.pt)" in listed and "NOT the authors' release" in listed
    assert "urban (c_centers.pt): 32 x 1536, the authors' released 'urban' centres" in listed
