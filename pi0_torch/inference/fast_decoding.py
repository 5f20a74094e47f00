"""π0-FAST's decoded tokens with the fused ops of `pi0_torch.kernels` around cuBLAS's GEMMs: nine ops per decoder layer
and token instead of about twenty-three.

A decoded token sees one contiguous range of the k/v cache, `[first[b], its own slot]` (openpi's window, see
`PI0FastForActionGeneration.prepare_decoding`), so attention needs no mask; the token's slot is a device value, so one
CUDA graph serves every step. The GEMMs stay cuBLAS's: at one row per sample they are matrix-vector products over
Gemma 2B's weights, which cuBLAS reads near bandwidth (split-K included) and π0's fused GEMM kernels, tiled for the
suffix's 50 rows, are not tuned for.

It computes what `FastDecoderLayer` computes with a k/v buffer, with fewer roundings in bf16 (RoPE rounds once, the
residual adds round with their GEMM). Where it runs: `PI0FastForActionGeneration.decoding_kernels`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from pi0_torch.inference.layer_pass import SamplingWeights
from pi0_torch.kernels import ops
from pi0_torch.kernels.reference import rms_norm

if TYPE_CHECKING:
    from pi0_torch.models.modeling_pi0_fast import FastDecoderLayer


@dataclass(frozen=True)
class DecodingLayers:
    """What the fused ops read of every decoder layer, made once per call of `generate_tokens` (`prepare_decoding`),
    so that a decoded token takes no view of its own (a view is host time like a launch: 108 of a token's 303 ops
    were these): per layer the attention and MLP norm scales `1 + weight` `[D]`, the projections' weights transposed
    (views) and the k/v caches `[B, S, H]` (views of the decoding cache's buffers)."""

    scales: list[tuple[torch.Tensor, torch.Tensor]]
    weights: list[SamplingWeights]
    keys: list[torch.Tensor]
    values: list[torch.Tensor]
    eps: float

    @classmethod
    def build(cls, weights: Sequence[SamplingWeights], layers: Sequence[FastDecoderLayer], keys: Sequence[torch.Tensor],
              values: Sequence[torch.Tensor]) -> DecodingLayers:
        """`weights`: each layer's (`layer_pass.decoder_sampling_weights`, the call's plain-weights check); `keys`,
        `values`: the decoding cache's per-layer buffers `[B, 1, S, H]`."""
        if not all(each.usable for each in weights):
            raise ValueError("fused decoding runs the GEMMs on the layers' weights, and a layer's projections are not "
                             "plain weights (LoRA, quantized or hooked layers, autocast): decode with fused=None")
        norms = [norm.weight for layer in layers for norm in (layer.block.attn_norm, layer.block.mlp_norm)]
        scales = torch._foreach_add(norms, 1)  # (one op for all of them)
        return cls(list(zip(scales[::2], scales[1::2])), list(weights), [each[:, 0] for each in keys],
                   [each[:, 0] for each in values], layers[0].block.attn_norm.eps)

    def tensors(self) -> list[torch.Tensor]:
        """The tensors made here (the norm scales), not views of the model's or the cache's."""
        return [scale for pair in self.scales for scale in pair]


def decode_layers_(
    layers: DecodingLayers,
    x: torch.Tensor,  # [B, D]: the decoded token's embedding, updated in place
    cos: torch.Tensor,  # [B, 1, H] RoPE of its position
    sin: torch.Tensor,
    first: torch.Tensor,  # long [B]: the first slot the token sees
    slot: torch.Tensor,  # long [1]: its own slot (written here; the last it sees)
) -> torch.Tensor:
    """The decoder layers on one decoded token per sample: writes its k/v at `slot` of every layer's buffers and
    returns `x` (the last layer's output)."""
    batch, head_dim, eps = x.shape[0], layers.keys[0].shape[-1], layers.eps
    ends = slot + 1
    rope_cache_write, range_attention, geglu = (ops.resolved(op, x.device)
                                                for op in (ops.rope_cache_write, ops.range_attention, ops.geglu))
    for (attention_scale, mlp_scale), weights, key_cache, value_cache in zip(layers.scales, layers.weights, layers.keys,
                                                                             layers.values):
        qkv = torch.mm(rms_norm(x, eps, attention_scale), weights.qkv)
        q = rope_cache_write(qkv, cos, sin, key_cache, value_cache, 0, slot)  # [B, N * H]
        attended = range_attention(q.view(batch, 1, -1, head_dim), key_cache, value_cache, first, ends)
        x.addmm_(attended, weights.o)
        x.addmm_(geglu(torch.mm(rms_norm(x, eps, mlp_scale), weights.gate_up)), weights.down)
    return x
