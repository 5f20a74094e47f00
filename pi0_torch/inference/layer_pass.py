"""One decoder layer's sampling pass, on the layer's own weights: what `JointDecoderLayer.forward` computes, in fewer
kernels.

A sampling pass writes the k/v cache and computes no gradients. There each projection runs as one GEMM on its weight
transposed once per call (`SamplingWeights`: no transpose or module call per projection and step), the residual
stream accumulates the o- and down-projections in place (`add_projection`), and π0.5's adaRMS shift goes through the
projection after its norm as the GEMM's bias (`project_normed`). Where that is not what calling the modules does
(hooks, LoRA or quantized projections, autocast; see `expert_sampling_weights`) the layer's own `forward` runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn
from torch.nn.modules.module import _global_forward_hooks, _global_forward_pre_hooks

from pi0_torch.inference.attention import attend
from pi0_torch.kernels.reference import apply_rope, rms_norm

if TYPE_CHECKING:
    from pi0_torch.inference.conditioning import NormParams
    from pi0_torch.inference.layout import StreamPass
    from pi0_torch.models.layers import ExpertLayer, JointDecoderLayer


@dataclass(frozen=True)
class SamplingWeights:
    """One expert layer's projection weights, transposed `[in, out]` (views, taken once per sampling call), for the
    passes of sampling, which run the GEMMs on them instead of calling the modules. `CALL_MODULES` holds none: the
    modules are called."""

    qkv: torch.Tensor | None  # [D, (N + 2K) H]
    o: torch.Tensor | None  # [N H, D]
    gate_up: torch.Tensor | None  # [D, 2 * mlp_width]
    down: torch.Tensor | None  # [mlp_width, D]

    @property
    def usable(self) -> bool:
        return self.qkv is not None


CALL_MODULES = SamplingWeights(None, None, None, None)
PROJECTIONS = ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")  # an expert's, in `SamplingWeights`' order


def expert_sampling_weights(expert: ExpertLayer) -> SamplingWeights:
    """The projections' weights for a sampling pass, or `CALL_MODULES` where running the GEMMs on them is not what
    calling the modules does: a projection that is not a bias-free `nn.Linear` itself (LoRA, quantized layers) or whose
    weight is not a plain parameter (a tensor subclass: quantized weights, FSDP2's DTensor shards), a hook or a replaced
    `forward` on a projection or norm (offloading, pruning, a user's hooks), or autocast."""
    modules = expert._modules  # (checked on every eager call: no `nn.Module.__getattr__`, about a microsecond each)
    if not all(plain_linear(modules.get(name), bias=False) for name in PROJECTIONS):
        return CALL_MODULES
    if runs_extra_code(modules["attn_norm"]) or runs_extra_code(modules["mlp_norm"]):
        return CALL_MODULES
    device = modules["qkv_proj"]._parameters["weight"].device.type
    if torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device):
        return CALL_MODULES
    return SamplingWeights(*(modules[name]._parameters["weight"].t() for name in PROJECTIONS))


def layer_sampling_weights(layer: JointDecoderLayer) -> tuple[SamplingWeights, SamplingWeights]:
    """The (VLM, action expert) `SamplingWeights` of a sampling pass; `CALL_MODULES` for both where the layer has
    hooks or a replaced `forward` of its own (block offloading puts the weights in place in a hook, after this is
    called; a hook that keeps the layer's outputs must not see them updated in place)."""
    if runs_extra_code(layer):
        return CALL_MODULES, CALL_MODULES
    return expert_sampling_weights(layer._modules["vlm"]), expert_sampling_weights(layer._modules["expert"])


@dataclass(frozen=True)
class ModelSamplingWeights:
    """The plain-weights check of one sampling call (`model_sampling_weights`), made once per call (a user may add a
    hook or an adapter between calls) and shared by its gate and every pass of it."""

    layers: tuple[tuple[SamplingWeights, SamplingWeights], ...]  # per decoder layer: (VLM, action expert)
    plain_action_linears: bool  # the action projections (π0: and the action/time MLP) are plain linears


def model_sampling_weights(model: nn.Module) -> ModelSamplingWeights:
    """Each decoder layer's (VLM, action expert) `SamplingWeights` of a π0 / π0.5 `model`, and whether its action
    projections are plain linear layers with biases."""
    action_linears = [model.action_in_proj, model.action_out_proj]
    if not model.config.pi05:
        action_linears += [model.action_time_mlp_in, model.action_time_mlp_out]
    return ModelSamplingWeights(tuple(layer_sampling_weights(layer) for layer in model.layers),
                                all(plain_linear(linear, bias=True) for linear in action_linears))


def decoder_sampling_weights(layers: Sequence[nn.Module]) -> list[SamplingWeights]:
    """Each π0-FAST decoder layer's `SamplingWeights` (`CALL_MODULES` where the layer itself runs extra code)."""
    return [CALL_MODULES if runs_extra_code(layer) else expert_sampling_weights(layer.block) for layer in layers]


def plain_linear(module: nn.Module | None, bias: bool) -> bool:
    """Whether calling `module` is `F.linear` on its own plain parameters (with a bias or without one, as `bias` says):
    an `nn.Linear` itself (not LoRA or a quantized layer) whose parameters are not tensor subclasses (quantized weights,
    FSDP2's DTensor shards), with no hooks and no replaced `forward`."""
    if type(module) is not nn.Linear or runs_extra_code(module):
        return False
    parameters = module._parameters  # (not `module.weight`: `nn.Module.__getattr__` costs more than this whole check)
    if type(parameters.get("weight")) is not nn.Parameter:
        return False
    return type(parameters.get("bias")) is nn.Parameter if bias else parameters.get("bias") is None


def activation_quantized(model: nn.Module, prefix: str = "") -> str | None:
    """The name of a linear layer of `model` (under `prefix`, e.g. "layers.0.expert") whose weight quantizes its input
    activations in each call (torchao's int8-dynamic or float8 schemes: a tensor subclass with activation quantization
    settings), or None. Such a linear has no functorch rules (RTC guidance's vector-Jacobian product) and synchronizes
    with the GPU in every matmul (pytorch/ao#4872: CUDA graph capture fails)."""
    for name, module in model.named_modules(prefix=prefix):
        weight = module._parameters.get("weight") if isinstance(module, nn.Linear) else None
        if weight is not None and getattr(weight, "act_quant_kwargs", None) is not None:
            return name
    return None


def runs_extra_code(module: nn.Module) -> bool:
    """Whether calling `module` runs more than its own class's `forward`: hooks (its own or global) or a `forward`
    replaced on the instance."""
    if module._forward_hooks or module._forward_pre_hooks or "forward" in module.__dict__:
        return True
    return bool(_global_forward_hooks or _global_forward_pre_hooks)  # (nn.Module's registries, mutated in place)


def any_runs_extra_code(module: nn.Module) -> bool:
    """`runs_extra_code` of `module` or of any module inside it. (Walked with a stack: checked on every eager call,
    and `nn.Module.modules()` takes over twice as long, a generator per level.)"""
    stack, seen = [module], {id(module)}
    while stack:
        current = stack.pop()
        if runs_extra_code(current):
            return True
        for child in current._modules.values():
            if child is not None and id(child) not in seen:
                seen.add(id(child))
                stack.append(child)
    return False


def project_normed(norm: nn.Module, x: torch.Tensor, params: NormParams | None, weight: torch.Tensor) -> torch.Tensor:
    """The projection `weight` (transposed) of the normed tokens. A sampling step's adaRMS shift, when `params` holds
    it through the projection (`shift_projected`, for every step at once), is added in the GEMM as its bias instead of
    to the normed tokens: `(normed + shift) W^T = normed W^T + shift W^T`, one kernel fewer (bf16: rounded in another
    order than openpi's, within bf16 rounding)."""
    if params is not None and params.shift_projected is not None:
        return torch.addmm(params.shift_projected, rms_norm(x, norm.eps, params.scale), weight)
    return torch.mm(norm.forward(x, params), weight)  # (no hooks to run: see `expert_sampling_weights`)


def add_projection(residual: torch.Tensor, y: torch.Tensor, gate: torch.Tensor | None, weight: torch.Tensor) -> torch.Tensor:
    """`residual + y @ weight` (adaRMS: `residual + (y @ weight) * gate`, one `addcmul`) where the caller never reads
    `residual` again: the projection accumulates into it with `addmm_`, one GEMM kernel with beta = 1 instead of a
    GEMM and an add (an out-of-place `addmm` is no better on CUDA: it copies the residual into its output first). The
    sum is then rounded once, where openpi rounds the projection and then the sum: the same in float32 to an ulp,
    within bf16 rounding in bf16."""
    if gate is not None:
        return torch.addcmul(residual, torch.mm(y, weight), gate)
    return residual.addmm_(y, weight)


def sampling_layer_pass(
    layer: JointDecoderLayer,
    prefix: torch.Tensor | None,  # [B * P, D0]
    suffix: torch.Tensor | None,  # [B * S, D1]
    streams: tuple[StreamPass | None, StreamPass | None],
    cache: tuple[torch.Tensor, torch.Tensor],  # this layer's k/v buffers [B, K, slots, H]
    expert_norms: tuple[NormParams, NormParams] | None,
    weights: tuple[SamplingWeights, SamplingWeights],  # (VLM, expert), usable for each stream that is not None
    keys_only: bool = False,
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """`layer(prefix, suffix, streams, cache, expert_norms, keys_only)` of a sampling pass (the cache written, no
    gradients), each expert's GEMMs on its `weights`; the residual streams are updated in place (the caller does not
    read `prefix` / `suffix` again)."""
    experts = ((layer.vlm, prefix, None, weights[0]), (layer.expert, suffix, expert_norms, weights[1]))
    queries: list[torch.Tensor | None] = [None, None]
    for index, ((expert, x, norms, own), stream) in enumerate(zip(experts, streams)):
        if x is None:
            continue
        qkv = project_normed(expert.attn_norm, x, norms[0] if norms is not None else None, own.qkv)  # [B * T, (N + 2K) H]
        heads, kv_heads = expert.heads[:2]
        qk, v = qkv.view(-1, stream.tokens, qkv.shape[-1] // layer.head_dim, layer.head_dim).split(
            (heads + kv_heads, kv_heads), dim=2
        )
        rounded = qk.new_empty(qk.shape) if qk.dtype != torch.float32 else None  # (bf16: the rotation rounds itself)
        q, k = apply_rope(qk, stream.cos, stream.sin, out=rounded).split((heads, kv_heads), dim=2)
        cache[0].index_copy_(2, stream.slots, k.to(x.dtype).transpose(1, 2))
        cache[1].index_copy_(2, stream.slots, v.transpose(1, 2))
        if not keys_only:
            queries[index] = q.to(x.dtype).contiguous()  # [B, T, N, H]
    if keys_only:
        return None, None

    outputs: list[torch.Tensor | None] = [None, None]
    for index, ((expert, x, norms, own), stream) in enumerate(zip(experts, streams)):
        if x is None:
            continue
        attn_params, mlp_params = norms if norms is not None else (None, None)
        attended = attend(queries[index], cache[0], cache[1], stream.attention)  # [B * T, N * H]
        x = add_projection(x, attended, attn_params.gate if attn_params is not None else None, own.o)
        hidden = expert.geglu(project_normed(expert.mlp_norm, x, mlp_params, own.gate_up))
        outputs[index] = add_projection(x, hidden, mlp_params.gate if mlp_params is not None else None, own.down)
    return outputs[0], outputs[1]
