"""Dense extraction per backbone against the GEMM bound, on CPU (random weights).

    python tests/benchmarks/backbone_speed.py [--rounds 5] [--batch 4] [--size 224 | --size 480 640]

For each entry at ViT-S/B size: the FLOPs of one extraction (value facet of the last block,
counted by torch's FlopCounterMode: every matmul, convolution and attention product up to the
point where the extractor stops), the time of one extraction, and the bound FLOPs / (the
machine's best measured fp32 GEMM rate at that backbone's own largest matrix shape, measured
just before and after each extraction). Three GEMMs are measured: torch.mm (the BLAS torch was
built with, MKL), oneDNN's linear as the extractor calls it (vprbench/gemm.py), and oneDNN's
linear with its weight reordered once into oneDNN's own blocked layout (as compilers prepare a
frozen model's weights; 4 to 9 % faster than the plain weight at these shapes on one CPU, 3 to
7 % on another); the bound takes the fastest, whichever it is on the machine. Rounds are
interleaved (every backbone once per round, in one order) so load on the machine hits all alike;
"of bound" is the median over rounds of bound / time.
With one thread the clock is the process's CPU time (on a shared machine, the time it
computed rather than the time it waited for a core); with several threads, wall time.
"GEMMs alone" replays the extraction's own matrix products, nothing else: every linear (oneDNN's,
or the BLAS's where gemm.py leaves products to it) and convolution call with its recorded arguments,
and torch's fused attention kernel (all of attention where the BLAS computes products, else below
gemm.ATTENTION_MIN_KEYS keys) as its two products per head, on the library the extractor uses
(gemm.library()). Its share of the bound is
the most the extraction could reach with these GEMMs if everything else (softmax, GELU, norms,
copies) took no time. Also:
the DINOv2 path as it is (official position resampling, hand-written token path) against
timm's forward_intermediates path (the one every other family takes) on the same model and layer.
"""
from __future__ import annotations

import argparse
import functools
import statistics
import time

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from vprbench.features.backbones import create_model
from vprbench.features.catalogue import backbone_spec
from vprbench.features.dense import DenseExtractor
from vprbench.gemm import library, linear, onednn_on

ENTRIES = ["dinov2_vits14", "dinov2_vitb14", "dinov2_vits14_reg", "dinov2_vitb14_reg", "dinov3_vits16",
           "dinov3_vitb16", "pe_spatial_s16", "pe_spatial_b16", "radio_v3_b16", "siglip2_b16", "dino_vitb16"]
#: (entry, layer) of the issue's comparison with today's DINOv2 path
DINOV2_PATHS = [("dinov2_vits14", 11), ("dinov2_vitb14", 8)]


#: the clock: CPU time of this process with one thread (the time it computed, not the time it
#: waited for a CPU other jobs held), wall time with several threads (CPU time would add them up)
CLOCK = {"fn": time.process_time}


def timed(fn, repeat: int = 1) -> float:
    start = CLOCK["fn"]()
    for _ in range(repeat):
        fn()
    return (CLOCK["fn"]() - start) / repeat


def rate(product, rows: int, width: int, hidden: int) -> float:
    """FLOP/s of `product`, a (rows x width) @ (width x hidden) GEMM."""
    product()
    flop = 2 * rows * width * hidden
    return flop / timed(product, max(1, int(2e9 / flop)))


#: each GEMM's product of a (rows x width) input and a (hidden x width) weight, set up once;
#: the bound takes the fastest
GEMMS = {
    "torch.mm": lambda a, weight: functools.partial(torch.mm, a, weight.T.contiguous()),
    "oneDNN": lambda a, weight: functools.partial(linear, a, weight, None),  # as the extractor calls it
    "oneDNN, packed weight": lambda a, weight: functools.partial(
        linear, a, torch.ops.mkldnn._reorder_linear_weight(weight, len(a)), None),
}


def gemm_rates(shape: tuple[int, int, int]) -> list[float]:
    """FLOP/s of each of GEMMS at the backbone's largest shape (tokens x width) @ (width x hidden),
    in its order."""
    rows, width, hidden = shape
    a, weight = torch.randn(rows, width), torch.randn(hidden, width)
    return [rate(product(a, weight), *shape) for product in GEMMS.values()]


def extractor(name: str, layer: int | None = None, facet: str = "value", path: str | None = None):
    spec = backbone_spec(name)
    if path == "timm":  # timm's own embedding, at any input size
        spec = spec.model_copy(update={"position_interpolation": path,
                                       "timm_kwargs": {**spec.timm_kwargs, "dynamic_img_size": True}})
    torch.manual_seed(0)
    model = create_model(spec)
    return DenseExtractor(model, spec, spec.depth - 1 if layer is None else layer, facet), spec


def flops(run) -> int:
    """FLOPs of `run` with torch's own linear layers and attention's math kernel: the counter
    knows no formula for oneDNN's linear nor for torch's fused CPU attention kernel (which it
    counted as 0 FLOPs)."""
    with (torch.backends.mkldnn.flags(enabled=False), sdpa_kernel(SDPBackend.MATH),
          FlopCounterMode(display=False) as counter):
        run()
    return counter.get_total_flops()


_PRODUCTS = (torch.ops.mkldnn._linear_pointwise.default, torch.ops.aten.convolution.default,
             torch.ops.aten.addmm.default, torch.ops.aten.mm.default, torch.ops.aten.bmm.default)
_FUSED_ATTENTION = torch.ops.aten._scaled_dot_product_flash_attention_for_cpu.default


class _Products(TorchDispatchMode):
    """Records the matrix products an extraction calls, to replay them alone."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _PRODUCTS:
            self.calls.append((func, args, kwargs))
        elif func == _FUSED_ATTENTION:  # its two products per head, as oneDNN computes them
            query, key, value = args[:3]
            key, value_t = key.contiguous(), value.transpose(-1, -2).contiguous()
            for b in range(query.shape[0]):
                for h in range(query.shape[1]):
                    self.calls.append((_attention_products, (query[b, h], key[b, h], value_t[b, h]), {}))
        return func(*args, **kwargs)


def _attention_products(query, key, value_t):
    if onednn_on():
        return linear(linear(query, key, None), value_t, None)
    return torch.mm(torch.mm(query, key.T), value_t.T)


def gemms_alone(run):
    """A function that replays the matrix products `run` calls, and nothing else."""
    with torch.no_grad(), _Products() as recorded:
        run()

    def replay():
        for func, args, kwargs in recorded.calls:
            func(*args, **kwargs)
    return replay


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--size", type=int, nargs="+", default=[224], help="side, or height and width, in pixels")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, torch.get_num_threads()])
    args = parser.parse_args()
    if len(args.size) > 2:
        parser.error("--size takes a side, or a height and a width")
    height, width = (args.size * 2)[:2]

    def images_for(spec):  # the largest multiple of the patch in each direction
        return torch.randn(args.batch, 3, height // spec.patch * spec.patch, width // spec.patch * spec.patch)

    cases = {}  # key: (extraction, FLOPs, largest GEMM shape or None, its GEMMs alone)
    for name in ENTRIES:
        ex, spec = extractor(name)
        images = images_for(spec)
        tokens = args.batch * ((height // spec.patch) * (width // spec.patch) + spec.prefix_tokens)
        hidden = ex.model.blocks[0].mlp.fc1.out_features
        run = functools.partial(ex, images)
        cases[name] = (run, flops(run), (tokens, spec.width, hidden), gemms_alone(run))
    for name, layer in DINOV2_PATHS:
        for path in ("dino", "timm"):
            ex, spec = extractor(name, layer, path=path)
            run = functools.partial(ex, images_for(spec))
            cases[f"{name} L{layer} {path}"] = (run, flops(run), None, None)

    for threads in args.threads:
        torch.set_num_threads(threads)
        CLOCK["fn"] = time.process_time if threads == 1 else time.perf_counter
        times = {key: [] for key in cases}
        alone = {key: [] for key, case in cases.items() if case[3]}  # time of its GEMMs alone, per round
        rates = {key: [] for key in alone}  # GEMMS' rates, per round
        for _ in range(args.rounds):
            for key, (run, count, shape, replay) in cases.items():
                with torch.no_grad():
                    run()  # warm
                    before = gemm_rates(shape) if shape else None
                    times[key].append(timed(run))
                    if shape:  # the GEMM rates measured just before and after the extraction they bound
                        alone[key].append(timed(replay))
                        after = gemm_rates(shape)
                        rates[key].append([(b + a) / 2 for b, a in zip(before, after)])
        clock = "CPU time of the process" if threads == 1 else "wall time"
        print(f"\n## {threads} thread(s), batch {args.batch} at {height}x{width}px, {clock}, medians of {args.rounds} "
              f"interleaved rounds; products on {library()} ({torch.backends.cpu.get_cpu_capability()})")
        print("| backbone | GFLOP per image | ms per image | " + " | ".join(f"{g} GFLOP/s" for g in GEMMS)
              + " | bound ms per image (fastest GEMM) | of bound | its GEMMs alone, ms per image | they, of bound |")
        print("|---" * (7 + len(GEMMS)) + "|")
        for key, (run, count, shape, replay) in cases.items():
            per_image = statistics.median(times[key]) / args.batch
            gflop = count / args.batch / 1e9
            if not shape:
                print(f"| {key} | {gflop:.2f} | {per_image * 1e3:.1f} |" + " |" * (4 + len(GEMMS)))
                continue
            medians = [statistics.median(r[i] for r in rates[key]) for i in range(len(GEMMS))]
            bounds = [count / max(r) for r in rates[key]]  # bound time per round
            of_bound = statistics.median(b / t for b, t in zip(bounds, times[key]))
            alone_of_bound = statistics.median(b / t for b, t in zip(bounds, alone[key]))
            print(f"| {key} | {gflop:.2f} | {per_image * 1e3:.1f} | "
                  + "".join(f"{r / 1e9:.1f} | " for r in medians)
                  + f"{gflop / max(medians) * 1e12:.1f} | {of_bound:.0%} | "
                  f"{statistics.median(alone[key]) / args.batch * 1e3:.1f} | {alone_of_bound:.0%} |")
        for name, layer in DINOV2_PATHS:
            pair = [times[f"{name} L{layer} {path}"] for path in ("dino", "timm")]
            ratio = statistics.median(t / d for d, t in zip(*pair))
            print(f"\n{name} layer {layer}: timm's forward_intermediates path / the DINOv2 path, per round: "
                  f"median {ratio:.2f}")


if __name__ == "__main__":
    main()
