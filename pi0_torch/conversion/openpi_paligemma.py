"""The openpi leaves π0 and π0-FAST share -- PaliGemma's SigLIP tower and the layers of a Gemma -- and their maps to
ours: what `pi0_torch.conversion.openpi_weights` (π0 / π0.5) and `pi0_torch.conversion.openpi_fast_weights`
(π0-FAST) both build on.

openpi stores every layer stacked on axis 0 and kernels as (in, out); we store one tensor per layer in torch's (out, in)
layout, with q/k/v and gate/up fused. A tree trained with openpi's LoRA variants (`gemma_2b_lora`, `gemma_300m_lora`:
the `*_low_mem_finetune` configs) holds adapter pairs beside the Gemma weights; they are merged into the weights they
adapt ([`openpi_lora_ranks`]). Everything here works one openpi leaf (or one layer of it) at a time through a
[`LeafReader`], so a converter can stream a 12 GB checkpoint with bounded memory.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

NO_LORA: Mapping[tuple[int, str], int] = MappingProxyType({})  # `openpi_lora_ranks` of a tree without adapters

# read(path, layer): the openpi array at `path` (without a trailing "/value"), or only its slice `[layer]`.
LeafReader = Callable[[str, "int | None"], np.ndarray]

IMG = "PaliGemma/img"
VISION_BLOCK = f"{IMG}/Transformer/encoderblock"
VISION_ATTENTION = f"{VISION_BLOCK}/MultiHeadDotProductAttention_0"
LLM = "PaliGemma/llm"
_VISION = "vision_tower"


def strip_value_suffix(path: str) -> str:
    """openpi training checkpoints store nnx state, whose leaf paths end in '/value'; released ones may not."""
    return path[: -len("/value")] if path.endswith("/value") else path


def expert_suffix(expert: int) -> str:
    """The suffix of a Gemma expert's leaves: none for expert 0 (the VLM, π0-FAST's only one), `_1` for π0's action
    expert."""
    return "" if expert == 0 else f"_{expert}"


def vision_openpi_shapes(config: Any, width: int) -> dict[str, tuple[int, ...]]:
    """The SigLIP leaves (tower and head to the Gemma `width`) of a π0 / π0.5 / π0-FAST `config`, with their shapes."""
    W, M, Lv, heads = config.vision_hidden_size, config.vision_intermediate_size, config.vision_num_layers, config.vision_num_heads
    p, tokens = config.patch_size, config.tokens_per_image
    hd = W // heads
    shapes: dict[str, tuple[int, ...]] = {
        f"{IMG}/embedding/kernel": (p, p, 3, W),
        f"{IMG}/embedding/bias": (W,),
        f"{IMG}/pos_embedding": (1, tokens, W),
        f"{IMG}/Transformer/encoder_norm/scale": (W,),
        f"{IMG}/Transformer/encoder_norm/bias": (W,),
        f"{IMG}/head/kernel": (W, width),
        f"{IMG}/head/bias": (width,),
        f"{VISION_BLOCK}/MlpBlock_0/Dense_0/kernel": (Lv, W, M),
        f"{VISION_BLOCK}/MlpBlock_0/Dense_0/bias": (Lv, M),
        f"{VISION_BLOCK}/MlpBlock_0/Dense_1/kernel": (Lv, M, W),
        f"{VISION_BLOCK}/MlpBlock_0/Dense_1/bias": (Lv, W),
        f"{VISION_ATTENTION}/out/kernel": (Lv, heads, hd, W),
        f"{VISION_ATTENTION}/out/bias": (Lv, W),
    }
    for norm in ("LayerNorm_0", "LayerNorm_1"):
        shapes[f"{VISION_BLOCK}/{norm}/scale"] = (Lv, W)
        shapes[f"{VISION_BLOCK}/{norm}/bias"] = (Lv, W)
    for projection in ("query", "key", "value"):
        shapes[f"{VISION_ATTENTION}/{projection}/kernel"] = (Lv, W, heads, hd)
        shapes[f"{VISION_ATTENTION}/{projection}/bias"] = (Lv, heads, hd)
    return shapes


def gemma_layers_openpi_shapes(config: Any, expert: int, width: int, mlp_width: int) -> dict[str, tuple[int, ...]]:
    """The stacked attention and MLP leaves of one Gemma expert (0: the VLM / π0-FAST's only one), with their shapes."""
    L, N, K, H = config.num_hidden_layers, config.num_attention_heads, config.num_key_value_heads, config.head_dim
    s, D, F = expert_suffix(expert), width, mlp_width
    return {
        f"{LLM}/layers/attn/q_einsum{s}/w": (L, N, D, H),
        f"{LLM}/layers/attn/kv_einsum{s}/w": (L, 2, K, D, H),
        f"{LLM}/layers/attn/attn_vec_einsum{s}/w": (L, N, H, D),
        f"{LLM}/layers/mlp{s}/gating_einsum": (L, 2, D, F),
        f"{LLM}/layers/mlp{s}/linear": (L, F, D),
    }


def openpi_lora_ranks(shapes: Mapping[str, tuple[int, ...]]) -> dict[tuple[int, str], int]:
    """The LoRA adapters an openpi tree holds (its leaf shapes): `{(expert, "attn" | "ffn"): rank}` for each Gemma
    expert (0: the VLM, 1: π0's action expert) whose attention or MLP has them; empty for a tree without LoRA."""
    shapes = {strip_value_suffix(path): shape for path, shape in shapes.items()}
    ranks = {}
    for expert in (0, 1):
        s = expert_suffix(expert)
        for kind, path in (("attn", f"{LLM}/layers/attn/q_einsum{s}/lora_a"), ("ffn", f"{LLM}/layers/mlp{s}/gating_einsum_lora_a")):
            if path in shapes:
                ranks[expert, kind] = shapes[path][-1]
    return ranks


def gemma_lora_openpi_shapes(config: Any, expert: int, width: int, mlp_width: int,
                             lora_ranks: Mapping[tuple[int, str], int]) -> dict[str, tuple[int, ...]]:
    """The stacked LoRA leaves of one Gemma expert that `lora_ranks` (`openpi_lora_ranks`) says it has, with their
    shapes (openpi's `lora.Einsum` and `lora.FeedForward`: `lora_a` takes the einsum's input side, `lora_b` gives its
    output side)."""
    L, N, K, H = config.num_hidden_layers, config.num_attention_heads, config.num_key_value_heads, config.head_dim
    s, D, F = expert_suffix(expert), width, mlp_width
    shapes = {}
    if (r := lora_ranks.get((expert, "attn"))) is not None:
        for name, a, b in (("q_einsum", (N, D), (N,)), ("kv_einsum", (2, K, D), (2, K)), ("attn_vec_einsum", (N, H), (N,))):
            shapes[f"{LLM}/layers/attn/{name}{s}/lora_a"] = (L, *a, r)
            shapes[f"{LLM}/layers/attn/{name}{s}/lora_b"] = (L, *b, r, D if name == "attn_vec_einsum" else H)
    if (r := lora_ranks.get((expert, "ffn"))) is not None:
        shapes.update({
            f"{LLM}/layers/mlp{s}/gating_einsum_lora_a": (L, 2, D, r), f"{LLM}/layers/mlp{s}/gating_einsum_lora_b": (L, 2, r, F),
            f"{LLM}/layers/mlp{s}/linear_lora_a": (L, F, r), f"{LLM}/layers/mlp{s}/linear_lora_b": (L, r, D),
        })
    return shapes


def shared_settings_from_openpi_shapes(shapes: Mapping[str, tuple[int, ...]]) -> dict[str, Any]:
    """The settings every member's config has that the leaf shapes tell (`pi0_torch.models.configuration_base`):
    the SigLIP tower, the attention of the Gemma (expert 0) and the vocabulary. `shapes` has no '/value' suffixes."""
    patch, _, _, vision_width = shapes[f"{IMG}/embedding/kernel"]
    tokens = shapes[f"{IMG}/pos_embedding"][1]
    layers, heads, _, head_dim = shapes[f"{LLM}/layers/attn/q_einsum/w"]
    return dict(
        image_size=math.isqrt(tokens) * patch,
        patch_size=patch,
        vision_hidden_size=vision_width,
        vision_intermediate_size=shapes[f"{VISION_BLOCK}/MlpBlock_0/Dense_0/kernel"][2],
        vision_num_layers=shapes[f"{VISION_BLOCK}/LayerNorm_0/scale"][0],
        vision_num_heads=shapes[f"{VISION_ATTENTION}/query/kernel"][2],
        num_hidden_layers=layers,
        num_attention_heads=heads,
        num_key_value_heads=shapes[f"{LLM}/layers/attn/kv_einsum/w"][2],
        head_dim=head_dim,
        vocab_size=shapes[f"{LLM}/embedder/input_embedding"][0],
    )


def as_tensor(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array))


def as_linear_weight(kernel: np.ndarray) -> torch.Tensor:
    """A flax kernel `(in, out)` as a torch `Linear` weight `(out, in)`."""
    return as_tensor(kernel.T)


def iter_openpi_vision_state_dict(read: LeafReader, config: Any) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for the SigLIP tower (`vision_tower.*`) and its head (`image_projection.*`) of a
    π0 / π0.5 / π0-FAST `config`, one layer at a time."""
    W = config.vision_hidden_size
    yield f"{_VISION}.embeddings.patch_embedding.weight", as_tensor(read(f"{IMG}/embedding/kernel", None).transpose(3, 2, 0, 1))
    yield f"{_VISION}.embeddings.patch_embedding.bias", as_tensor(read(f"{IMG}/embedding/bias", None))
    yield f"{_VISION}.embeddings.position_embedding.weight", as_tensor(read(f"{IMG}/pos_embedding", None)[0])
    for i in range(config.vision_num_layers):
        prefix = f"{_VISION}.encoder.layers.{i}"
        for ours, theirs in (("layer_norm1", "LayerNorm_0"), ("layer_norm2", "LayerNorm_1")):
            yield f"{prefix}.{ours}.weight", as_tensor(read(f"{VISION_BLOCK}/{theirs}/scale", i))
            yield f"{prefix}.{ours}.bias", as_tensor(read(f"{VISION_BLOCK}/{theirs}/bias", i))
        for ours, theirs in (("q_proj", "query"), ("k_proj", "key"), ("v_proj", "value")):
            yield f"{prefix}.self_attn.{ours}.weight", as_linear_weight(read(f"{VISION_ATTENTION}/{theirs}/kernel", i).reshape(W, -1))
            yield f"{prefix}.self_attn.{ours}.bias", as_tensor(read(f"{VISION_ATTENTION}/{theirs}/bias", i).reshape(-1))
        yield f"{prefix}.self_attn.out_proj.weight", as_linear_weight(read(f"{VISION_ATTENTION}/out/kernel", i).reshape(-1, W))
        yield f"{prefix}.self_attn.out_proj.bias", as_tensor(read(f"{VISION_ATTENTION}/out/bias", i))
        for ours, theirs in (("fc1", "Dense_0"), ("fc2", "Dense_1")):
            yield f"{prefix}.mlp.{ours}.weight", as_linear_weight(read(f"{VISION_BLOCK}/MlpBlock_0/{theirs}/kernel", i))
            yield f"{prefix}.mlp.{ours}.bias", as_tensor(read(f"{VISION_BLOCK}/MlpBlock_0/{theirs}/bias", i))
    yield f"{_VISION}.post_layernorm.weight", as_tensor(read(f"{IMG}/Transformer/encoder_norm/scale", None))
    yield f"{_VISION}.post_layernorm.bias", as_tensor(read(f"{IMG}/Transformer/encoder_norm/bias", None))
    yield "image_projection.weight", as_linear_weight(read(f"{IMG}/head/kernel", None))
    yield "image_projection.bias", as_tensor(read(f"{IMG}/head/bias", None))


def iter_openpi_layer_weights(read: LeafReader, config: Any, layer: int, expert: int, prefix: str,
                              lora_ranks: Mapping[tuple[int, str], int] = NO_LORA) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield the attention and MLP weights of one Gemma expert's `layer` as `ExpertLayer` names under `prefix`
    (q/k/v and gate/up fused), with the LoRA adapters `lora_ranks` names merged in; its norms are left to the caller.

    openpi's LoRA adds `x A B` to each einsum `x W` (per head for q, k and v), so `W + A B` is merged. The attention's
    product is scaled by alpha / rank, which every openpi variant sets to 1 (alpha = rank; checkpoints do not store
    it), and the MLP's is not scaled at all (`lora.FeedForward`). The attention output's second einsum sums `lora_b`
    over the heads, so its merged update is `A (sum over heads of B)`.
    """
    N, K, H = config.num_attention_heads, config.num_key_value_heads, config.head_dim
    s = expert_suffix(expert)
    attn, mlp = f"{LLM}/layers/attn", f"{LLM}/layers/mlp{s}"
    q = read(f"{attn}/q_einsum{s}/w", layer)  # (N, D, H)
    kv = read(f"{attn}/kv_einsum{s}/w", layer)  # (2, K, D, H)
    attn_vec = read(f"{attn}/attn_vec_einsum{s}/w", layer)  # (N, H, D)
    gating = read(f"{mlp}/gating_einsum", layer)  # (2, D, F): [0] gate (GELU), [1] up
    linear = read(f"{mlp}/linear", layer)  # (F, D)
    if (expert, "attn") in lora_ranks:
        q = q + read(f"{attn}/q_einsum{s}/lora_a", layer) @ read(f"{attn}/q_einsum{s}/lora_b", layer)  # (N, D, r) @ (N, r, H)
        kv = kv + read(f"{attn}/kv_einsum{s}/lora_a", layer) @ read(f"{attn}/kv_einsum{s}/lora_b", layer)
        heads_b = read(f"{attn}/attn_vec_einsum{s}/lora_b", layer).sum(0)  # (N, r, D) -> (r, D)
        attn_vec = attn_vec + read(f"{attn}/attn_vec_einsum{s}/lora_a", layer) @ heads_b  # (N, H, r) @ (r, D)
    if (expert, "ffn") in lora_ranks:
        gating = gating + read(f"{mlp}/gating_einsum_lora_a", layer) @ read(f"{mlp}/gating_einsum_lora_b", layer)
        linear = linear + read(f"{mlp}/linear_lora_a", layer) @ read(f"{mlp}/linear_lora_b", layer)
    D = q.shape[1]
    q_rows = q.transpose(0, 2, 1).reshape(N * H, D)
    k_rows, v_rows = (kv[j].transpose(0, 2, 1).reshape(K * H, D) for j in (0, 1))
    yield f"{prefix}.qkv_proj.weight", as_tensor(np.concatenate([q_rows, k_rows, v_rows]))
    yield f"{prefix}.o_proj.weight", as_linear_weight(attn_vec.reshape(N * H, D))  # head-major rows, then (out, in)
    yield f"{prefix}.gate_up_proj.weight", as_tensor(np.concatenate([gating[0].T, gating[1].T]))
    yield f"{prefix}.down_proj.weight", as_linear_weight(linear)
