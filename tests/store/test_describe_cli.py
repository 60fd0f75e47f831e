"""`describe` goes the way `evaluate` goes: per-dataset settings, the store, post-processing."""
import shutil

import h5py
import numpy as np
import torch

from vprbench.cli.main import main
from vprbench.features.backbones import backbone_spec, create_model
from release_formats import official_state_dict


def test_describe_gives_the_descriptors_evaluate_stores(shared_data, tmp_path, capsys):
    queries = sorted((shared_data / "corridor" / "query").glob("*.jpg"))
    common = ["--method", "hog", "--resize", "64", "64"]
    assert main(["evaluate", *common, "--dataset", "corridor", "--data-dir", str(shared_data), "--json"]) == 0
    capsys.readouterr()
    (stored,) = (tmp_path / "user-cache" / "vprbench" / "stores").rglob("queries.h5")
    with h5py.File(stored) as f:
        expected = f["descriptors"][...][[3, 50, 7]]
    out = tmp_path / "d.npy"
    images = [str(queries[i]) for i in (3, 50, 7)]
    assert main(["describe", *common, "--dataset", "corridor", *images, "--out", str(out), "--workers", "2"]) == 0
    np.testing.assert_array_equal(np.load(out), expected)


def test_describe_applies_pca_fitted_on_fit_on_images(shared_data, tmp_path, capsys):
    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    weights = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), weights)
    database = tmp_path / "db"
    database.mkdir()
    for path in sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:12]:
        shutil.copy(path, database / path.name)
    queries = [str(p) for p in sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:3]]
    out = tmp_path / "pca.npy"
    args = ["describe", "--method", "anyloc", "--backbone", "dinov2_vits14", "--weights", str(weights), "--layer", "3",
            "--aggregation", "gem", "--pca-dim", "4", "--fit-on", str(database), *queries, "--out", str(out)]
    assert main(args) == 0
    described = np.load(out)
    assert described.shape == (3, 4)  # PCA-whitened, not the 384-D GeM descriptors
    np.testing.assert_allclose(np.linalg.norm(described, axis=1), 1, rtol=1e-5)
    assert main(args) == 0  # a second run is served from the stores
    np.testing.assert_array_equal(np.load(out), described)


ANYLOC = ["--method", "anyloc", "--backbone", "dino_vits8", "--weights", "random", "--layer", "3", "--facet", "value",
          "--resize", "56", "56"]


def test_describe_with_a_dataset_uses_its_ready_domain_vocabulary(shared_data, tmp_path, cli):
    """--dataset applies the dataset's vocabulary: pitts30k's is 'urban'. Before: refused with 'give --fit-on',
    needs_fit read before the dataset was applied."""
    torch.manual_seed(0)
    torch.save(torch.nn.functional.normalize(torch.randn(4, 384), dim=1), tmp_path / "c_centers.pt")
    code, _, err = cli("vocabulary", "import", tmp_path / "c_centers.pt", "--source", "urban", "--backbone",
                       "dino_vits8@random", "--layer", 3, "--facet", "value")
    assert code == 0, err
    images = [str(p) for p in sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]]
    vlad = [*ANYLOC, "--aggregation", "vlad", "--clusters", 4, *images, "--quiet"]
    code, _, err = cli("describe", *vlad, "--vocabulary", "domain", "--dataset", "pitts30k", "--out", tmp_path / "d.npy")
    assert code == 0, err
    code, _, err = cli("describe", *vlad, "--vocabulary", "urban", "--out", tmp_path / "urban.npy")
    assert code == 0, err
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), np.load(tmp_path / "urban.npy"))


def test_pca_wider_than_the_images_fitted_on_is_refused_before_describing(shared_data, tmp_path, cli):
    """Before: every image was described (the model loaded, the store written), then PCA's fit refused."""
    queries = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    cache = tmp_path / "cache"
    code, _, err = cli("describe", *ANYLOC, "--aggregation", "gem", "--pca-dim", 2, *queries, "--out",
                       tmp_path / "d.npy", "--cache-dir", cache)
    assert code == 1 and "PCA dimension 2" in err and "the images described (no --fit-on) (2)" in err
    assert not cache.exists() and not (tmp_path / "d.npy").exists()


def test_fit_on_for_a_method_that_fits_nothing_is_refused_before_describing(shared_data, tmp_path, cli):
    """Before: hog, or AnyLoc's GeM without PCA, described every --fit-on image into a store nothing read, then
    wrote the queries' descriptors as without it: --fit-on ignored, silently."""
    queries = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    database, cache = tmp_path / "db", tmp_path / "cache"
    database.mkdir()
    for path in sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:4]:
        shutil.copy(path, database / path.name)
    for method in (["--method", "hog"], [*ANYLOC, "--aggregation", "gem"]):
        code, _, err = cli("describe", *method, "--fit-on", database, *queries, "--out", tmp_path / "d.npy",
                           "--cache-dir", cache)
        assert code == 1 and "Traceback" not in err and err.count("\n") == 1, err
        assert err.strip() == (f"error: Method {method[1]!r} fits nothing on database images with these options (no "
                               f"vocabulary to fit, no post-processing such as PCA): --fit-on {database} would be "
                               "described for nothing; drop it.")
        assert not cache.exists() and not (tmp_path / "d.npy").exists()
    # PCA is fitted on them: of use
    code, _, err = cli("describe", *ANYLOC, "--aggregation", "gem", "--pca-dim", 2, "--fit-on", database, *queries,
                       "--out", tmp_path / "d.npy", "--cache-dir", cache, "--quiet")
    assert code == 0 and np.load(tmp_path / "d.npy").shape == (2, 2), err
