"""openpi π0-FAST parameter names and layouts -> ours (`PI0FastForActionGeneration`).

A π0-FAST tree is PaliGemma alone: the same SigLIP leaves as π0 and one Gemma (`PaliGemma/llm/...` without the
`_1` expert leaves and without action heads); its LM head is the token embedding. The SigLIP and per-layer Gemma
maps are the ones π0 uses too (`pi0_torch.conversion.openpi_paligemma`); `load_openpi_params`,
`check_openpi_shapes`, `config_from_openpi_shapes` and `iter_openpi_state_dict` of
`pi0_torch.conversion.openpi_weights` hand π0-FAST trees and configs to this module.

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

from collections.abc import Iterator, Mapping
from typing import Any

import torch

from pi0_torch.conversion.openpi_paligemma import (
    LLM,
    NO_LORA,
    LeafReader,
    as_tensor,
    gemma_layers_openpi_shapes,
    gemma_lora_openpi_shapes,
    iter_openpi_layer_weights,
    iter_openpi_vision_state_dict,
    shared_settings_from_openpi_shapes,
    strip_value_suffix,
    vision_openpi_shapes,
)
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig


def expected_openpi_fast_shapes(config: PI0FastConfig,
                                lora_ranks: Mapping[tuple[int, str], int] = NO_LORA) -> dict[str, tuple[int, ...]]:
    """Every openpi leaf path (without '/value') a π0-FAST checkpoint of `config` holds, with its shape; with the
    LoRA leaves of `lora_ranks` (`openpi_lora_ranks`) for a LoRA fine-tune's tree."""
    L, D = config.num_hidden_layers, config.hidden_size
    shapes = vision_openpi_shapes(config, D)
    shapes[f"{LLM}/embedder/input_embedding"] = (config.vocab_size, D)
    shapes.update(gemma_layers_openpi_shapes(config, 0, D, config.intermediate_size))
    shapes.update(gemma_lora_openpi_shapes(config, 0, D, config.intermediate_size, lora_ranks))
    for norm in ("pre_attention_norm", "pre_ffw_norm"):
        shapes[f"{LLM}/layers/{norm}/scale"] = (L, D)
    shapes[f"{LLM}/final_norm/scale"] = (D,)
    return shapes


def config_from_openpi_fast_shapes(shapes: Mapping[str, tuple[int, ...]], **overrides: Any) -> PI0FastConfig:
    """Every dimension of a π0-FAST config from the leaf shapes of its openpi checkpoint.

    The action settings (`action_dim`, `action_horizon`, `max_token_len`) are not stored in the weights: they keep
    openpi's `Pi0FASTConfig` defaults (32, 32, 250: `pi0_fast_base`) unless given in `overrides` (DROID: 8, 10;
    LIBERO: 7, 10, 180).
    """
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    inferred = dict(
        shared_settings_from_openpi_shapes(shapes),
        hidden_size=shapes[f"{LLM}/layers/attn/q_einsum/w"][2],
        intermediate_size=shapes[f"{LLM}/layers/mlp/gating_einsum"][3],
    )
    return PI0FastConfig(**{**inferred, **overrides})


def iter_openpi_fast_state_dict(read: LeafReader, config: PI0FastConfig,
                                lora_ranks: Mapping[tuple[int, str], int] = NO_LORA) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for every parameter of `PI0FastForActionGeneration(config)`, one layer at a time,
    the LoRA adapters `lora_ranks` names merged in."""
    yield from iter_openpi_vision_state_dict(read, config)
    yield "embed_tokens.weight", as_tensor(read(f"{LLM}/embedder/input_embedding", None))
    for i in range(config.num_hidden_layers):
        prefix = f"layers.{i}.block"
        yield from iter_openpi_layer_weights(read, config, i, 0, prefix, lora_ranks)
        yield f"{prefix}.attn_norm.weight", as_tensor(read(f"{LLM}/layers/pre_attention_norm/scale", i))
        yield f"{prefix}.mlp_norm.weight", as_tensor(read(f"{LLM}/layers/pre_ffw_norm/scale", i))
    yield "final_norm.weight", as_tensor(read(f"{LLM}/final_norm/scale", None))
