"""Dense (per-patch) features from one block and facet of a ViT, as AnyLoc extracts them.

The forward pass is written out here (patch embedding, official position-embedding
interpolation, blocks) so it stops right after the requested block: for a q/k/v facet a
hook on that block's fused qkv linear captures its output and ends the pass; later
blocks never run.
"""
from __future__ import annotations

import math
import threading

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import VPRBenchError
from ..gemm import onednn_products
from .allocator import keep_freed_memory
from .catalogue import BackboneEntry

FACETS = ("query", "key", "value", "token")


class _Stop(Exception):
    """Raised by the qkv hook to end the forward pass once the facet is captured."""


def interpolate_pos_embed(pos_embed: torch.Tensor, grid: tuple[int, int], num_prefix: int = 1) -> torch.Tensor:
    """Resample a square patch position embedding to `grid` (rows, cols) as DINO/DINOv2 do.

    Bicubic, align_corners=False, no antialiasing, driven by scale_factor = (grid + 0.1) / M
    (M = side of the trained grid), so the sampling follows that scale and not the output
    size ratio. Returned unchanged for an M x M grid.
    """
    prefix, patches = pos_embed[:, :num_prefix], pos_embed[:, num_prefix:]
    n = patches.shape[1]
    m = int(math.sqrt(n))
    if m * m != n:
        raise VPRBenchError(f"Position embedding of {n} patches is not a square grid")
    if tuple(grid) == (m, m):
        return pos_embed
    dim = patches.shape[-1]
    dtype = patches.dtype
    resampled = F.interpolate(
        patches.float().reshape(1, m, m, dim).permute(0, 3, 1, 2),
        scale_factor=((grid[0] + 0.1) / m, (grid[1] + 0.1) / m),
        mode="bicubic",
        align_corners=False,
        antialias=False,
    )
    if tuple(resampled.shape[-2:]) != tuple(grid):  # the 0.1 offset guarantees this
        raise RuntimeError(f"position embedding resampled to {tuple(resampled.shape[-2:])}, expected {grid}")
    resampled = resampled.permute(0, 2, 3, 1).reshape(1, -1, dim).to(dtype)
    return torch.cat([prefix, resampled], dim=1)


def patch_grid(height: int, width: int, patch: int, stride: int) -> tuple[int, int]:
    """(rows, columns) of patch features of an input of height x width pixels (a multiple of the patch)."""
    return 1 + (height - patch) // stride, 1 + (width - patch) // stride


class DenseExtractor(nn.Module):
    """Per-patch features of block `layer` (0-based) and `facet` of a timm ViT.

    `stride` < patch size runs overlapping patches (the DINO v1 extractor's stride 4).
    `head_interleaved` orders q/k/v channels as the DINO v1 extractor does (channel
    j*heads + h, i.e. dims within a head vary slowest); otherwise the natural [q|k|v] thirds.
    Threads may share an extractor or its model: each pass's hook acts in its own thread only.
    """

    def __init__(self, model: nn.Module, spec: BackboneEntry, layer: int, facet: str, *,
                 stride: int | None = None, head_interleaved: bool = False):
        super().__init__()
        depth = len(model.blocks)
        if facet not in FACETS:
            raise VPRBenchError(f"Unknown facet {facet!r}: use one of {', '.join(FACETS)}.")
        if not isinstance(layer, int) or isinstance(layer, bool) or not 0 <= layer < depth:
            raise VPRBenchError(
                f"Layer {layer!r} is out of range for {spec.name}: it has {depth} blocks, "
                f"valid layers are 0..{depth - 1} (0-based)."
            )
        attn = getattr(model.blocks[layer], "attn", None)
        if facet != "token" and not (attn is not None and (getattr(attn, "qkv", None) is not None
                                                           or getattr(attn, "q_proj", None) is not None)):
            # a manifest may list q/k/v for an attention kind without them (parallel blocks)
            raise VPRBenchError(f"Facet {facet!r}: block {layer} of {spec.name} ({type(model.blocks[layer]).__name__}) "
                                "has no separate query/key/value projection; use facet token.")
        self.model, self.spec, self.layer, self.facet = model, spec, layer, facet
        keep_freed_memory()  # every block's tensors reuse the last one's memory
        self.stride = stride or spec.patch
        if spec.patch % self.stride:
            raise VPRBenchError(f"stride {self.stride} must divide the patch size {spec.patch} of {spec.name}")
        self.head_interleaved = head_interleaved
        self.num_prefix = getattr(model, "num_prefix_tokens", 1)
        self.dim = model.embed_dim

    def grid(self, height: int, width: int) -> tuple[int, int]:
        return patch_grid(height, width, self.spec.patch, self.stride)

    def _tokens(self, images: torch.Tensor) -> torch.Tensor:
        """Patch embedding + prefix tokens + interpolated position embedding."""
        m = self.model
        proj = m.patch_embed.proj
        x = F.conv2d(images, proj.weight, proj.bias, stride=self.stride)
        grid = tuple(x.shape[-2:])
        x = m.patch_embed.norm(x.flatten(2).transpose(1, 2))
        prefix = [m.cls_token.expand(x.shape[0], -1, -1)]
        if getattr(m, "reg_token", None) is not None:
            prefix.append(m.reg_token.expand(x.shape[0], -1, -1))
        if getattr(m, "no_embed_class", False):  # DINOv2 with registers: prefix tokens carry no pos-embed
            x = x + interpolate_pos_embed(m.pos_embed, grid, num_prefix=0)
            x = torch.cat(prefix + [x], dim=1)
        else:
            x = torch.cat(prefix + [x], dim=1)
            x = x + interpolate_pos_embed(m.pos_embed, grid, num_prefix=1)
        return m.norm_pre(m.pos_drop(x))

    @torch.no_grad()
    @onednn_products()
    def forward(self, images: torch.Tensor, keep_prefix: bool = False) -> torch.Tensor:
        """(B, 3, H, W) -> (B, patches, D) raw facet features (CLS/register tokens dropped
        unless `keep_prefix`)."""
        if self.spec.position_interpolation == "timm":
            return self._intermediate(images, keep_prefix)
        x = self._tokens(images)
        block = self.model.blocks[self.layer]
        for blk in self.model.blocks[: self.layer]:
            x = blk(x)
        if self.facet == "token":
            out = block(x)
        else:
            captured, caller = {}, threading.get_ident()

            def hook(_module, _inputs, output):
                if threading.get_ident() == caller:  # not another thread's pass through a shared model
                    captured["qkv"] = output
                    raise _Stop

            handle = block.attn.qkv.register_forward_hook(hook)
            try:
                block(x)
            except _Stop:
                pass
            finally:
                handle.remove()
            out = self._facet(captured["qkv"])
        return out if keep_prefix else out[:, self.num_prefix:]

    def _facet(self, qkv: torch.Tensor) -> torch.Tensor:
        index = FACETS.index(self.facet)
        b, t, three_d = qkv.shape
        d = three_d // 3
        part = qkv[..., index * d:(index + 1) * d]
        if not self.head_interleaved:
            return part
        heads = self.model.blocks[self.layer].attn.num_heads
        # (B, T, heads, d_head) -> (B, T, d_head, heads): channel j*heads + h
        return part.reshape(b, t, heads, d // heads).transpose(2, 3).reshape(b, t, d)

    # ------------------------------------------------ timm's own embedding (RoPE, registers, ...)
    def _check_size(self, images: torch.Tensor) -> None:
        height, width = images.shape[-2:]
        if height % self.spec.patch or width % self.spec.patch:
            raise VPRBenchError(f"Input of {height}x{width} pixels is not a multiple of the patch {self.spec.patch} "
                                f"of {self.spec.name}; resize or crop it to a multiple of {self.spec.patch}.")

    def _intermediate(self, images: torch.Tensor, keep_prefix: bool) -> torch.Tensor:
        """timm's `forward_intermediates` up to block `layer` (later blocks never run); a q/k/v
        facet is computed by a pre-hook on that block's attention, which then ends the pass."""
        self._check_size(images)
        if self.stride != self.spec.patch:
            raise VPRBenchError(f"{self.spec.name} runs at its patch stride {self.spec.patch} only.")
        if self.facet == "token":
            found = self.model.forward_intermediates(images, indices=[self.layer], stop_early=True, norm=False,
                                                     output_fmt="NLC", intermediates_only=True,
                                                     return_prefix_tokens=self.num_prefix > 0)[0]
            patches, prefix = found if isinstance(found, tuple) else (found, None)
            return torch.cat([prefix, patches], dim=1) if keep_prefix and prefix is not None else patches
        captured, caller = {}, threading.get_ident()

        def hook(attn, args, kwargs):
            if threading.get_ident() == caller:  # not another thread's pass through a shared model
                captured.update(attention_qkv(attn, args[0], kwargs.get("rope")))
                raise _Stop

        handle = self.model.blocks[self.layer].attn.register_forward_pre_hook(hook, with_kwargs=True)
        try:
            self.model.forward_intermediates(images, indices=[self.layer], stop_early=True, intermediates_only=True,
                                             output_fmt="NLC")
        except _Stop:
            pass
        finally:
            handle.remove()
        out = captured[self.facet]
        return out if keep_prefix else out[:, self.num_prefix:]

    @torch.no_grad()
    @onednn_products()
    def cls_token(self, images: torch.Tensor) -> torch.Tensor:
        """The final-norm CLS token (the backbone's global output), unnormalised."""
        if self.spec.position_interpolation == "timm":
            self._check_size(images)
            _, prefix = self.model.forward_intermediates(images, indices=[len(self.model.blocks) - 1], norm=True,
                                                         output_fmt="NLC", intermediates_only=True,
                                                         return_prefix_tokens=True)[0]
            return prefix[:, 0]
        x = self._tokens(images)
        for blk in self.model.blocks:
            x = blk(x)
        return self.model.norm(x)[:, 0]


def attention_qkv(attn: nn.Module, x: torch.Tensor, rope: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """{"query", "key", "value"}: (B, N, heads * head_dim) as timm's attention computes them
    before the product: fused qkv (with EVA/DINOv3's separate q/v biases) or separate
    projections, q/k norms, and RoPE on the query and key of the patch tokens (not the prefix)."""
    b, n, _ = x.shape
    heads = attn.num_heads
    if getattr(attn, "qkv", None) is not None:
        if getattr(attn, "q_bias", None) is not None:
            qkv = F.linear(x, attn.qkv.weight, torch.cat((attn.q_bias, attn.k_bias, attn.v_bias)))
        else:
            qkv = attn.qkv(x)
        q, k, v = qkv.reshape(b, n, 3, heads, -1).permute(2, 0, 3, 1, 4).unbind(0)
    else:
        q, k, v = (proj(x).reshape(b, n, heads, -1).transpose(1, 2) for proj in (attn.q_proj, attn.k_proj, attn.v_proj))
    q, k = attn.q_norm(q), attn.k_norm(k)
    if rope is not None:
        from timm.layers import apply_rot_embed_cat

        npt, half = attn.num_prefix_tokens, getattr(attn, "rotate_half", False)
        q = torch.cat([q[:, :, :npt], apply_rot_embed_cat(q[:, :, npt:], rope, half=half)], dim=2).type_as(v)
        k = torch.cat([k[:, :, :npt], apply_rot_embed_cat(k[:, :, npt:], rope, half=half)], dim=2).type_as(v)
    return {name: t.transpose(1, 2).reshape(b, n, -1) for name, t in (("query", q), ("key", k), ("value", v))}
