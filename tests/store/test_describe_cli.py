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

