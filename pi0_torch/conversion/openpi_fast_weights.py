"""openpi π0-FAST parameter names and layouts -> ours (`PI0FastForActionGeneration`).

A π0-FAST tree is PaliGemma alone: the same SigLIP leaves as π0 and one Gemma (`PaliGemma/llm/...` without the
`_1` expert leaves and without action heads); its LM head is the token embedding. The SigLIP and per-layer Gemma
maps are π0's (`pi0_torch.conversion.openpi_weights`); `load_openpi_params`, `check_openpi_shapes`,
`config_from_openpi_shapes` and `iter_openpi_state_dict` there hand π0-FAST trees and configs to this module.

```python
>>> import numpy as np
>>> from pi0_torch import PI0FastForActionGeneration
>>> from pi0_torch.conversion.openpi_weights import config_from_openpi_shapes, load_openpi_params
>>> arrays = dict(np.load("tests/fixtures/openpi/pi0_fast_small/params_flat.npz"))
>>> config = config_from_openpi_shapes({k: v.shape for k, v in arrays.items()})
>>> type(config).__name__, config.hidden_size, config.vocab_size
('PI0FastConfig', 64, 1100)
>>> load_openpi_params(PI0FastForActionGeneration(config), arrays)

```
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import torch

from pi0_torch.conversion.openpi_weights import (
    _ATTN,
    _BLOCK,
    _IMG,
    _LLM,
    LeafReader,
    _t,
    gemma_layers_openpi_shapes,
    iter_openpi_layer_weights,
    iter_openpi_vision_state_dict,
    strip_value_suffix,
    vision_openpi_shapes,
)
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig


def expected_openpi_fast_shapes(config: PI0FastConfig) -> dict[str, tuple[int, ...]]:
    """Every openpi leaf path (without '/value') a π0-FAST checkpoint of `config` holds, with its shape."""
    L, D = config.num_hidden_layers, config.hidden_size
    shapes = vision_openpi_shapes(config, D)
    shapes[f"{_LLM}/embedder/input_embedding"] = (config.vocab_size, D)
    shapes.update(gemma_layers_openpi_shapes(config, 0, D, config.intermediate_size))
    for norm in ("pre_attention_norm", "pre_ffw_norm"):
        shapes[f"{_LLM}/layers/{norm}/scale"] = (L, D)
    shapes[f"{_LLM}/final_norm/scale"] = (D,)
    return shapes


def config_from_openpi_fast_shapes(shapes: Mapping[str, tuple[int, ...]], **overrides: Any) -> PI0FastConfig:
    """Every dimension of a π0-FAST config from the leaf shapes of its openpi checkpoint.

    The action settings (`action_dim`, `action_horizon`, `max_token_len`) are not stored in the weights: they keep
    openpi's `Pi0FASTConfig` defaults (32, 32, 250: `pi0_fast_base`) unless given in `overrides` (DROID: 8, 10;
    LIBERO: 7, 10, 180).
    """
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    patch, _, _, vision_width = shapes[f"{_IMG}/embedding/kernel"]
    tokens = shapes[f"{_IMG}/pos_embedding"][1]
    layers, heads, width, head_dim = shapes[f"{_LLM}/layers/attn/q_einsum/w"]
    inferred = dict(
        image_size=math.isqrt(tokens) * patch,
        patch_size=patch,
        vision_hidden_size=vision_width,
        vision_intermediate_size=shapes[f"{_BLOCK}/MlpBlock_0/Dense_0/kernel"][2],
        vision_num_layers=shapes[f"{_BLOCK}/LayerNorm_0/scale"][0],
        vision_num_heads=shapes[f"{_ATTN}/query/kernel"][2],
        hidden_size=width,
        intermediate_size=shapes[f"{_LLM}/layers/mlp/gating_einsum"][3],
        num_hidden_layers=layers,
        num_attention_heads=heads,
        num_key_value_heads=shapes[f"{_LLM}/layers/attn/kv_einsum/w"][2],
        head_dim=head_dim,
        vocab_size=shapes[f"{_LLM}/embedder/input_embedding"][0],
    )
    return PI0FastConfig(**{**inferred, **overrides})


def iter_openpi_fast_state_dict(read: LeafReader, config: PI0FastConfig) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for every parameter of `PI0FastForActionGeneration(config)`, one layer at a time."""
    yield from iter_openpi_vision_state_dict(read, config)
    yield "embed_tokens.weight", _t(read(f"{_LLM}/embedder/input_embedding", None))
    for i in range(config.num_hidden_layers):
        prefix = f"layers.{i}.block"
        yield from iter_openpi_layer_weights(read, config, i, 0, prefix)
        yield f"{prefix}.attn_norm.weight", _t(read(f"{_LLM}/layers/pre_attention_norm/scale", i))
        yield f"{prefix}.mlp_norm.weight", _t(read(f"{_LLM}/layers/pre_ffw_norm/scale", i))
    yield "final_norm.weight", _t(read(f"{_LLM}/final_norm/scale", None))
