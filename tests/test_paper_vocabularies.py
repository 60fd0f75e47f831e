"""The ViT-G presets use the paper's vocabulary for each dataset: the authors' released centres
(placed where a download would put them; never downloaded in tests), map-specific where the
paper fits on the database, and a noted map-specific fallback where no released centres fit."""
from __future__ import annotations

import shutil
import socket

import pytest
import torch

from vprbench import VPRBenchError, create_method
from vprbench.methods.anyloc_lookup import paper_choice
from vprbench.methods.anyloc_vocabulary import fetch_released, release, released_path, released_sources
from vprbench.cli.main import main
from vprbench.weights import file_sha256

#: dataset -> (the source the paper uses, the released folder it comes from or None for map-specific)
PAPER = {
    "baidu-mall": ("indoor", "indoor"), "gardens-point": ("indoor", "indoor"), "17places": ("indoor", "indoor"),
    "pitts30k": ("urban", "urban"), "st-lucia": ("urban", "urban"), "oxford": ("urban", "urban"),
    "hawkins": ("hawkins", "hawkins"), "laurel-caverns": ("laurel-caverns", "laurel_caverns"),
    "nardo-air": ("aerial", "aerial"), "nardo-air-r": ("aerial", "aerial"), "vp-air": ("aerial", "aerial"),
    "mid-atlantic-ridge": ("map-mid-atlantic-ridge", None),
}


@pytest.fixture
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise OSError("network disabled in tests")

    monkeypatch.setattr(socket.socket, "connect", refuse)

    def no_name(*args, **kwargs):  # what an offline machine's resolver says, without waiting on it
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_name)


@pytest.fixture
def released_in_cache(shared_data, no_network):
    """The shared copies of the released c_centers.pt, where `vprbench vocabulary download` puts them."""
    source_root = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32"
    for source in released_sources():
        target = released_path(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source_root / target.parent.name / "c_centers.pt", target)
    return source_root


def test_recorded_checksums_are_the_shared_copies(shared_data):
    folders = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32"
    recorded = release()["sha256"]
    assert sorted(recorded) == sorted(p.name for p in folders.iterdir())
    for folder, digest in recorded.items():
        assert file_sha256(folders / folder / "c_centers.pt") == digest, folder


def test_paper_choice_for_each_of_the_twelve_datasets(released_in_cache):
    for dataset, (source, folder) in PAPER.items():
        found, chosen, note = paper_choice(dataset, "dinov2_vitg14", 31, "value", 32)
        assert (chosen, note) == (source, ""), dataset
        if folder is None:
            assert found is None, dataset
        else:
            assert found.centres.shape == (32, 1536)
            assert file_sha256(found.meta["path"]) == release()["sha256"][folder], dataset


def test_preset_records_which_vocabulary_each_run_used(released_in_cache):
    for dataset, (source, folder) in PAPER.items():
        method = create_method("anyloc-vlad-dinov2")  # no weights are loaded until images are described
        method.use_dataset(dataset)
        vocabulary = method.provenance()["vocabulary"]
        assert vocabulary["name"] == source and vocabulary["option"] == "domain"
        if folder is None:
            assert method.needs_fit and vocabulary["fitted_on_evaluated_database"]
            assert vocabulary["source"] == "fitted" and method.fingerprint()["vocabulary"] == "map"
        else:
            # the authors fitted each domain's centres on its databases, the evaluated one among them
            assert not method.needs_fit and vocabulary["fitted_on_evaluated_database"] is True
            assert dataset in vocabulary["datasets"] and f"the database of {dataset}" in vocabulary["fitted_on"]
            assert vocabulary["source"] == "released" and vocabulary["released_as"] == folder
            assert vocabulary["sha256"] == release()["sha256"][folder]
            assert vocabulary["commit"] == "89cade5529a590c4ed2999b396dcd3cab86e275b"
            assert method.fingerprint()["vocabulary"] == "sha256:" + vocabulary["centres_sha256"]
    pca = create_method("anyloc-vlad-dinov2-pca").provenance()["pca"]
    assert pca["fitted_on_evaluated_database"] and pca["dim"] == 512


def test_other_features_fall_back_to_map_specific_with_a_note(released_in_cache):
    method = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", layer=3, clusters=4)
    with pytest.warns(UserWarning, match="no 'indoor' vocabulary for dinov2_vits14 layer 3 value with 4 clusters.*map-specific"):
        method.use_dataset("baidu-mall")
    assert method.needs_fit and "note" in method.provenance()["vocabulary"]
    with pytest.warns(UserWarning, match="layer 30"):
        create_method("anyloc-vlad-dinov2", layer=30).use_dataset("pitts30k")


def test_named_released_vocabulary_and_download_command(released_in_cache, capsys):
    method = create_method("anyloc", vocabulary="aerial")
    assert method.provenance()["vocabulary"]["source"] == "released"
    assert main(["vocabulary", "download"]) == 0
    out = capsys.readouterr().out
    assert out.count("sha256") == 9 and "89cade5529a5" in out


def test_damaged_file_is_downloaded_again_and_offline_says_where_it_goes(released_in_cache):
    path = released_path("urban")
    path.write_bytes(b"not the released file")
    with pytest.raises(VPRBenchError, match=r"Cannot download the authors' 'urban' centres from https://raw\.githubusercontent\.com/"
                                            r"AnyLoc/Revisit-Anything/89cade5529a590c4ed2999b396dcd3cab86e275b/"
                                            r"cache/vocabulary/dinov2_vitg14/l31_value_c32/urban/c_centers\.pt"
                                            r" \(Name or service not known\)\. On a machine with internet access"):
        fetch_released("urban")  # was: '(ConnectionError: HTTPSConnectionPool(host=...) ... NameResolutionError(...))'


def test_importing_the_released_file_keeps_the_runs_key(tmp_path, shared_data, no_network):
    """`vocabulary import c_centers.pt --source urban` places the authors' file: a run naming 'urban' is
    known by their published sha256 before and after (re-saving it made another key: every cell ran again)."""
    from vprbench.spec import resolve_spec

    cache = tmp_path / "cache"
    before = resolve_spec("anyloc-vlad-dinov2", "pitts30k", cache_dir=cache)
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    assert main(["vocabulary", "import", str(released), "--source", "urban", "--cache-dir", str(cache)]) == 0
    after = resolve_spec("anyloc-vlad-dinov2", "pitts30k", cache_dir=cache)
    assert before.found == after.found == {"vocabulary": "sha256:" + release()["sha256"]["urban"]}
    assert after.key == before.key
    method = create_method("anyloc-vlad-dinov2", vocabulary="urban", cache_dir=cache)
    assert method.provenance()["vocabulary"]["source"] == "released"


def test_importing_the_released_file_over_centres_of_that_name_takes_their_place(tmp_path, shared_data, no_network,
                                                                                  capsys):
    """Centres fitted or imported as 'urban' before (vocabulary.pt, read first), then the authors' file imported as
    'urban' (a fit of that key ending while the import was on its way, or run before): runs use the release. It was
    written beside vocabulary.pt as c_centers.pt, said to replace the centres, and never read."""
    from vprbench.spec import resolve_spec

    cache = tmp_path / "cache"
    own = tmp_path / "own.pt"
    torch.save(torch.randn(32, 1536), own)
    assert main(["vocabulary", "import", str(own), "--source", "urban", "--cache-dir", str(cache)]) == 0
    mine = resolve_spec("anyloc-vlad-dinov2", "pitts30k", cache_dir=cache).found
    assert mine != {"vocabulary": "sha256:" + release()["sha256"]["urban"]}
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    assert main(["vocabulary", "import", str(released), "--source", "urban", "--cache-dir", str(cache)]) == 0
    assert "replacing the centres cached as 'urban'" in capsys.readouterr().out
    after = resolve_spec("anyloc-vlad-dinov2", "pitts30k", cache_dir=cache)
    assert after.found == {"vocabulary": "sha256:" + release()["sha256"]["urban"]}
    method = create_method("anyloc-vlad-dinov2", vocabulary="urban", cache_dir=cache)
    assert method.provenance()["vocabulary"]["source"] == "released"


@pytest.mark.parametrize("claimed, shown", [
    (["--layer", "20"], "dinov2_vitg14 layer 20 value"), (["--facet", "key"], "dinov2_vitg14 layer 31 key"),
    (["--backbone", "dinov2_vitg14@random"], "dinov2_vitg14@random layer 31 value")])
def test_released_centres_serve_only_the_features_they_were_fitted_on(tmp_path, shared_data, capsys, claimed, shown):
    """The authors' file names no setting, its sha256 does (ViT-G/14 block 31 value, official weights): imported
    for another block, facet or random weights it is refused in one line naming both, and nothing is cached (it was
    cached as layer 20's, or key's, and served to those features with a record saying 'cache', not 'released');
    named by its path for other features, the method refuses it too."""
    cache = tmp_path / "cache"
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    assert main(["vocabulary", "import", str(released), "--source", "urban", *claimed, "--cache-dir", str(cache)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert (f"is the authors' released 'urban' centres, fitted on dinov2_vitg14 layer 31 value with 32 clusters "
            f"(official weights), but these features are {shown} with 32 clusters") in err
    assert not list(cache.glob("vocabularies/*/urban/*.pt"))
    options = {"--layer": "layer", "--facet": "facet"}
    given = ({"weights": "random"} if claimed[0] == "--backbone" else {options[claimed[0]]: claimed[1]})
    with pytest.raises(VPRBenchError, match=f"these features are {shown} with 32 clusters"):
        create_method("anyloc-vlad-dinov2", vocabulary=str(released), cache_dir=cache, **{
            k: int(v) if k == "layer" else v for k, v in given.items()})


def test_released_centres_are_taken_with_a_checkpoint_of_ones_own(tmp_path, shared_data):
    """A local ViT-G/14 file may be the official one (DINOv2 publishes no sha256): its key (BACKBONE@<hex>) takes
    the authors' centres on the user's word, imported or as a path, as before; random weights never do (above)."""
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    assert main(["vocabulary", "import", str(released), "--source", "urban", "--backbone", "dinov2_vitg14@0123456789abcdef",
                 "--cache-dir", str(tmp_path)]) == 0
    assert list(tmp_path.glob("vocabularies/dinov2_vitg14@0123456789abcdef-l31-value-c32/urban/*.pt"))
