"""openpi parameter names and layouts -> ours.

openpi stores every layer stacked on axis 0 and kernels as (in, out); we store one tensor per layer in torch's
(out, in) layout, with q/k/v and gate/up fused. Everything here works one openpi leaf (or one layer of it) at a time,
so a converter can stream a 12 GB checkpoint with bounded memory.

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

import math
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig

# read(path, layer): the openpi array at `path` (without a trailing "/value"), or only its slice `[layer]`.
LeafReader = Callable[[str, "int | None"], np.ndarray]

_IMG = "PaliGemma/img"
_BLOCK = f"{_IMG}/Transformer/encoderblock"
_ATTN = f"{_BLOCK}/MultiHeadDotProductAttention_0"
_LLM = "PaliGemma/llm"
_VISION = "vision_tower"


def strip_value_suffix(path: str) -> str:
    """openpi training checkpoints store nnx state, whose leaf paths end in '/value'; released ones may not."""
    return path[: -len("/value")] if path.endswith("/value") else path


def _suffix(expert: int) -> str:
    return "" if expert == 0 else f"_{expert}"


def vision_openpi_shapes(config: Any, width: int) -> dict[str, tuple[int, ...]]:
    """The SigLIP leaves (tower and head to the Gemma `width`) of a π0 / π0.5 / π0-FAST `config`, with their shapes."""
    W, M, Lv, heads = config.vision_hidden_size, config.vision_intermediate_size, config.vision_num_layers, config.vision_num_heads
    p, tokens = config.patch_size, config.tokens_per_image
    hd = W // heads
    shapes: dict[str, tuple[int, ...]] = {
        f"{_IMG}/embedding/kernel": (p, p, 3, W),
        f"{_IMG}/embedding/bias": (W,),
        f"{_IMG}/pos_embedding": (1, tokens, W),
        f"{_IMG}/Transformer/encoder_norm/scale": (W,),
        f"{_IMG}/Transformer/encoder_norm/bias": (W,),
        f"{_IMG}/head/kernel": (W, width),
        f"{_IMG}/head/bias": (width,),
        f"{_BLOCK}/MlpBlock_0/Dense_0/kernel": (Lv, W, M),
        f"{_BLOCK}/MlpBlock_0/Dense_0/bias": (Lv, M),
        f"{_BLOCK}/MlpBlock_0/Dense_1/kernel": (Lv, M, W),
        f"{_BLOCK}/MlpBlock_0/Dense_1/bias": (Lv, W),
        f"{_ATTN}/out/kernel": (Lv, heads, hd, W),
        f"{_ATTN}/out/bias": (Lv, W),
    }
    for norm in ("LayerNorm_0", "LayerNorm_1"):
        shapes[f"{_BLOCK}/{norm}/scale"] = (Lv, W)
        shapes[f"{_BLOCK}/{norm}/bias"] = (Lv, W)
    for projection in ("query", "key", "value"):
        shapes[f"{_ATTN}/{projection}/kernel"] = (Lv, W, heads, hd)
        shapes[f"{_ATTN}/{projection}/bias"] = (Lv, heads, hd)
    return shapes


def gemma_layers_openpi_shapes(config: Any, expert: int, width: int, mlp_width: int) -> dict[str, tuple[int, ...]]:
    """The stacked attention and MLP leaves of one Gemma expert (0: the VLM / π0-FAST's only one), with their shapes."""
    L, N, K, H = config.num_hidden_layers, config.num_attention_heads, config.num_key_value_heads, config.head_dim
    s, D, F = _suffix(expert), width, mlp_width
    return {
        f"{_LLM}/layers/attn/q_einsum{s}/w": (L, N, D, H),
        f"{_LLM}/layers/attn/kv_einsum{s}/w": (L, 2, K, D, H),
        f"{_LLM}/layers/attn/attn_vec_einsum{s}/w": (L, N, H, D),
        f"{_LLM}/layers/mlp{s}/gating_einsum": (L, 2, D, F),
        f"{_LLM}/layers/mlp{s}/linear": (L, F, D),
    }


def expected_openpi_shapes(config: PI0Config) -> dict[str, tuple[int, ...]]:
    """Every openpi leaf path (without '/value') a checkpoint of `config` holds, with its shape."""
    L = config.num_hidden_layers
    D0, D1 = config.vlm_hidden_size, config.expert_hidden_size
    shapes = vision_openpi_shapes(config, D0)
    shapes[f"{_LLM}/embedder/input_embedding"] = (config.vocab_size, D0)
    for expert, (D, F) in enumerate(
        [(D0, config.vlm_intermediate_size), (D1, config.expert_intermediate_size)]
    ):
        s = _suffix(expert)
        shapes.update(gemma_layers_openpi_shapes(config, expert, D, F))
        adaptive = expert == 1 and config.pi05
        for norm in ("pre_attention_norm", "pre_ffw_norm"):
            if adaptive:
                shapes[f"{_LLM}/layers/{norm}{s}/Dense_0/kernel"] = (L, D, 3 * D)
                shapes[f"{_LLM}/layers/{norm}{s}/Dense_0/bias"] = (L, 3 * D)
            else:
                shapes[f"{_LLM}/layers/{norm}{s}/scale"] = (L, D)
        if adaptive:
            shapes[f"{_LLM}/final_norm{s}/Dense_0/kernel"] = (D, 3 * D)
            shapes[f"{_LLM}/final_norm{s}/Dense_0/bias"] = (3 * D,)
        else:
            shapes[f"{_LLM}/final_norm{s}/scale"] = (D,)
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
    return f"{_LLM}/layers/attn/q_einsum/w" in paths and not {f"{_LLM}/layers/attn/q_einsum_1/w", "action_in_proj/kernel"} & paths


def config_from_openpi_shapes(shapes: Mapping[str, tuple[int, ...]], **overrides: Any) -> PI0Config | PI0FastConfig:
    """Infer π0 vs π0.5 vs π0-FAST and every dimension from the leaf shapes of an openpi checkpoint.

    `action_horizon`, `max_token_len` and camera names are not stored in the weights: they keep the π0/π0.5
    defaults unless given in `overrides`. Raises `ValueError` when the tree is not a π0/π0.5 parameter tree.
    A π0-FAST tree gives a `PI0FastConfig` (see `pi0_torch.conversion.openpi_fast_weights`).
    """
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    if is_openpi_fast_tree(shapes) and f"{_IMG}/embedding/kernel" in shapes:
        from pi0_torch.conversion.openpi_fast_weights import config_from_openpi_fast_shapes

        return config_from_openpi_fast_shapes(shapes, **overrides)
    required = [f"{_IMG}/embedding/kernel", f"{_IMG}/pos_embedding", f"{_LLM}/layers/attn/q_einsum/w", "action_in_proj/kernel"]
    missing = [path for path in required if path not in shapes]
    if missing:
        raise ValueError(f"not a pi0/pi0.5 parameter tree: missing {', '.join(missing)}")
    patch, _, _, vision_width = shapes[f"{_IMG}/embedding/kernel"]
    tokens = shapes[f"{_IMG}/pos_embedding"][1]
    layers, heads, vlm_width, head_dim = shapes[f"{_LLM}/layers/attn/q_einsum/w"]
    vocab_size = shapes[f"{_LLM}/embedder/input_embedding"][0]
    inferred = dict(
        pi05=f"{_LLM}/final_norm_1/Dense_0/kernel" in shapes,
        image_size=math.isqrt(tokens) * patch,
        patch_size=patch,
        vision_hidden_size=vision_width,
        vision_intermediate_size=shapes[f"{_BLOCK}/MlpBlock_0/Dense_0/kernel"][2],
        vision_num_layers=shapes[f"{_BLOCK}/LayerNorm_0/scale"][0],
        vision_num_heads=shapes[f"{_ATTN}/query/kernel"][2],
        vlm_hidden_size=vlm_width,
        vlm_intermediate_size=shapes[f"{_LLM}/layers/mlp/gating_einsum"][3],
        expert_hidden_size=shapes[f"{_LLM}/layers/attn/q_einsum_1/w"][2],
        expert_intermediate_size=shapes[f"{_LLM}/layers/mlp_1/gating_einsum"][3],
        num_hidden_layers=layers,
        num_attention_heads=heads,
        num_key_value_heads=shapes[f"{_LLM}/layers/attn/kv_einsum/w"][2],
        head_dim=head_dim,
        vocab_size=vocab_size,
        action_dim=shapes["action_in_proj/kernel"][0],
    )
    return PI0Config(**{**inferred, **overrides})


def check_openpi_shapes(shapes: Mapping[str, tuple[int, ...]], config: PI0Config | PI0FastConfig) -> None:
    """Raise `ValueError` naming every missing, unexpected or mis-shaped leaf."""
    shapes = {strip_value_suffix(k): tuple(v) for k, v in shapes.items()}
    if isinstance(config, PI0FastConfig):
        from pi0_torch.conversion.openpi_fast_weights import expected_openpi_fast_shapes

        expected = expected_openpi_fast_shapes(config)
    else:
        expected = expected_openpi_shapes(config)
    missing = sorted(set(expected) - set(shapes))
    unexpected = sorted(set(shapes) - set(expected))
    misshaped = sorted(f"{p} {shapes[p]} (expected {expected[p]})" for p in set(expected) & set(shapes) if shapes[p] != expected[p])
    problems = [f"{kind}: {', '.join(names)}" for kind, names in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", misshaped)) if names]
    if problems:
        raise ValueError("openpi parameters do not match the config; " + "; ".join(problems))


def _t(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array))


def _linear(kernel: np.ndarray) -> torch.Tensor:  # (in, out) -> (out, in)
    return _t(kernel.T)


def iter_openpi_vision_state_dict(read: LeafReader, config: Any) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for the SigLIP tower (`vision_tower.*`) and its head (`image_projection.*`) of a
    π0 / π0.5 / π0-FAST `config`, one layer at a time."""
    W = config.vision_hidden_size
    yield f"{_VISION}.embeddings.patch_embedding.weight", _t(read(f"{_IMG}/embedding/kernel", None).transpose(3, 2, 0, 1))
    yield f"{_VISION}.embeddings.patch_embedding.bias", _t(read(f"{_IMG}/embedding/bias", None))
    yield f"{_VISION}.embeddings.position_embedding.weight", _t(read(f"{_IMG}/pos_embedding", None)[0])
    for i in range(config.vision_num_layers):
        prefix = f"{_VISION}.encoder.layers.{i}"
        for ours, theirs in (("layer_norm1", "LayerNorm_0"), ("layer_norm2", "LayerNorm_1")):
            yield f"{prefix}.{ours}.weight", _t(read(f"{_BLOCK}/{theirs}/scale", i))
            yield f"{prefix}.{ours}.bias", _t(read(f"{_BLOCK}/{theirs}/bias", i))
        for ours, theirs in (("q_proj", "query"), ("k_proj", "key"), ("v_proj", "value")):
            yield f"{prefix}.self_attn.{ours}.weight", _linear(read(f"{_ATTN}/{theirs}/kernel", i).reshape(W, -1))
            yield f"{prefix}.self_attn.{ours}.bias", _t(read(f"{_ATTN}/{theirs}/bias", i).reshape(-1))
        yield f"{prefix}.self_attn.out_proj.weight", _linear(read(f"{_ATTN}/out/kernel", i).reshape(-1, W))
        yield f"{prefix}.self_attn.out_proj.bias", _t(read(f"{_ATTN}/out/bias", i))
        for ours, theirs in (("fc1", "Dense_0"), ("fc2", "Dense_1")):
            yield f"{prefix}.mlp.{ours}.weight", _linear(read(f"{_BLOCK}/MlpBlock_0/{theirs}/kernel", i))
            yield f"{prefix}.mlp.{ours}.bias", _t(read(f"{_BLOCK}/MlpBlock_0/{theirs}/bias", i))
    yield f"{_VISION}.post_layernorm.weight", _t(read(f"{_IMG}/Transformer/encoder_norm/scale", None))
    yield f"{_VISION}.post_layernorm.bias", _t(read(f"{_IMG}/Transformer/encoder_norm/bias", None))
    yield "image_projection.weight", _linear(read(f"{_IMG}/head/kernel", None))
    yield "image_projection.bias", _t(read(f"{_IMG}/head/bias", None))


def iter_openpi_layer_weights(read: LeafReader, config: Any, layer: int, expert: int, prefix: str) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield the attention and MLP weights of one Gemma expert's `layer` as `ExpertLayer` names under `prefix`
    (q/k/v and gate/up fused); its norms are left to the caller."""
    N, K, H = config.num_attention_heads, config.num_key_value_heads, config.head_dim
    s = _suffix(expert)
    q = read(f"{_LLM}/layers/attn/q_einsum{s}/w", layer)  # (N, D, H)
    kv = read(f"{_LLM}/layers/attn/kv_einsum{s}/w", layer)  # (2, K, D, H)
    D = q.shape[1]
    q_rows = q.transpose(0, 2, 1).reshape(N * H, D)
    k_rows, v_rows = (kv[j].transpose(0, 2, 1).reshape(K * H, D) for j in (0, 1))
    yield f"{prefix}.qkv_proj.weight", _t(np.concatenate([q_rows, k_rows, v_rows]))
    # attn_vec_einsum (N, H, D): head-major rows, then (out, in)
    yield f"{prefix}.o_proj.weight", _linear(read(f"{_LLM}/layers/attn/attn_vec_einsum{s}/w", layer).reshape(N * H, D))
    gating = read(f"{_LLM}/layers/mlp{s}/gating_einsum", layer)  # (2, D, F): [0] gate (GELU), [1] up
    yield f"{prefix}.gate_up_proj.weight", _t(np.concatenate([gating[0].T, gating[1].T]))
    yield f"{prefix}.down_proj.weight", _linear(read(f"{_LLM}/layers/mlp{s}/linear", layer))


def iter_openpi_state_dict(read: LeafReader, config: PI0Config | PI0FastConfig) -> Iterator[tuple[str, torch.Tensor]]:
    """Yield `(our_name, tensor)` for every parameter of `PI0ForActionGeneration(config)` (or, for a
    `PI0FastConfig`, of `PI0FastForActionGeneration(config)`).

    Reads stacked leaves one layer at a time through `read(path, layer)`, so at most one layer's worth of arrays is
    alive at once. Tensors keep the dtype `read` returns.
    """
    if isinstance(config, PI0FastConfig):
        from pi0_torch.conversion.openpi_fast_weights import iter_openpi_fast_state_dict

        yield from iter_openpi_fast_state_dict(read, config)
        return
    yield from iter_openpi_vision_state_dict(read, config)
    yield "embed_tokens.weight", _t(read(f"{_LLM}/embedder/input_embedding", None))

    for i in range(config.num_hidden_layers):
        for expert, name in enumerate(("vlm", "expert")):
            s, prefix = _suffix(expert), f"layers.{i}.{name}"
            yield from iter_openpi_layer_weights(read, config, i, expert, prefix)
            for ours, theirs in (("attn_norm", "pre_attention_norm"), ("mlp_norm", "pre_ffw_norm")):
                if expert == 1 and config.pi05:
                    yield f"{prefix}.{ours}.modulation.weight", _linear(read(f"{_LLM}/layers/{theirs}{s}/Dense_0/kernel", i))
                    yield f"{prefix}.{ours}.modulation.bias", _t(read(f"{_LLM}/layers/{theirs}{s}/Dense_0/bias", i))
                else:
                    yield f"{prefix}.{ours}.weight", _t(read(f"{_LLM}/layers/{theirs}{s}/scale", i))
    yield "vlm_final_norm.weight", _t(read(f"{_LLM}/final_norm/scale", None))
    if config.pi05:
        yield "expert_final_norm.modulation.weight", _linear(read(f"{_LLM}/final_norm_1/Dense_0/kernel", None))
        yield "expert_final_norm.modulation.bias", _t(read(f"{_LLM}/final_norm_1/Dense_0/bias", None))
    else:
        yield "expert_final_norm.weight", _t(read(f"{_LLM}/final_norm_1/scale", None))

    head_names = ["action_in_proj", "action_out_proj"]
    head_names += ["time_mlp_in", "time_mlp_out"] if config.pi05 else ["state_proj", "action_time_mlp_in", "action_time_mlp_out"]
    for name in head_names:
        yield f"{name}.weight", _linear(read(f"{name}/kernel", None))
        yield f"{name}.bias", _t(read(f"{name}/bias", None))


def load_openpi_params(model: nn.Module, arrays: Mapping[str, np.ndarray]) -> None:
    """Load openpi-named arrays (e.g. `params_flat.npz`) into `model` in place, in the model's dtype.

    Every leaf must be present with the shape `model.config` implies, and every model parameter gets filled;
    otherwise `ValueError` names the offending leaves and nothing is loaded.
    """
    arrays = {strip_value_suffix(k): v for k, v in arrays.items()}
    config: PI0Config | PI0FastConfig = model.config  # type: ignore[assignment]
    check_openpi_shapes({k: v.shape for k, v in arrays.items()}, config)

    def read(path: str, layer: int | None) -> np.ndarray:
        array = np.asarray(arrays[path])
        return array if layer is None else array[layer]

    state_dict = dict(iter_openpi_state_dict(read, config))
    ours = model.state_dict()
    mismatched = [f"{k} {tuple(v.shape)} vs {tuple(ours[k].shape)}" for k, v in state_dict.items() if k in ours and v.shape != ours[k].shape]
    if mismatched or set(state_dict) != set(ours):
        raise ValueError(
            f"internal mapping error: missing {sorted(set(ours) - set(state_dict))}, "
            f"extra {sorted(set(state_dict) - set(ours))}, mis-shaped {mismatched}"
        )
    model.load_state_dict(state_dict, strict=True)
