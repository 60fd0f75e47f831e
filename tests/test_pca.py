import numpy as np
import pytest

from vprbench.aggregation import PCAWhitening, pca_whiten
from vprbench.errors import VPRBenchError


def data(n, d, seed):
    return np.random.default_rng(seed).normal(size=(n, d)).astype(np.float32)


def test_pca_whitening_dims_norms_and_whiteness():
    db, q = data(200, 64, 0), data(30, 64, 1)
    out_db, out_q = pca_whiten(db, q, 16)
    assert out_db.shape == (200, 16) and out_q.shape == (30, 16) and out_db.dtype == np.float32
    assert np.allclose(np.linalg.norm(out_q, axis=1), 1, atol=1e-5)
    # before the final L2 the database projections are white: unit variance, uncorrelated
    pca = PCAWhitening(16).fit(db)
    raw = (db - pca.mean) @ pca.projection.T
    assert np.allclose(np.cov(raw, rowvar=False), np.eye(16), atol=1e-3)


def test_pca_state_roundtrip():
    db = data(50, 20, 2)
    pca = PCAWhitening(8).fit(db)
    again = PCAWhitening.from_state(pca.state())
    assert again.dim == 8 and np.array_equal(again.transform(db), pca.transform(db))


def test_pca_errors():
    with pytest.raises(VPRBenchError, match="PCA dimension 512 is larger than the number of database images \\(100\\)"):
        PCAWhitening().fit(data(100, 1000, 0))
    with pytest.raises(VPRBenchError, match="descriptor dimension \\(10\\): choose pca_dim <= 10"):
        PCAWhitening(20).fit(data(100, 10, 0))
    with pytest.raises(VPRBenchError, match="at least 1"):
        PCAWhitening(0)
    with pytest.raises(VPRBenchError, match="before being fitted"):
        PCAWhitening(4).transform(data(3, 10, 0))
    pca = PCAWhitening(4).fit(data(30, 10, 0))
    with pytest.raises(VPRBenchError, match="fitted on 10-dimensional descriptors"):
        pca.transform(data(3, 11, 0))
