"""fp32 matrix products on CPU computed by oneDNN, the GEMM library inside torch, on CPUs where it
outruns the BLAS.

The BLAS libraries the products would otherwise call (MKL under torch's nn.Linear and its CPU
attention kernel, OpenBLAS under numpy) are slower on some CPUs: on the AMD EPYC (AVX-512) this
was measured on, one core reaches 84 to 100 GFLOP/s with MKL, 107 to 115 with OpenBLAS and 176
to 199 with oneDNN at a ViT's and a search's shapes. On another EPYC with AVX-512 (cpu family 25,
model 17) all three run at about 100: there oneDNN gains little, and attention by head costs 0 to
7 %. On an EPYC with AVX2 only (family 25, model 1) oneDNN is the slowest: 62 to 86 GFLOP/s against
MKL's and OpenBLAS's 75 to 94, whole extractions 1.12 to 1.23 times as long. So oneDNN is used where torch
runs its AVX-512 kernels (`onednn_faster`), decided by the CPU, never by timing, so a machine's
results do not depend on its load. Two users:

- `onednn_products()`: inside it, without autograd or autocast, every fp32 CPU `F.linear` goes
  to oneDNN's linear with the layer's own weight (hooks and state dicts see nothing new), and
  so does each head's two products in `F.scaled_dot_product_attention` from
  `ATTENTION_MIN_KEYS` keys on (plain attention: no mask, dropout or causality); anything else
  runs as it would. The dense extractor runs in it.
- `products(a, b)`: a @ b.T of two float32 row-major arrays (exact search's scores).
- `linear(x, weight, bias)`: the one oneDNN call both make.

Results differ from the BLAS's by float32 rounding only (another order of summation).
`torch.backends.mkldnn.flags(enabled=False)` turns both off.
"""
from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch.overrides import TorchFunctionMode

# oneDNN only reads a search's lent rows (read-only pages of a store): torch's warning is moot
warnings.filterwarnings("ignore", message="The given NumPy array is not writable", module=__name__)


@functools.cache
def _available() -> bool:
    """oneDNN's linear is in this torch and computes a small product right (tried once per process:
    on a platform where it fails, everything runs on the BLAS)."""
    if not (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")):
        return False
    a, b = torch.arange(6.0).reshape(2, 3), torch.arange(12.0).reshape(4, 3)
    try:
        return torch.equal(linear(a, b, None), torch.tensor([[5.0, 14.0, 23.0, 32.0], [14.0, 50.0, 86.0, 122.0]]))
    except RuntimeError:
        return False


#: torch's CPU capabilities (`torch.backends.cpu.get_cpu_capability`) on which oneDNN's fp32 products
#: outrun the BLAS's (see the module)
ONEDNN_FASTER_ON = ("AVX512",)


@functools.cache
def onednn_faster() -> bool:
    """Whether this CPU runs oneDNN's products faster than its BLAS's: by the vector instructions
    torch runs here (ATEN_CPU_CAPABILITY may lower them), not by a timing."""
    return torch.backends.cpu.get_cpu_capability() in ONEDNN_FASTER_ON


def onednn_on() -> bool:
    """oneDNN is in this torch, faster on this CPU, and not turned off (torch.backends.mkldnn.flags)."""
    return _available() and torch.backends.mkldnn.enabled and onednn_faster()


def library() -> str:
    """What computes fp32 CPU products here, for a record: "oneDNN" or "BLAS"."""
    return "oneDNN" if onednn_on() else "BLAS"


try:  # whether CPU autocast is on, asked once how: by device since torch 2.4, by its own function before
    torch.is_autocast_enabled("cpu")
    _cpu_autocast = functools.partial(torch.is_autocast_enabled, "cpu")
except TypeError:
    _cpu_autocast = torch.is_autocast_cpu_enabled


def _dense_fp32_cpu(t: torch.Tensor | None) -> bool:
    return t is None or (t.device.type == "cpu" and t.dtype == torch.float32 and t.layout == torch.strided)


def _onednn_can_take(*tensors) -> bool:
    """oneDNN is on; every tensor (None: an absent bias) is a dense fp32 CPU tensor, none with a
    gradient to track; CPU autocast is off."""
    return (
        onednn_on()
        and all(t is None or isinstance(t, torch.Tensor) for t in tensors)
        and all(_dense_fp32_cpu(t) for t in tensors)
        and not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors))
        and not _cpu_autocast()
    )


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """x @ weight.T (+ bias) on oneDNN, as every product here is computed (check `onednn_on()` first)."""
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")


def _plain_linear(input, weight, bias=None, **other):
    """(x, weight, bias) when the call is a linear layer that oneDNN takes, else None."""
    plain = (not other and isinstance(input, torch.Tensor) and isinstance(weight, torch.Tensor)
             and weight.dim() == 2 and input.dim() >= 2 and input.numel() > 0
             and _onednn_can_take(input, weight, bias))
    return (input, weight, bias) if plain else None


#: from this many keys on, attention's products on oneDNN, head by head, beat torch's fused CPU
#: kernel (which calls MKL). Attention alone, one thread: about equal at 257 keys, 1.2 to 1.6 times
#: faster from 401 to 1,531; two threads: 1.0 to 1.4. On a CPU whose oneDNN is no faster than
#: its BLAS it is 1.06 to 1.33 times slower, 0 to 7 % of an extraction (docs/performance.md)
ATTENTION_MIN_KEYS = 400
#: attention's scores are computed this many at a time (16 MB of float32), a few query rows at a time
SCORE_ELEMENTS = 1 << 22


def _plain_attention(query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None,
                     enable_gqa=False, **other):
    """(q, k, v, scale) when the call is plain attention that oneDNN takes, else None."""
    plain = (not other and attn_mask is None and dropout_p == 0.0 and not is_causal and not enable_gqa
             and all(isinstance(t, torch.Tensor) and t.dim() == 4 for t in (query, key, value))
             and query.shape[:2] == key.shape[:2] == value.shape[:2] and key.shape[2] == value.shape[2]
             and query.shape[3] == key.shape[3] and key.shape[2] >= ATTENTION_MIN_KEYS and query.numel() > 0
             and _onednn_can_take(query, key, value))
    return (query, key, value, query.shape[-1] ** -0.5 if scale is None else scale) if plain else None


def _attention(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, scale: float) -> torch.Tensor:
    """softmax(scale q k^T) v, head by head, both products on oneDNN; (B, H, T, D) out with the
    memory of (B, T, H, D), as torch's CPU kernel gives it (a ViT's next reshape copies nothing)."""
    batch, heads, tokens, _ = query.shape
    query, key = query * scale, key.contiguous()  # scaled before the product, as timm's own path
    value_t = value.transpose(-1, -2).contiguous()  # oneDNN's weight: (D, keys)
    out = query.new_empty(batch, tokens, heads, value.shape[-1])
    rows = max(1, SCORE_ELEMENTS // key.shape[2])
    for b in range(batch):
        for h in range(heads):
            q, k, v = query[b, h], key[b, h], value_t[b, h]
            for start in range(0, tokens, rows):
                scores = linear(q[start:start + rows], k, None)
                out[b, start:start + rows, h] = linear(scores.softmax(-1), v, None)
    return out.transpose(1, 2)


#: the torch functions oneDNN takes: (what it takes of a call, what it runs instead)
_TAKEN = {F.linear: (_plain_linear, linear), F.scaled_dot_product_attention: (_plain_attention, _attention)}


class _OneDNNProducts(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        taken = _TAKEN.get(func)
        plain = taken[0](*args, **kwargs) if taken else None
        return taken[1](*plain) if plain is not None else func(*args, **kwargs)


@contextlib.contextmanager
def onednn_products() -> Iterator[None]:
    """Within it (or a function it decorates), fp32 CPU linear layers and attention products run
    on oneDNN (see the module)."""
    if not (_available() and onednn_faster()):
        yield
        return
    with _OneDNNProducts():
        yield


def products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b.T, (M, D) x (N, D) -> (M, N) float32, on oneDNN (torch's threads) when both are
    C-contiguous float32 and oneDNN is on, else numpy's (its BLAS's threads)."""
    if (onednn_on() and a.dtype == b.dtype == np.float32 and a.flags.c_contiguous and b.flags.c_contiguous
            and a.size and b.size):
        return linear(torch.from_numpy(a), torch.from_numpy(b), None).numpy()
    return np.matmul(a, b.T)
