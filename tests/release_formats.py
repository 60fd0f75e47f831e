"""Random timm models written in their authors' release formats: state-dict keys, shapes and
layouts exactly as each release names them, so tests read what users download.

Sources of each layout: DINO and DINOv2 (facebookresearch/dino, dinov2 hub files: timm's keys plus
the unused mask_token; the giant's SwiGLU as mlp.w12/w3; registers as register_tokens beside a
position embedding with a CLS slot); DINOv3 (facebookresearch/dinov3 vision_transformer.py and
layers/: storage_tokens, ls1/ls2.gamma, rope_embed.periods kept in bfloat16, qkv.bias with its
k-masking qkv.bias_mask, local_cls_norm in the satellite ViT-L; the key list of the released
ViT-S/16 is quoted in facebookresearch/dinov3 issue 290, the all-zero biases in issue 195);
Perception Encoder (facebookresearch/perception_models core/vision_encoder/pe.py); C-RADIOv3
(NVIDIA's checkpoint as timm's _convert_radio reads it); SigLIP 2 (big_vision's two-tower .npz,
image tower under params/img/, encoder blocks stacked for lax.scan, as timm's _load_weights reads).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch


def official_state_dict(model, spec) -> dict[str, torch.Tensor]:
    """The release's state dict for `model` (a timm model of `spec`'s architecture). Where the
    conversion to timm is one float operation (the DINOv2-registers CLS position), `model` is
    set to its result, so a loaded file equals `model` exactly."""
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    return WRITERS[spec.family](state, model, spec)


def write_release(model, spec, folder: Path) -> Path:
    """The release file of `model` in `folder`: a .npz for SigLIP 2, else a PyTorch file."""
    if spec.family == "SigLIP 2":
        path = folder / "siglip2_b16_224.npz"
        np.savez(path, **siglip2_npz(model))
        return path
    path = folder / "release.pth"
    torch.save(official_state_dict(model, spec), path)
    return path


def _dino(state, model, spec):
    return state


def _dinov2(state, model, spec):
    state = {k.replace(".mlp.fc1.", ".mlp.w12.").replace(".mlp.fc2.", ".mlp.w3.") if "giant" in spec.timm else k: v
             for k, v in state.items()}
    return {**state, "mask_token": torch.zeros(1, model.embed_dim)}


def _dinov2_registers(state, model, spec):
    cls_position = torch.randn(1, 1, model.embed_dim)
    release_cls = state.pop("cls_token") - cls_position
    with torch.no_grad():
        model.cls_token.copy_(release_cls + cls_position)  # what timm's converter gives back
    state = _dinov2(state, model, spec)
    return {**state, "cls_token": release_cls, "register_tokens": state.pop("reg_token"),
            "pos_embed": torch.cat([cls_position, state.pop("pos_embed")], dim=1)}


def _dinov3(state, model, spec):
    dim = model.embed_dim
    out = {"storage_tokens": state.pop("reg_token"), "mask_token": torch.zeros(1, dim),
           "rope_embed.periods": model.rope.periods.to(torch.bfloat16)}
    for key, value in state.items():
        out[key.replace(".gamma_1", ".ls1.gamma").replace(".gamma_2", ".ls2.gamma")] = value
        if key.endswith("attn.qkv.weight"):  # zero biases; the mask keeps q and v, drops k
            out[key.replace(".weight", ".bias")] = torch.zeros(3 * dim)
            out[key.replace(".weight", ".bias_mask")] = torch.cat([torch.ones(dim), torch.zeros(dim), torch.ones(dim)])
    if spec.tag == "sat493m":  # the satellite ViT-L's norm of local crops' CLS (pretraining only)
        out.update({"local_cls_norm.weight": torch.ones(dim), "local_cls_norm.bias": torch.zeros(dim)})
    return out


def _perception_encoder(state, model, spec):
    """conv1, class_embedding, positional_embedding, transformer.resblocks.N, ln_pre/ln_post; a core
    model's attention pool (probe, nn.MultiheadAttention's packed in_proj, layernorm) and its
    projection `proj` (width x output dim), which timm converts to a head these models leave out."""
    pool = {"attn_pool.latent": "attn_pool.probe", "attn_pool.proj.": "attn_pool.attn.out_proj.",
            "attn_pool.norm.": "attn_pool.layernorm."}
    if "attn_pool.q.weight" in state:
        for part in ("weight", "bias"):
            state[f"attn_pool.attn.in_proj_{part}"] = torch.cat([state.pop(f"attn_pool.q.{part}"),
                                                                 state.pop(f"attn_pool.kv.{part}")])
        state = {next((k.replace(a, b) for a, b in pool.items() if k.startswith(a)), k): v for k, v in state.items()}
        state["proj"] = torch.randn(model.embed_dim, model.embed_dim)
    state = {("ln_post." + k[5:] if k.startswith("norm.") else k): v for k, v in state.items()}
    swaps = [("patch_embed.proj", "conv1"), ("pos_embed", "positional_embedding"), ("blocks.", "transformer.resblocks."),
             ("norm_pre", "ln_pre"), (".norm1.", ".ln_1."), (".norm2.", ".ln_2."), ("attn.qkv.", "attn.in_proj_"),
             ("attn.proj", "attn.out_proj"), ("mlp.fc1", "mlp.c_fc"), ("mlp.fc2", "mlp.c_proj")]
    out = {}
    for key, value in state.items():
        if key == "cls_token":
            out["class_embedding"] = value.reshape(-1)
            continue
        for timm_part, release_part in swaps:
            key = key.replace(timm_part, release_part)
        out[key] = value[0] if key == "positional_embedding" else value
    return out


def _radio(state, model, spec):
    """{"state_dict": radio_model.model.*}: a bias-free linear patch embedder over (C, p, p)
    patches, the 128 x 128 position grid flattened, one token tensor holding CLS and registers."""
    with torch.no_grad():
        model.embeds.proj.bias.zero_()
    dim, patch = model.embed_dim, spec.patch
    prefix = "radio_model.model."
    embedder = state.pop("embeds.proj.weight").reshape(dim, patch, patch, 3).permute(0, 3, 1, 2).flatten(1)
    out = {f"{prefix}patch_generator.embedder.weight": embedder,
           f"{prefix}patch_generator.pos_embed": state.pop("embeds.pos_embed").reshape(1, -1, dim),
           f"{prefix}patch_generator.cls_token.token": torch.cat([state.pop("embeds.cls_token")[0],
                                                                  state.pop("embeds.reg_token")[0]]),
           "radio_model.input_conditioner.norm_mean": torch.zeros(3, 1, 1)}
    state.pop("embeds.proj.bias")
    out.update({prefix + k.replace(".gamma", ".grandma"): v for k, v in state.items()})
    return {"state_dict": out, "args": {"model": "vit_base_patch16_224"}}


WRITERS = {"DINO": _dino, "DINOv2": _dinov2, "DINOv2-registers": _dinov2_registers, "DINOv3": _dinov3,
           "Perception Encoder": _perception_encoder, "RADIO": _radio}


def siglip2_npz(model) -> dict[str, np.ndarray]:
    """big_vision's arrays for a timm SigLIP ViT with its attention-pooling head: flax kernels
    (in, out), attention kernels split per head, blocks stacked along a first axis; a text tower
    and the logit scale/bias beside it, which the image tower's loader leaves alone."""
    sd = {k: v.detach().numpy() for k, v in model.state_dict().items()}
    dim, heads = model.embed_dim, model.blocks[0].attn.num_heads

    def attention(prefix, q, k, v, qb, kb, vb, out, out_bias):
        found = {f"{prefix}{name}/kernel": w.T.reshape(dim, heads, -1) for name, w in (("query", q), ("key", k), ("value", v))}
        found.update({f"{prefix}{name}/bias": b.reshape(heads, -1) for name, b in (("query", qb), ("key", kb), ("value", vb))})
        return {**found, f"{prefix}out/kernel": out.reshape(dim, heads, -1).transpose(1, 2, 0), f"{prefix}out/bias": out_bias}

    def mlp(prefix, source):
        return {f"{prefix}Dense_{i}/{part}": sd[f"{source}fc{i + 1}.weight"].T if part == "kernel" else sd[f"{source}fc{i + 1}.bias"]
                for i in range(2) for part in ("kernel", "bias")}

    blocks = []
    for i in range(len(model.blocks)):
        b = f"blocks.{i}."
        q, k, v = np.split(sd[b + "attn.qkv.weight"], 3)
        qb, kb, vb = np.split(sd[b + "attn.qkv.bias"], 3)
        blocks.append({"LayerNorm_0/scale": sd[b + "norm1.weight"], "LayerNorm_0/bias": sd[b + "norm1.bias"],
                       "LayerNorm_1/scale": sd[b + "norm2.weight"], "LayerNorm_1/bias": sd[b + "norm2.bias"],
                       **attention("MultiHeadDotProductAttention_0/", q, k, v, qb, kb, vb,
                                   sd[b + "attn.proj.weight"], sd[b + "attn.proj.bias"]),
                       **mlp("MlpBlock_0/", b + "mlp.")})
    img = "params/img/"
    arrays = {f"{img}Transformer/encoderblock/{name}": np.stack([block[name] for block in blocks]) for name in blocks[0]}
    pool = "attn_pool."
    pk, pv = np.split(sd[pool + "kv.weight"], 2)
    pkb, pvb = np.split(sd[pool + "kv.bias"], 2)
    arrays.update({
        f"{img}embedding/kernel": sd["patch_embed.proj.weight"].transpose(2, 3, 1, 0),
        f"{img}embedding/bias": sd["patch_embed.proj.bias"], f"{img}pos_embedding": sd["pos_embed"],
        f"{img}Transformer/encoder_norm/scale": sd["norm.weight"], f"{img}Transformer/encoder_norm/bias": sd["norm.bias"],
        f"{img}MAPHead_0/probe": sd[pool + "latent"],
        f"{img}MAPHead_0/LayerNorm_0/scale": sd[pool + "norm.weight"], f"{img}MAPHead_0/LayerNorm_0/bias": sd[pool + "norm.bias"],
        **attention(f"{img}MAPHead_0/MultiHeadDotProductAttention_0/", sd[pool + "q.weight"], pk, pv, sd[pool + "q.bias"],
                    pkb, pvb, sd[pool + "proj.weight"], sd[pool + "proj.bias"]),
        **mlp(f"{img}MAPHead_0/MlpBlock_0/", pool + "mlp."),
        "params/txt/Embed_0/embedding": np.zeros((8, dim), np.float32),
        "params/t": np.array([2.3], np.float32), "params/b": np.array([-10.0], np.float32),
    })
    return arrays
