"""fp32 matrix products on CPU computed by oneDNN, the GEMM library inside torch, where it can.

The BLAS libraries the products would otherwise call (MKL under torch's nn.Linear, OpenBLAS
under numpy) are slower on some CPUs: on the AMD EPYC (AVX-512) this was measured on, one core
reaches 84 to 100 GFLOP/s with MKL, 107 to 115 with OpenBLAS and 176 to 199 with oneDNN at a
ViT's and a search's shapes. Two users:

- `onednn_linear()`: inside it, every fp32 `F.linear` on CPU without autograd or autocast goes
  to oneDNN's linear with the layer's own weight (hooks and state dicts see nothing new);
  anything else runs as it would. The dense extractor runs in it.
- `products(a, b)`: a @ b.T of two float32 row-major arrays (exact search's scores).

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
        return torch.equal(_linear(a, b, None), torch.tensor([[5.0, 14.0, 23.0, 32.0], [14.0, 50.0, 86.0, 122.0]]))
    except RuntimeError:
        return False


def onednn_on() -> bool:
    """oneDNN is in this torch and not turned off (torch.backends.mkldnn.flags)."""
    return _available() and torch.backends.mkldnn.enabled


try:  # whether CPU autocast is on, asked once how: by device since torch 2.4, by its own function before
    torch.is_autocast_enabled("cpu")
    _cpu_autocast = functools.partial(torch.is_autocast_enabled, "cpu")
except TypeError:
    _cpu_autocast = torch.is_autocast_cpu_enabled


def _dense_fp32_cpu(t: torch.Tensor | None) -> bool:
    return t is None or (t.device.type == "cpu" and t.dtype == torch.float32 and t.layout == torch.strided)


def _onednn_can_take(x, weight, bias) -> bool:
    return (
        onednn_on()
        and isinstance(x, torch.Tensor) and isinstance(weight, torch.Tensor) and weight.dim() == 2
        and (bias is None or isinstance(bias, torch.Tensor))
        and x.dim() >= 2 and x.numel() > 0
        and all(_dense_fp32_cpu(t) for t in (x, weight, bias))
        and not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, bias)))
        and not _cpu_autocast()
    )


def _linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")


class _OneDNNLinear(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is F.linear:
            x, weight = args[0] if args else kwargs["input"], args[1] if len(args) > 1 else kwargs["weight"]
            bias = args[2] if len(args) > 2 else kwargs.get("bias")
            if _onednn_can_take(x, weight, bias):
                return _linear(x, weight, bias)
        return func(*args, **kwargs)


@contextlib.contextmanager
def onednn_linear() -> Iterator[None]:
    """Within it (or a function it decorates), fp32 CPU linear layers run on oneDNN (see the module)."""
    if not _available():
        yield
        return
    with _OneDNNLinear():
        yield


def products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b.T, (M, D) x (N, D) -> (M, N) float32, on oneDNN (torch's threads) when both are
    C-contiguous float32 and oneDNN is on, else numpy's (its BLAS's threads)."""
    if (onednn_on() and a.dtype == b.dtype == np.float32 and a.flags.c_contiguous and b.flags.c_contiguous
            and a.size and b.size):
        return _linear(torch.from_numpy(a), torch.from_numpy(b), None).numpy()
    return np.matmul(a, b.T)
