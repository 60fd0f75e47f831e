"""fp32 CPU linear layers and attention products on oneDNN inside the dense extractor
(vprbench/gemm.py), and every case it must leave to torch's own operators."""
import contextlib

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from vprbench.features.backbones import create_model
from vprbench.features.catalogue import backbone_spec
from vprbench.features.dense import DenseExtractor
from vprbench.gemm import onednn_products

pytestmark = [pytest.mark.skipif(not torch.backends.mkldnn.is_available(), reason="torch built without oneDNN"),
              pytest.mark.filterwarnings("ignore:TF32 acceleration")]  # said by mkldnn.flags() on CPU builds

ONEDNN = "mkldnn._linear_pointwise.default"


@pytest.fixture(autouse=True)
def onednn_here(monkeypatch):
    """The oneDNN path on any CPU (on one without AVX-512 vprbench leaves products to the BLAS)."""
    import vprbench.gemm as gemm

    monkeypatch.setattr(gemm, "onednn_faster", lambda: True)


class Ops(TorchDispatchMode):
    """Names of the operators that ran."""

    def __init__(self):
        super().__init__()
        self.names = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.add(str(func))
        return func(*args, **(kwargs or {}))


def ran(fn):
    with Ops() as ops:
        out = fn()
    return out, ops.names


@pytest.fixture(scope="module")
def vits():
    spec = backbone_spec("dinov3_vits16")  # RoPE, registers, separate q/v biases: timm's path
    torch.manual_seed(0)
    return create_model(spec, depth=3), spec


@pytest.mark.parametrize("facet", ["value", "token"])
def test_the_extractor_computes_its_linear_layers_on_onednn(vits, facet):
    model, spec = vits
    images = torch.randn(2, 3, 64, 48)
    extractor = DenseExtractor(model, spec, 2, facet)
    fast, names = ran(lambda: extractor(images))
    assert ONEDNN in names and "aten.addmm.default" not in names and "aten.mm.default" not in names
    with torch.backends.mkldnn.flags(enabled=False):  # the off switch: torch's own linear
        plain, names = ran(lambda: extractor(images))
    assert ONEDNN not in names and "aten.addmm.default" in names
    # another order of summation only: float32 rounding, relative to the features' scale
    assert (fast - plain).abs().max() <= 1e-5 * plain.abs().max()
    assert torch.equal(extractor(images), fast)  # and deterministic


def test_outside_the_extractor_a_linear_layer_is_untouched(vits):
    model, _ = vits
    x = torch.randn(5, 384)
    _, names = ran(lambda: model.blocks[0].mlp.fc1(x))
    assert ONEDNN not in names


@pytest.mark.parametrize("case", ["float64", "grad", "bfloat16-autocast", "vector"])
def test_what_onednn_does_not_take_runs_as_torch_would(case):
    torch.manual_seed(0)
    layer = torch.nn.Linear(16, 8)
    x = torch.randn(3, 16)
    if case == "float64":
        layer, x = layer.double(), x.double()
    if case == "vector":
        x = x[0]
    context = torch.autocast("cpu", dtype=torch.bfloat16) if case == "bfloat16-autocast" else torch.no_grad()
    if case == "grad":
        context = torch.enable_grad()
    with context:
        expected = layer(x)
        with onednn_products():
            got, names = ran(lambda: layer(x))
    assert ONEDNN not in names
    assert got.dtype == expected.dtype and torch.equal(got, expected)
    if case == "grad":  # autograd still reaches the weights
        got.sum().backward()
        assert layer.weight.grad is not None and layer.weight.grad.abs().sum() > 0


def test_onednn_linear_layers_take_arguments_by_keyword_and_without_bias():
    torch.manual_seed(0)
    x, weight, bias = torch.randn(2, 7, 16), torch.randn(8, 16), torch.randn(8)
    with torch.no_grad(), onednn_products():
        (with_bias, names), (without, _) = ran(lambda: F.linear(x, weight=weight, bias=bias)), ran(lambda: F.linear(x, weight))
    assert ONEDNN in names and with_bias.shape == (2, 7, 8)
    torch.testing.assert_close(with_bias, F.linear(x, weight, bias), rtol=0, atol=1e-5)
    torch.testing.assert_close(without, F.linear(x, weight), rtol=0, atol=1e-5)


def test_products_of_rows_run_on_onednn_and_fall_back_to_numpy():
    """gemm.products (exact search's scores): a @ b.T on oneDNN for C-contiguous float32 rows,
    also read-only ones (a store's lent pages); numpy's matmul otherwise, bit for bit."""
    import numpy as np

    from vprbench.gemm import products

    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((70, 300), dtype=np.float32), rng.standard_normal((90, 300), dtype=np.float32)
    b.flags.writeable = False
    got, names = ran(lambda: products(a, b))
    assert ONEDNN in names and got.shape == (70, 90) and got.dtype == np.float32
    np.testing.assert_allclose(got, a @ b.T, rtol=0, atol=1e-4)  # sums of 300 products of unit normals
    for x, y in ((a.astype(np.float64), b.astype(np.float64)), (a[:, ::2], b[:, ::2])):
        got, names = ran(lambda: products(x, y))
        assert ONEDNN not in names and np.array_equal(got, x @ y.T)
    with torch.backends.mkldnn.flags(enabled=False):
        got, names = ran(lambda: products(a, b))
    assert ONEDNN not in names and np.array_equal(got, a @ b.T)


def qkv(batch=2, heads=3, tokens=450, dim=16, seed=0):
    """Query, key and value as a ViT's attention gets them: views into one fused qkv output."""
    torch.manual_seed(seed)
    return torch.randn(batch, tokens, 3, heads, dim).permute(2, 0, 3, 1, 4).unbind(0)


@pytest.mark.parametrize("scale", [None, 0.3])
def test_attention_from_many_keys_runs_its_products_on_onednn(scale):
    q, k, v = qkv()
    expected = F.scaled_dot_product_attention(q, k, v, scale=scale)
    with torch.no_grad(), onednn_products():
        got, names = ran(lambda: F.scaled_dot_product_attention(q, k, v, scale=scale))
    assert ONEDNN in names and not any("scaled_dot_product" in name for name in names)
    assert got.shape == expected.shape == (2, 3, 450, 16)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-5)  # softmax-weighted means of unit normals
    assert got.transpose(1, 2).is_contiguous()  # (B, T, H, D) memory, as torch's CPU kernel gives it


def test_attention_of_a_few_queries_over_many_keys_runs_on_onednn():
    """Queries and keys of different lengths (an attention-pooling head: one latent query)."""
    _, k, v = qkv()
    q = torch.randn(2, 3, 1, 16)
    expected = F.scaled_dot_product_attention(q, k, v)
    with torch.no_grad(), onednn_products():
        got, names = ran(lambda: F.scaled_dot_product_attention(q, k, v))
    assert ONEDNN in names and got.shape == expected.shape == (2, 3, 1, 16)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-5)


def test_attention_scores_computed_a_few_rows_at_a_time_give_the_same_output(monkeypatch):
    import vprbench.gemm as gemm

    q, k, v = qkv()
    with torch.no_grad(), onednn_products():
        whole = F.scaled_dot_product_attention(q, k, v)
        monkeypatch.setattr(gemm, "SCORE_ELEMENTS", 7 * 450)  # 7 query rows at a time: 65 pieces per head
        pieces = F.scaled_dot_product_attention(q, k, v)
    # float32 rounding of another summation order: up to 8e-7 with torch 2.14's oneDNN, 1.2e-6 with torch 2.6's
    torch.testing.assert_close(pieces, whole, rtol=0, atol=2e-6)


@pytest.mark.parametrize("case", ["few-keys", "mask", "dropout", "causal", "grad", "float64", "grouped", "off"])
def test_attention_oneDNN_does_not_take_runs_as_torch_would(case):
    q, k, v = qkv(tokens=60 if case == "few-keys" else 450)
    kwargs = {"mask": {"attn_mask": torch.zeros(450, 450)}, "dropout": {"dropout_p": 0.5},
              "causal": {"is_causal": True}}.get(case, {})
    if case == "float64":
        q, k, v = q.double(), k.double(), v.double()
    if case == "grouped":  # one key/value head for three query heads
        k, v, kwargs = k[:, :1], v[:, :1], {"enable_gqa": True}
    if case == "grad":
        q = q.detach().requires_grad_()
    context = torch.enable_grad() if case == "grad" else torch.no_grad()
    switch = torch.backends.mkldnn.flags(enabled=False) if case == "off" else contextlib.nullcontext()
    with context:
        torch.manual_seed(1)
        expected = F.scaled_dot_product_attention(q, k, v, **kwargs)
        with switch, onednn_products():
            torch.manual_seed(1)  # dropout draws the same mask
            got, names = ran(lambda: F.scaled_dot_product_attention(q, k, v, **kwargs))
    assert ONEDNN not in names
    assert torch.equal(got, expected)


def test_the_extractor_computes_attention_on_onednn_from_many_tokens(vits):
    model, spec = vits
    images = torch.randn(1, 3, 320, 336)  # 420 patches and 5 prefix tokens
    extractor = DenseExtractor(model, spec, 2, "value")
    fast, names = ran(lambda: extractor(images))
    assert not any("scaled_dot_product" in name for name in names)
    with torch.backends.mkldnn.flags(enabled=False):
        plain, names = ran(lambda: extractor(images))
    assert any("scaled_dot_product" in name for name in names)
    assert (fast - plain).abs().max() <= 1e-5 * plain.abs().max()


def test_inner_products_of_no_queries_write_nothing():
    """search.inner_products (the one place scores are computed) with an empty query slice."""
    import numpy as np

    from vprbench.search.exact import inner_products

    out = np.empty((0, 5), dtype=np.float32)
    inner_products(np.zeros((0, 3), np.float32), np.ones((5, 3), np.float32), out, np.float32(2))
    assert out.shape == (0, 5)


@pytest.mark.parametrize("capability, library", [("AVX512", "oneDNN"), ("AVX2", "BLAS"), ("DEFAULT", "BLAS")])
def test_onednn_is_used_on_the_cpus_where_it_outruns_the_blas(vits, monkeypatch, capability, library):
    """By the vector instructions torch runs (never by a timing): AVX-512 -> oneDNN; else the BLAS,
    which outran oneDNN on an AVX2 EPYC (torch's own linear, its fused attention, numpy's products)."""
    import numpy as np

    import vprbench.gemm as gemm

    monkeypatch.undo()  # the rule itself, not the fixture's
    gemm.onednn_faster.cache_clear()
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: capability)
    try:
        assert gemm.library() == library
        model, spec = vits
        extractor = DenseExtractor(model, spec, 2, "value")
        _, names = ran(lambda: extractor(torch.randn(1, 3, 320, 336)))  # 425 tokens: attention by head on oneDNN
        _, products = ran(lambda: gemm.products(np.ones((3, 4), np.float32), np.ones((5, 4), np.float32)))
        assert (ONEDNN in names) == (ONEDNN in products) == (library == "oneDNN")
        assert any("scaled_dot_product" in name for name in names) == (library == "BLAS")
    finally:
        gemm.onednn_faster.cache_clear()
