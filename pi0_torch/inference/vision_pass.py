"""SigLIP's pass in fused sampling, on the tower's own weights: what `SiglipVisionModel(pixel_values).last_hidden_state`
computes (transformers' pre-LN encoder, then `post_layernorm`), in nine launches per encoder layer instead of twelve:

- each residual add runs with the LayerNorm after it (`add_layer_norm_`: the next layer's `layer_norm1`, the MLP's
  `layer_norm2`, the last layer's into `post_layernorm`);
- the MLP's first projection takes its tanh GELU in the GEMM's epilogue (`linear_gelu_tanh`);
- the patch positions are added from their table, with no gather (their ids are `0 .. patches - 1`);
- attention is SDPA's, whose CUDA kernels write their output as `[N, T, heads, H]`, so no copy lays it out for the
  o-projection.

The q/k/v projections stay three GEMMs: one would need a packed copy of their weights (107 M parameters at full size).
Used by the fused sampling of `PI0ForActionGeneration` (`ActionSampling.cache_prefix`) where `tower_pass` finds the tower
plain: transformers' own modules, plain weights, no hooks.
"""

from __future__ import annotations

import functools
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from pi0_torch.inference.layer_pass import any_runs_extra_code, plain_linear
from pi0_torch.kernels import ops


def tower_pass(tower: nn.Module) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """`vision_tokens` on `tower`, or None where running its weights is not what calling it does: a projection that
    is not a plain biased `nn.Linear` (LoRA, quantized layers), a replaced module, a hook anywhere in it, or an MLP
    activation other than tanh GELU (π0's SigLIP: `siglip_vision_tower`)."""
    layers = getattr(getattr(tower, "encoder", None), "layers", None)
    embeddings = getattr(tower, "embeddings", None)
    if layers is None or embeddings is None or type(getattr(tower, "post_layernorm", None)) is not nn.LayerNorm:
        return None
    if getattr(getattr(tower, "config", None), "hidden_act", None) != "gelu_pytorch_tanh":
        return None
    if type(embeddings.patch_embedding) is not nn.Conv2d or type(embeddings.position_embedding) is not nn.Embedding:
        return None
    if any_runs_extra_code(tower):
        return None
    for layer in layers:  # (by `_modules`, not `nn.Module.__getattr__`: every eager call checks 27 layers)
        modules = layer._modules
        attention, mlp = modules["self_attn"]._modules, modules["mlp"]._modules
        linears = [attention[name] for name in ("q_proj", "k_proj", "v_proj", "out_proj")] + [mlp["fc1"], mlp["fc2"]]
        if not all(plain_linear(linear, bias=True) for linear in linears):
            return None
        if type(modules["layer_norm1"]) is not nn.LayerNorm or type(modules["layer_norm2"]) is not nn.LayerNorm:
            return None
    return functools.partial(vision_tokens, tower)


def vision_tokens(tower: nn.Module, pixel_values: torch.Tensor) -> torch.Tensor:
    """SigLIP's patch tokens `[N, T, D]` of images `[N, 3, H, W]` (see the module docstring)."""
    embeddings, layers = tower.embeddings, tower.encoder.layers
    patches = embeddings.patch_embedding(pixel_values.to(embeddings.patch_embedding.weight.dtype))  # [N, D, grid, grid]
    images, width = patches.shape[:2]
    tokens = patches.shape[2] * patches.shape[3]
    hidden = patches.new_empty(images * tokens, width)  # (the residual stream, row-major: the sum lands there directly)
    torch.add(patches.flatten(2).transpose(1, 2), embeddings.position_embedding.weight, out=hidden.view(images, tokens, width))
    first_norm = layers[0].layer_norm1
    normed = F.layer_norm(hidden, (width,), first_norm.weight, first_norm.bias, first_norm.eps)
    for index, layer in enumerate(layers):
        attention, mlp = layer.self_attn, layer.mlp
        q, k, v = (torch.addmm(linear.bias, normed, linear.weight.t()).view(images, tokens, -1, attention.head_dim).transpose(1, 2)
                   for linear in (attention.q_proj, attention.k_proj, attention.v_proj))  # [N, heads, T, H]
        attended = F.scaled_dot_product_attention(q, k, v, scale=attention.scale).transpose(1, 2).reshape(hidden.shape)
        projected = torch.addmm(attention.out_proj.bias, attended, attention.out_proj.weight.t())
        normed = add_layer_norm_(hidden, projected, layer.layer_norm2)
        projected = torch.addmm(mlp.fc2.bias, linear_gelu_tanh(normed, mlp.fc1), mlp.fc2.weight.t())
        normed = add_layer_norm_(hidden, projected, layers[index + 1].layer_norm1 if index + 1 < len(layers) else tower.post_layernorm)
    return normed.view(images, tokens, width)


def add_layer_norm_(residual: torch.Tensor, y: torch.Tensor, norm: nn.LayerNorm) -> torch.Tensor:
    """`residual += y`; returns `norm(residual)` (one fused op)."""
    return ops.call(ops.add_layer_norm_, residual, y, norm.weight, norm.bias, norm.eps)


def linear_gelu_tanh(x: torch.Tensor, linear: nn.Linear) -> torch.Tensor:
    """`gelu_tanh(linear(x))`. On CUDA (and counted on the meta device as CUDA runs it) one `_addmm_activation`, whose
    GELU is the tanh one there: cuBLASLt's epilogue, or `gelu_(approximate="tanh")` after the GEMM where cuBLASLt cannot
    take it. Elsewhere the GEMM and `F.gelu`: the CPU's `_addmm_activation` computes the erf GELU."""
    if x.device.type in ("cuda", "meta"):
        return torch._addmm_activation(linear.bias, x, linear.weight.t(), use_gelu=True)
    return F.gelu(torch.addmm(linear.bias, x, linear.weight.t()), approximate="tanh")
