"""A run's key follows the vocabulary its method loads: from the method's cache folder (spec_for), or
from a folder in the working directory named by a bare word."""
import torch

from vprbench import create_method
from vprbench.aggregation.vocabulary import Vocabulary
from vprbench.methods.anyloc_vocabulary import save_to_cache
from vprbench.spec import resolve_spec, spec_for
from vprbench.weights import file_sha256


def test_spec_for_names_the_vocabulary_of_the_methods_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("VPRBENCH_CACHE", str(tmp_path / "default"))  # holds no vocabulary
    cache = tmp_path / "mine"
    centres = torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(0)), dim=1)
    path = save_to_cache(Vocabulary(centres, {}), "dinov2_vits14@random", 1, "value", "indoor", cache)
    method = create_method("anyloc", backbone="dinov2_vits14", weights="random", layer=1, clusters=4,
                           vocabulary="indoor", resize=[56, 56], cache_dir=cache)
    assert method.fingerprint()["vocabulary"].startswith("sha256:")  # the method uses the centres of `cache`
    found = {"vocabulary": "sha256:" + file_sha256(path)}
    assert spec_for(method, "corridor").found == found  # was {}: the record told of no vocabulary
    assert spec_for(method, "corridor", cache_dir=cache).found == found


def test_a_bare_word_folder_vocabulary_is_known_by_the_file_it_holds(tmp_path, monkeypatch):
    """`vocabulary = "urban"` run beside the authors' unpacked release (urban/c_centers.pt) loads that
    folder's file: its key changes with the file (it did not: a sweep served the record of the old centres)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "urban").mkdir()
    options = {"backbone": "dinov2_vits14", "weights": "random", "layer": 1, "clusters": 4, "vocabulary": "urban"}
    keys = []
    for seed in (0, 1):
        torch.save(torch.randn(4, 384, generator=torch.Generator().manual_seed(seed)), tmp_path / "urban" / "c_centers.pt")
        spec = resolve_spec("anyloc", "corridor", options=options, cache_dir=tmp_path / "cache")
        assert spec.found == {"vocabulary": "sha256:" + file_sha256(tmp_path / "urban" / "c_centers.pt")}
        keys.append((spec.key, spec.row_key))
    assert keys[0][0] != keys[1][0] and keys[0][1] == keys[1][1]
    method = create_method("anyloc", **options)  # the method does load the folder's file
    assert method.vocabulary_info["file"] == "urban/c_centers.pt"
