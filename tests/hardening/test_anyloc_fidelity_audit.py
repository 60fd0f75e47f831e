"""AnyLoc fidelity audit: each detail that decides equality with the paper and the authors' code,
checked against an independent numpy reading of the formula (random inputs, tiny random models);
the paper's settings and plans: test_anyloc_settings_audit.py."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from PIL import Image

from vprbench.aggregation import pooling, vlad
from vprbench.aggregation.pca import PCAWhitening
from vprbench.aggregation.kmeans import kmeans_cosine
from vprbench.aggregation.vocabulary import fit_vocabulary
from vprbench.errors import VPRBenchError
from vprbench.evaluation.metrics import correct_at, first_positive_rank, recall_at_k
from vprbench.search.exact import search
from vprbench.features.backbones import backbone_spec, create_model
from vprbench.features.dense import DenseExtractor, interpolate_pos_embed
from vprbench.features.preprocess import preprocess

MEAN, STD = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])


# ---------------------------------------------------------------- independent numpy formulas
def _unit(x, eps=1e-12):
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), eps)


def _cos_labels(x, c):
    a = x / (np.linalg.norm(x, axis=-1, keepdims=True) + 1e-8)
    b = c / (np.linalg.norm(c, axis=-1, keepdims=True) + 1e-8)
    return (a @ b.T).argmax(-1)


def _np_hard_vlad(feats, centres):
    """Normalise, label by cosine argmax, residual to the raw centre, sum, intra-norm, L2."""
    x = _unit(feats.astype(np.float64))
    labels = _cos_labels(x, centres)
    out = np.zeros_like(centres, dtype=np.float64)
    for k in set(labels.tolist()):
        out[k] = _unit((x[labels == k] - centres[k]).sum(0))
    return _unit(out.reshape(-1))


def _np_soft_weights(x, c, temperature=1.0):
    cos = (x @ c.T) / np.maximum(np.linalg.norm(x, axis=1)[:, None] * np.linalg.norm(c, axis=1)[None], 1e-8)
    e = np.exp(temperature * cos - (temperature * cos).max(1, keepdims=True))
    return e / e.sum(1, keepdims=True)


def _np_soft_vlad_official(feats, centres):
    w = _np_soft_weights(feats, centres)
    x = _unit(feats.astype(np.float64))
    residuals = x[:, None, :] - centres[None, :, :]                        # [q, c, d]
    out = np.stack([_unit((w[:, k, None, None] * residuals).reshape(-1, x.shape[1]).sum(0))
                    for k in range(len(centres))])
    return _unit(out.reshape(-1))


def _np_soft_vlad_textbook(feats, centres):
    w = _np_soft_weights(feats, centres)
    x = _unit(feats.astype(np.float64))
    out = np.stack([_unit((w[:, k, None] * (x - centres[k])).sum(0)) for k in range(len(centres))])
    return _unit(out.reshape(-1))


def _np_kmeans(x, k, init, max_iter=100, tol=1e-4):
    c = init.astype(np.float64)
    for it in range(1, max_iter + 1):
        labels = _cos_labels(x, c)
        new = np.stack([x[labels == j].mean(0) if (labels == j).any() else np.zeros(x.shape[1]) for j in range(k)])
        err = ((new - c) ** 2).sum()
        c = new
        if err <= tol:
            break
    return c, it


def _np_bilinear(img, out_h, out_w):
    """align_corners=False, no antialias: src = (dst + 0.5) * in/out - 0.5, clamped at 0."""
    def axis(n_in, n_out):
        m = np.zeros((n_out, n_in))
        for d in range(n_out):
            s = max((d + 0.5) * n_in / n_out - 0.5, 0.0)
            i0 = min(int(np.floor(s)), n_in - 1)
            i1, t = min(i0 + 1, n_in - 1), s - i0
            m[d, i0] += 1 - t
            m[d, i1] += t
        return m
    ah, aw = axis(img.shape[1], out_h), axis(img.shape[2], out_w)
    return np.einsum("ph,chw,qw->cpq", ah, img, aw, optimize=True)


def _np_bicubic_scale(grid, scale, out, a=-0.75):
    """Cubic convolution driven by the scale factor: src = (dst + 0.5) / scale - 0.5, edges clamped."""
    def w(t):
        t = abs(t)
        return (a + 2) * t**3 - (a + 3) * t**2 + 1 if t <= 1 else (a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a if t < 2 else 0)

    def axis(n_in, n_out, s):
        m = np.zeros((n_out, n_in))
        for d in range(n_out):
            src = (d + 0.5) / s - 0.5
            i0 = math.floor(src)
            for k in range(i0 - 1, i0 + 3):
                m[d, min(max(k, 0), n_in - 1)] += w(src - k)
        return m
    return np.einsum("ph,hwc,qw->pqc", axis(grid.shape[0], out[0], scale[0]), grid, axis(grid.shape[1], out[1], scale[1]),
                     optimize=True)


def _png(path, h, w, seed=0):
    rgb = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path)
    return rgb


# ---------------------------------------------------------------- aggregation
@pytest.fixture
def feats_centres():
    rng = np.random.default_rng(3)
    feats = rng.normal(size=(60, 8)).astype(np.float32) * rng.uniform(0.5, 3, (60, 1)).astype(np.float32)
    centres = rng.normal(size=(6, 8)).astype(np.float32) * 0.7   # not unit-norm, as the authors' centres
    centres[5] = -10 * np.abs(centres[5])                       # far away: likely unused, stays zero
    return feats, centres


def test_hard_vlad_is_the_official_formula(feats_centres):
    feats, centres = feats_centres
    expected = _np_hard_vlad(feats, centres)
    ours = vlad.vlad_hard(torch.from_numpy(feats), torch.from_numpy(centres), normalise_features=True).numpy()
    assert ours.shape == (6 * 8,)
    np.testing.assert_allclose(ours, expected, atol=1e-6)
    # DINOv2 path: patch features arrive normalised and VLAD takes them as they are
    ours_unit = vlad.vlad_hard(torch.from_numpy(_unit(feats)), torch.from_numpy(centres)).numpy()
    np.testing.assert_allclose(ours_unit, expected, atol=1e-6)
    assert np.all(expected.reshape(6, 8)[[k for k in range(6) if k not in set(_cos_labels(feats, centres))]] == 0)


def test_soft_vlads_are_the_official_and_textbook_formulas(feats_centres):
    feats, centres = feats_centres
    t = torch.from_numpy(feats), torch.from_numpy(centres)
    official = vlad.vlad_soft_official(*t, normalise_features=True).numpy()
    textbook = vlad.vlad_soft(*t, normalise_features=True).numpy()
    np.testing.assert_allclose(official, _np_soft_vlad_official(feats, centres), atol=1e-5)
    np.testing.assert_allclose(textbook, _np_soft_vlad_textbook(feats, centres), atol=1e-5)
    assert np.abs(official - textbook).max() > 1e-2  # two different options


def test_gem_is_the_signed_real_cube_root_of_the_mean_cube():
    x = np.random.default_rng(4).normal(size=(2, 30, 5))
    m = (x**3).mean(1)
    expected = _unit(np.abs(m) ** (1 / 3) * np.sign(m))
    np.testing.assert_allclose(pooling.gem(torch.from_numpy(x), 3.0).numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(pooling.gap(torch.from_numpy(x)).numpy(), _unit(x.mean(1)), atol=1e-6)
    np.testing.assert_allclose(pooling.gmp(torch.from_numpy(x)).numpy(), _unit(x.max(1)), atol=1e-6)


def test_cosine_kmeans_is_the_official_algorithm():
    rng = np.random.default_rng(5)
    x = _unit(rng.normal(size=(300, 6))).astype(np.float32)
    init_idx = np.random.RandomState(42).choice(300, size=[7], replace=False)  # numpy seed 42, as the authors
    expected, iters = _np_kmeans(x.astype(np.float64), 7, x[init_idx])
    ours, ours_iters = kmeans_cosine(x, 7)
    np.testing.assert_allclose(ours.numpy(), expected, atol=1e-5)
    assert ours_iters == iters and not np.allclose(np.linalg.norm(expected, axis=1), 1)  # plain means
    # an empty cluster becomes a zero vector (a duplicated initial centre never wins the argmax)
    init = torch.from_numpy(x[[0, 0, 1, 2]])
    ours_dup, _ = kmeans_cosine(x, 4, init=init, max_iter=1)
    assert torch.all(ours_dup[1] == 0)
    np.testing.assert_allclose(ours_dup.numpy(), _np_kmeans(x.astype(np.float64), 4, x[[0, 0, 1, 2]], max_iter=1)[0],
                               atol=1e-5)


def test_exact_vocabulary_fits_normalised_features():
    rng = np.random.default_rng(6)
    chunks = [rng.normal(size=(40, 5)).astype(np.float32) * 4 for _ in range(3)]
    x = _unit(np.concatenate(chunks).astype(np.float64))
    expected, _ = _np_kmeans(x, 4, x[np.random.RandomState(42).choice(120, size=[4], replace=False)])
    ours = fit_vocabulary(iter(chunks), 4, exact=True).centres.numpy()
    np.testing.assert_allclose(ours, expected, atol=1e-5)


# ---------------------------------------------------------------- preprocessing and features
def test_dinov2_preprocessing_is_normalise_resize_then_crop(tmp_path):
    rgb = _png(tmp_path / "a.png", 227, 301).astype(np.float64)
    x = ((rgb / 255.0 - MEAN) / STD).transpose(2, 0, 1)
    spec = backbone_spec("dinov2_vitg14")
    native = preprocess(tmp_path / "a.png", spec).numpy()
    # 227 -> 224 starts at round(1.5) = 2, 301 -> 294 at round(3.5) = 4 (half to even)
    np.testing.assert_allclose(native, x[:, 2:226, 4:298], atol=1e-5)
    resized = preprocess(tmp_path / "a.png", spec, resize=(100, 131)).numpy()
    np.testing.assert_allclose(resized, _np_bilinear(x, 100, 131)[:, 1:99, 2:128], atol=1e-4)


def test_dino_v1_preprocessing_is_nearest_to_224x298(tmp_path):
    rgb = _png(tmp_path / "b.png", 150, 190, seed=1).astype(np.float64)
    x = ((rgb / 255.0 - MEAN) / STD).transpose(2, 0, 1)
    rows = np.floor(np.arange(224) * 150 / 224).astype(int)
    cols = np.floor(np.arange(298) * 190 / 298).astype(int)
    ours = preprocess(tmp_path / "b.png", backbone_spec("dino_vits8")).numpy()
    np.testing.assert_allclose(ours, x[:, rows][:, :, cols], atol=1e-5)


def test_position_embedding_follows_the_scale_factor():
    rng = np.random.default_rng(7)
    grid = rng.normal(size=(5, 5, 3))
    pos = torch.from_numpy(np.concatenate([np.ones((1, 3)), grid.reshape(25, 3)])[None]).float()
    for out in [(3, 7), (8, 4)]:
        expected = _np_bicubic_scale(grid, ((out[0] + 0.1) / 5, (out[1] + 0.1) / 5), out).reshape(-1, 3)
        ours = interpolate_pos_embed(pos, out)
        np.testing.assert_allclose(ours[0, 1:].numpy(), expected, atol=1e-5)
        assert torch.equal(ours[0, 0], pos[0, 0])


@pytest.fixture(scope="module")
def tiny_dinov2():
    torch.manual_seed(11)
    spec = backbone_spec("dinov2_vits14")
    return create_model(spec, depth=3, embed_dim=48, num_heads=4), spec


def test_dinov2_facets_by_hand(tiny_dinov2):
    """tokens = conv patch embedding + CLS + official position embedding; facet = thirds of block
    L's qkv(norm1(x)); token = block L's output (no final norm); CLS dropped."""
    model, spec = tiny_dinov2
    images = torch.randn(1, 3, 42, 70)  # 3 x 5 patches
    with torch.no_grad():
        patches = torch.nn.functional.conv2d(images, model.patch_embed.proj.weight, model.patch_embed.proj.bias,
                                             stride=14).flatten(2).transpose(1, 2)
        grid = model.pos_embed[0, 1:].reshape(37, 37, 48).numpy().astype(np.float64)
        pe = _np_bicubic_scale(grid, ((3 + 0.1) / 37, (5 + 0.1) / 37), (3, 5)).reshape(1, 15, 48)
        x = torch.cat([model.cls_token + model.pos_embed[:, :1], patches + torch.from_numpy(pe).float()], dim=1)
        x = model.blocks[0](x)
        block = model.blocks[1]
        qkv = (block.norm1(x) @ block.attn.qkv.weight.T + block.attn.qkv.bias)[:, 1:]
        token = block(x)[:, 1:]
    for i, facet in enumerate(("query", "key", "value")):
        ours = DenseExtractor(model, spec, 1, facet)(images)
        torch.testing.assert_close(ours, qkv[..., i * 48:(i + 1) * 48], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(DenseExtractor(model, spec, 1, "token")(images), token, atol=1e-4, rtol=1e-4)


def test_dinov2_cls_is_the_final_norm_cls_token(tiny_dinov2):
    model, spec = tiny_dinov2
    images = torch.randn(1, 3, 518, 518)  # the trained 37 x 37 grid: timm's own forward needs no resampling
    with torch.no_grad():
        expected = model.forward_features(images)[:, 0]  # after the final norm
    ours = DenseExtractor(model, spec, len(model.blocks) - 1, "token").cls_token(images)
    torch.testing.assert_close(ours, expected, atol=1e-4, rtol=1e-4)


def test_dino_v1_key_facet_interleaves_heads_at_stride_4():
    torch.manual_seed(12)
    spec = backbone_spec("dino_vits8")
    model = create_model(spec, depth=2, embed_dim=24, num_heads=3)
    ext = DenseExtractor(model, spec, 1, "key", stride=4, head_interleaved=True)
    assert ext.grid(224, 298) == (55, 73)  # 1 + (H - 8) // 4
    captured = {}
    hook = model.blocks[1].attn.qkv.register_forward_hook(lambda m, i, o: captured.setdefault("qkv", o))
    out = ext(torch.randn(1, 3, 24, 28))
    hook.remove()
    k = captured["qkv"][0, 1:, 24:48].numpy()             # [t, heads * d_head], head-major
    expected = k.reshape(-1, 3, 8).transpose(0, 2, 1).reshape(-1, 24)  # channel j * heads + h
    np.testing.assert_array_equal(out[0].numpy(), expected)


def test_patch_normalisation_per_path():
    """DINOv2: every patch feature L2-normalised (GeM on unit vectors); DINO v1: raw for GeM/GAP/GMP,
    normalised inside VLAD."""
    from vprbench.methods.anyloc import AnyLoc

    raw = torch.from_numpy(np.random.default_rng(8).normal(size=(1, 20, 384)).astype(np.float32) * 3)
    fake = lambda batch: raw  # noqa: E731 (stands in for the extractor)
    for backbone, aggregation, expected in [
        ("dinov2_vits14", "gem", pooling.gem(_unit(raw.numpy()))),
        ("dino_vits8", "gem", pooling.gem(raw)),
        ("dino_vits8", "gap", pooling.gap(raw)),
    ]:
        method = AnyLoc(backbone=backbone, weights="random", aggregation=aggregation, layer=1, facet="value")
        method._extractor = fake
        torch.testing.assert_close(method._global(torch.zeros(1, 3, 8, 8)), expected.float(), atol=1e-6, rtol=1e-5)
    centres = np.random.default_rng(9).normal(size=(4, 384)).astype(np.float32)
    method = AnyLoc(backbone="dino_vits8", weights="random", aggregation="vlad", clusters=4, layer=1, facet="key")
    method._extractor, method.centres = fake, torch.from_numpy(centres)
    np.testing.assert_allclose(method._global(torch.zeros(1, 3, 8, 8))[0].numpy(),
                               _np_hard_vlad(raw[0].numpy(), centres), atol=1e-6)


# ---------------------------------------------------------------- PCA, search, recall
def test_pca_whitening_is_sklearn_pca_whiten_then_l2():
    rng = np.random.default_rng(10)
    db = rng.normal(size=(80, 30)) @ rng.normal(size=(30, 30))
    q = rng.normal(size=(20, 30)) @ rng.normal(size=(30, 30))
    mean = db.mean(0)
    _, s, vt = np.linalg.svd(db - mean, full_matrices=False)
    proj = vt[:12] / np.sqrt(s[:12] ** 2 / (len(db) - 1))[:, None]
    exp_db, exp_q = _unit((db - mean) @ proj.T), _unit((q - mean) @ proj.T)
    pca = PCAWhitening(12).fit(db.astype(np.float32))
    ours_db, ours_q = pca.transform(db.astype(np.float32)), pca.transform(q.astype(np.float32))
    # equal up to each component's sign, so every query-database similarity is equal
    signs = np.sign((ours_db * exp_db).sum(0))
    np.testing.assert_allclose(ours_db, exp_db * signs, atol=1e-4)
    np.testing.assert_allclose(ours_q @ ours_db.T, exp_q @ exp_db.T, atol=1e-4)
    with pytest.raises(VPRBenchError, match="larger than the number of database images"):
        PCAWhitening(81).fit(db.astype(np.float32))


def test_search_is_cosine_and_recall_counts_queries_without_positives():
    rng = np.random.default_rng(13)
    db, q = _unit(rng.normal(size=(50, 16))).astype(np.float32), _unit(rng.normal(size=(4, 16))).astype(np.float32)
    _, idx = search(db, q, 5)
    np.testing.assert_array_equal(idx, np.argsort(-(q @ db.T), axis=1, kind="stable")[:, :5])
    positives = [np.array([idx[0, 0]]), np.array([idx[1, 3], 49 if idx[1, 0] != 49 else 48]), np.array([], int),
                 np.array([idx[3, 4]])]
    recall = recall_at_k(first_positive_rank(correct_at(idx, positives)), (1, 4, 5))
    assert recall == {1: 25.0, 4: 50.0, 5: 75.0}  # the query with no positive is a failure at every K
