"""A vocabulary's name claims what it was fitted on (a domain, map-DATASET): centres whose content names
another source (a vprbench fit's metadata, the authors' release by its sha256) are not served or imported
under it. Before, a file copied into another name's cache folder was served, and the run named the folder's
source while its record listed the file's datasets."""
import argparse

import pytest
import torch

from vprbench.aggregation import Vocabulary
from vprbench.aggregation.vocabulary import vocabulary_dir
from vprbench.cli import vocabulary as cli
from vprbench.errors import VPRBenchError
from vprbench.methods.anyloc_lookup import paper_choice, resolve_vocabulary
from vprbench.methods.anyloc_vocabulary import save_to_cache

RELEASED = "vocabularies/anyloc-dinov2_vitg14-l31-value-c32"
AUTHORS = ("dinov2_vitg14", 31, "value")


def released(shared_data, folder: str):
    path = shared_data / RELEASED / folder / "c_centers.pt"
    if not path.is_file():
        pytest.skip(f"released centres {path} are absent")
    return path


def test_the_authors_urban_centres_copied_into_the_indoor_folder_are_refused(shared_data):
    urban = released(shared_data, "urban")
    indoor = vocabulary_dir(*AUTHORS, 32, "indoor")
    indoor.mkdir(parents=True)
    (indoor / "c_centers.pt").write_bytes(urban.read_bytes())
    with pytest.raises(VPRBenchError) as refused:
        resolve_vocabulary("indoor", *AUTHORS, 32)
    assert str(refused.value) == (
        f"Vocabulary {indoor / 'c_centers.pt'} holds the centres of 'urban' but sits in the cache folder of 'indoor': "
        f"move it to {vocabulary_dir(*AUTHORS, 32, 'urban')} (or delete it), then run again.")
    with pytest.raises(VPRBenchError, match="holds the centres of 'urban'"):  # the paper's choice for Baidu Mall
        paper_choice("baidu-mall", *AUTHORS, 32)
    (indoor / "c_centers.pt").write_bytes(released(shared_data, "indoor").read_bytes())  # its own: served
    assert resolve_vocabulary("indoor", *AUTHORS, 32).centres.shape == (32, 1536)


def test_a_fit_saved_as_one_domain_and_copied_under_another_is_refused(tmp_path):
    setting = ("dinov2_vits14@random", 11, "value")
    fitted = Vocabulary(torch.randn(4, 384), {"datasets": {"oxford": 3}})
    path = save_to_cache(fitted, *setting, "urban")
    assert resolve_vocabulary("urban", *setting, 4).meta["source"] == "urban"
    aerial = vocabulary_dir(*setting, 4, "aerial", stride=14)
    aerial.mkdir(parents=True)
    (aerial / path.name).write_bytes(path.read_bytes())
    with pytest.raises(VPRBenchError, match=r"holds the centres of 'urban' but sits in the cache folder of 'aerial'"):
        resolve_vocabulary("aerial", *setting, 4)
    mine = vocabulary_dir(*setting, 4, "my-centres", stride=14)  # a name of one's own claims nothing
    mine.mkdir(parents=True)
    (mine / path.name).write_bytes(path.read_bytes())
    assert resolve_vocabulary("my-centres", *setting, 4).clusters == 4


def test_import_refuses_centres_under_another_sources_name(shared_data, capsys):
    def imported(source):
        parser = argparse.ArgumentParser(prog="vprbench")
        cli.add_parsers(parser.add_subparsers(dest="command"))
        args = parser.parse_args(["vocabulary", "import", str(released(shared_data, "urban")), "--source", source,
                                  "--backbone", "dinov2_vitg14", "--layer", "31", "--facet", "value"])
        return args.run(args)

    with pytest.raises(VPRBenchError) as refused:
        imported("map-pitts30k")
    assert str(refused.value).endswith("holds the centres of 'urban', not of 'map-pitts30k': import it with "
                                       "--source urban (or under a name of your own).")
    assert not vocabulary_dir(*AUTHORS, 32, "map-pitts30k").exists()  # nothing cached under the wrong name
    assert imported("urban") == 0 and imported("urban-release") == 0
    assert resolve_vocabulary("urban-release", *AUTHORS, 32).centres.shape == (32, 1536)
