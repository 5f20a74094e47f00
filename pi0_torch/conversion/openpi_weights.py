"""openpi parameter names and layouts -> ours: π0 / π0.5's map, and the entry points for any openpi tree.

π0 / π0.5 is PaliGemma (its SigLIP and Gemma leaves are mapped by `pi0_torch.conversion.openpi_paligemma`, as for
π0-FAST) plus the action expert (the `_1` Gemma leaves, with adaRMS norms for π0.5) and the action heads, mapped here.
[`config_from_openpi_shapes`], [`check_openpi_shapes`], [`iter_openpi_state_dict`] and [`load_openpi_params`] take
a tree or config of either family member: a π0-FAST one goes to `pi0_torch.conversion.openpi_fast_weights`.
Everything works one openpi leaf (or one layer of it) at a time, so a converter can stream a 12 GB checkpoint with
bounded memory.

```python
>>> import numpy as np
>>> from pi0_torch import PI0ForActionGeneration
>>> from pi0_torch.conversion.openpi_weights import config_from_openpi_shapes, load_openpi_params
>>> arrays = dict(np.load("tests/fixtures/openpi/pi0_small/params_flat.npz"))
>>> model = PI0ForActionGeneration(config_from_openpi_shapes({k: v.shape for k, v in arrays.items()}))
>>> load_openpi_params(model, arrays)

```
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from pi0_torch.conversion.openpi_fast_weights import (
    config_from_openpi_fast_shapes,
    expected_openpi_fast_shapes,
    iter_openpi_fast_state_dict,
)
from pi0_torch.conversion.openpi_paligemma import (
    IMG,
    LLM,
    NO_LORA,
    LeafReader,
    as_linear_weight,
    as_tensor,
    expert_suffix,
    gemma_layers_openpi_shapes,
    gemma_lora_openpi_shapes,
    iter_openpi_layer_weights,
    iter_openpi_vision_state_dict,
    openpi_lora_ranks,
    shared_settings_from_openpi_shapes,
    strip_value_suffix,
    vision_openpi_shapes,
)
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig


def expected_openpi_shapes(config: PI0Config, lora_ranks: Mapping[tuple[int, str], int] = NO_LORA) -> dict[str, tuple[int, ...]]:
    """Every openpi leaf path (without '/value') a checkpoint of `config` holds, with its shape; with the LoRA leaves
    of `lora_ranks` (`openpi_lora_ranks`) for a LoRA fine-tune's tree."""
    L = config.num_hidden_layers
    D0, D1 = config.vlm_hidden_size, config.expert_hidden_size
    shapes = vision_openpi_shapes(config, D0)
    shapes[f"{LLM}/embedder/input_embedding"] = (config.vocab_size, D0)
    for expert, (D, F) in enumerate(
        [(D0, config.vlm_intermediate_size), (D1, config.expert_intermediate_size)]
    ):
        s = expert_suffix(expert)
        shapes.update(gemma_layers_openpi_shapes(config, expert, D, F))
        shapes.update(gemma_lora_openpi_shapes(config, expert, D, F, lora_ranks))
        adaptive = expert == 1 and config.pi05
        for norm in ("pre_attention_norm", "pre_ffw_norm"):
            if adaptive:
                shapes[f"{LLM}/layers/{norm}{s}/Dense_0/kernel"] = (L, D, 3 * D)
                shapes[f"{LLM}/layers/{norm}{s}/Dense_0/bias"] = (L, 3 * D)
            else:
                shapes[f"{LLM}/layers/{norm}{s}/scale"] = (L, D)
        if adaptive:
            shapes[f"{LLM}/final_norm{s}/Dense_0/kernel"] = (D, 3 * D)
            shapes[f"{LLM}/final_norm{s}/Dense_0/bias"] = (3 * D,)
        else:
            shapes[f"{LLM}/final_norm{s}/scale"] = (D,)
    A = config.action_dim
    heads_shapes = {"action_in_proj": (A, D1), "action_out_proj": (D1, A)}
    if config.pi05:
        heads_shapes.update(time_mlp_in=(D1, D1), time_mlp_out=(D1, D1))
    else:
        heads_shapes.update(state_proj=(A, D1), action_time_mlp_in=(2 * D1, D1), action_time_mlp_out=(D1, D1))
    for name, (fan_in, fan_out) in heads_shapes.items():
        shapes[f"{name}/kernel"] = (fan_in, fan_out)
        shapes[f"{name}/bias"] = (fan_out,)
    return shapes


def is_openpi_fast_tree(shapes: Mapping[str, tuple[int, ...]]) -> bool:
    """Whether openpi leaf paths are a π0-FAST tree: PaliGemma's one Gemma, no action expert and no action heads."""
    paths = {strip_value_suffix(k) for k in shapes}
    return f"{LLM}/layers/attn/q_einsum/w" in paths and not {f"{LLM}/layers/attn/q_einsum_1/w", "action_in_proj/kernel"} & paths


def config_from_openpi_shapes(shapes: Mapping[str, tuple[int, ...]], **overrides: Any) -> PI0Config | PI0FastConfig:
    """Infer π0 vs π0.5 vs π0-FAST and every dimension from the leaf shapes of an openpi checkpoint.

    `action_horizon`, `max_token_len` and camera names are not stored in the weights: they keep the π0/π0.5
    defaults unless given in `overrides`. Raises `ValueError` when the tree is not a π0/π0.5 parameter tree.
    A π0-FAST tree gives a `PI0FastConfig` (see `pi0_torch.conversion.openpi_fast_weights`).
    """
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    if is_openpi_fast_tree(shapes) and f"{IMG}/embedding/kernel" in shapes:
        return config_from_openpi_fast_shapes(shapes, **overrides)
    required = [f"{IMG}/embedding/kernel", f"{IMG}/pos_embedding", f"{LLM}/layers/attn/q_einsum/w", "action_in_proj/kernel"]
    missing = [path for path in required if path not in shapes]
    if missing:
        raise ValueError(f"not a pi0/pi0.5 parameter tree: missing {', '.join(missing)}")
    inferred = dict(
        shared_settings_from_openpi_shapes(shapes),
        pi05=f"{LLM}/final_norm_1/Dense_0/kernel" in shapes,
        vlm_hidden_size=shapes[f"{LLM}/layers/attn/q_einsum/w"][2],
        vlm_intermediate_size=shapes[f"{LLM}/layers/mlp/gating_einsum"][3],
        expert_hidden_size=shapes[f"{LLM}/layers/attn/q_einsum_1/w"][2],
        expert_intermediate_size=shapes[f"{LLM}/layers/mlp_1/gating_einsum"][3],
        action_dim=shapes["action_in_proj/kernel"][0],
    )
    return PI0Config(**{**inferred, **overrides})


def check_openpi_shapes(shapes: Mapping[str, tuple[int, ...]], config: PI0Config | PI0FastConfig) -> None:
    """Raise `ValueError` naming every missing, unexpected or mis-shaped leaf (LoRA leaves included, where the tree
    has any)."""
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    expected_shapes = expected_openpi_fast_shapes if isinstance(config, PI0FastConfig) else expected_openpi_shapes
    expected = expected_shapes(config, openpi_lora_ranks(shapes))  # type: ignore[arg-type]
    missing = sorted(set(expected) - set(shapes))
    unexpected = sorted(set(shapes) - set(expected))
    misshaped = sorted(f"{p} {shapes[p]} (expected {expected[p]})" for p in set(expected) & set(shapes) if shapes[p] != expected[p])
    problems = [f"{kind}: {', '.join(names)}" for kind, names in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", misshaped)) if names]
    if problems:
        raise ValueError("openpi parameters do not match the config; " + "; ".join(problems))


def iter_openpi_state_dict(read: LeafReader, config: PI0Config | PI0FastConfig,
                           lora_ranks: Mapping[tuple[int, str], int] = NO_LORA) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for every parameter of `PI0ForActionGeneration(config)` (or, for a
    `PI0FastConfig`, of `PI0FastForActionGeneration(config)`), the LoRA adapters `lora_ranks` names
    (`openpi_lora_ranks` of the tree) merged into the Gemma weights.

    Reads stacked leaves one layer at a time through `read(path, layer)`, so at most one layer's worth of arrays is
    alive at once. Tensors keep the dtype `read` returns.
    """
    if isinstance(config, PI0FastConfig):
        yield from iter_openpi_fast_state_dict(read, config, lora_ranks)
        return
    yield from iter_openpi_vision_state_dict(read, config)
    yield "embed_tokens.weight", as_tensor(read(f"{LLM}/embedder/input_embedding", None))

    for i in range(config.num_hidden_layers):
        for expert, name in enumerate(("vlm", "expert")):
            s, prefix = expert_suffix(expert), f"layers.{i}.{name}"
            yield from iter_openpi_layer_weights(read, config, i, expert, prefix, lora_ranks)
            for ours, theirs in (("attn_norm", "pre_attention_norm"), ("mlp_norm", "pre_ffw_norm")):
                if expert == 1 and config.pi05:
                    yield f"{prefix}.{ours}.modulation.weight", as_linear_weight(read(f"{LLM}/layers/{theirs}{s}/Dense_0/kernel", i))
                    yield f"{prefix}.{ours}.modulation.bias", as_tensor(read(f"{LLM}/layers/{theirs}{s}/Dense_0/bias", i))
                else:
                    yield f"{prefix}.{ours}.weight", as_tensor(read(f"{LLM}/layers/{theirs}{s}/scale", i))
    yield "vlm_final_norm.weight", as_tensor(read(f"{LLM}/final_norm/scale", None))
    if config.pi05:
        yield "expert_final_norm.modulation.weight", as_linear_weight(read(f"{LLM}/final_norm_1/Dense_0/kernel", None))
        yield "expert_final_norm.modulation.bias", as_tensor(read(f"{LLM}/final_norm_1/Dense_0/bias", None))
    else:
        yield "expert_final_norm.weight", as_tensor(read(f"{LLM}/final_norm_1/scale", None))

    head_names = ["action_in_proj", "action_out_proj"]
    head_names += ["time_mlp_in", "time_mlp_out"] if config.pi05 else ["state_proj", "action_time_mlp_in", "action_time_mlp_out"]
    for name in head_names:
        yield f"{name}.weight", as_linear_weight(read(f"{name}/kernel", None))
        yield f"{name}.bias", as_tensor(read(f"{name}/bias", None))


def load_openpi_params(model: nn.Module, arrays: Mapping[str, np.ndarray]) -> None:
    """Load openpi-named arrays (e.g. `params_flat.npz`) into `model` in place, in the model's dtype; a LoRA
    fine-tune's adapters are merged into the weights.

    Every leaf must be present with the shape `model.config` implies, and every model parameter gets filled;
    otherwise `ValueError` names the offending leaves and nothing is loaded.
    """
    arrays = {strip_value_suffix(k): v for k, v in arrays.items()}
    config: PI0Config | PI0FastConfig = model.config  # type: ignore[assignment]
    check_openpi_shapes({k: v.shape for k, v in arrays.items()}, config)

    def read(path: str, layer: int | None) -> np.ndarray:
        array = np.asarray(arrays[path])
        return array if layer is None else array[layer]

    state_dict = dict(iter_openpi_state_dict(read, config, openpi_lora_ranks({k: v.shape for k, v in arrays.items()})))
    ours = model.state_dict()
    mismatched = [f"{k} {tuple(v.shape)} vs {tuple(ours[k].shape)}" for k, v in state_dict.items() if k in ours and v.shape != ours[k].shape]
    if mismatched or set(state_dict) != set(ours):
        raise ValueError(
            f"internal mapping error: missing {sorted(set(ours) - set(state_dict))}, "
            f"extra {sorted(set(state_dict) - set(ours))}, mis-shaped {mismatched}"
        )
    model.load_state_dict(state_dict, strict=True)
