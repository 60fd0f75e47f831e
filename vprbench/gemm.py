"""Linear layers on CPU computed by oneDNN, the GEMM library inside torch, instead of its BLAS.

On CPU, nn.Linear calls the BLAS torch was built with (MKL). On the AMD EPYC (AVX-512) this was
measured on, MKL's fp32 GEMM reaches 90 to 100 GFLOP/s per core at a ViT's shapes, and oneDNN
200: a ViT-S extraction took 62 instead of 102 ms per image. Inside `onednn_linear()`, every fp32
`F.linear` on CPU without autograd or autocast goes to oneDNN's linear (the weight stays an
ordinary tensor: hooks and state dicts see nothing new); anything else runs as it would.
Results differ from nn.Linear's by float32 rounding only (another order of summation).
`torch.backends.mkldnn.flags(enabled=False)` turns it off.
"""
from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch.overrides import TorchFunctionMode


@functools.cache
def _available() -> bool:
    return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def _dense_fp32_cpu(t: torch.Tensor | None) -> bool:
    return t is None or (t.device.type == "cpu" and t.dtype == torch.float32 and t.layout == torch.strided)


def _onednn_can_take(x, weight, bias) -> bool:
    return (
        torch.backends.mkldnn.enabled
        and isinstance(x, torch.Tensor) and isinstance(weight, torch.Tensor) and weight.dim() == 2
        and (bias is None or isinstance(bias, torch.Tensor))
        and x.dim() >= 2 and x.numel() > 0
        and all(_dense_fp32_cpu(t) for t in (x, weight, bias))
        and not (torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, bias)))
        and not torch.is_autocast_enabled("cpu")
    )


class _OneDNNLinear(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is F.linear:
            x, weight = args[0] if args else kwargs["input"], args[1] if len(args) > 1 else kwargs["weight"]
            bias = args[2] if len(args) > 2 else kwargs.get("bias")
            if _onednn_can_take(x, weight, bias):
                return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")
        return func(*args, **kwargs)


@contextlib.contextmanager
def onednn_linear() -> Iterator[None]:
    """Within it (or a function it decorates), fp32 CPU linear layers run on oneDNN (see the module)."""
    if not _available():
        yield
        return
    with _OneDNNLinear():
        yield
