"""π0 / π0.5 in PyTorch, numerically matching openpi (`src/openpi/models/pi0.py`, `gemma.py`, `siglip.py`).

Reading order: normalisation and RoPE, one layer of the joint two-expert Gemma, the model (prefix and suffix
embedding, training forward, cached sampling). Shapes: B batch, C cameras, P prefix tokens, S suffix tokens,
N query heads, K kv heads, H head size, D0 / D1 widths of the VLM Gemma (expert 0) and the action expert (expert 1).
Inside a layer each expert's tokens are 2-D, `[B * T, D]`, the layout its projections take without reshaping.

Every pass lays its tokens out so that each one attends to a single contiguous range of keys (no mask matrix): each
sample's valid prefix tokens are moved to the end of the prefix slots, with padding and masked cameras before them
(`compact_prefix`), and the suffix follows; see `pi0_torch.models.attention`. The result equals openpi's prefix-LM
mask on the original layout (tests compare the two with `pi0_torch.masks.prefix_lm_mask`).

`generate_actions` reads its inputs on the host once (their checks and the prefix layout) and then never again:
the sampling after that never waits for the device, so it can be replayed as one CUDA graph (`capture_sampling`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.modules.module import _global_forward_hooks, _global_forward_pre_hooks
from transformers import PreTrainedModel, SiglipVisionConfig, SiglipVisionModel
from transformers.modeling_layers import GradientCheckpointingLayer
from transformers.utils import ModelOutput

from pi0_torch.models.attention import KERNELS, AttentionPlan, KeyRanges, attend, choose_kernel, plan_attention
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.flow_matching import euler_times, interpolate, sample_flow_time, sincos_time_embedding
from pi0_torch.models.rtc import (
    DEFAULT_MAX_GUIDANCE,
    METHODS,
    ChunkPrefix,
    check_rtc_inputs,
    chunk_prefix,
    guidance_weight,
    per_sample_steps,
)
from pi0_torch.utils import files
from pi0_torch.utils.quiet import transformers_progress
from pi0_torch.utils.validation import check_int, check_pretrained_location, describe, hub_errors, nonfinite_error
from pi0_torch.utils.validation import check_tensor as _check_tensor  # (the name other model modules import from here)

# ----------------------------------------------------------------------------------------------------------------------
# Normalisation and rotary position embedding
# ----------------------------------------------------------------------------------------------------------------------

_FUSED_RMS_NORM = getattr(torch.ops.aten, "_fused_rms_norm", None)  # one kernel (recent torch); else the formula


def rms_norm(x: torch.Tensor, eps: float, weight: torch.Tensor | None = None) -> torch.Tensor:
    """`x * rsqrt(mean(x^2) + eps)`, times `weight` if given, in float32 arithmetic; returned in `x`'s dtype."""
    if _FUSED_RMS_NORM is not None and (weight is None or weight.dtype == x.dtype):
        return _FUSED_RMS_NORM(x, [x.shape[-1]], weight, eps)[0]
    x32 = x.float()
    normed = x32 * torch.rsqrt(x32.pow(2).mean(dim=-1, keepdim=True) + eps)
    return (normed if weight is None else normed * weight).to(x.dtype)


@dataclass
class NormParams:
    """What a Gemma norm applies to the normalised tokens, `normed * scale (+ shift)`, and (adaRMS) the gate of the
    residual that follows. Each tensor broadcasts against the tokens `[B * T, D]`: `[D]`, or `[B * T, D]` per token
    (or has a leading time axis before `StepConditioning.steps` splits it)."""

    scale: torch.Tensor  # 1 + weight (RMSNorm); 1 + the modulation's scale (adaRMS)
    shift: torch.Tensor | None = None
    gate: torch.Tensor | None = None
    shift_projected: torch.Tensor | None = None  # adaRMS in sampling: `shift @ W^T` of the projection after the norm

    def tensors(self) -> list[torch.Tensor]:
        return [t for t in (self.scale, self.shift, self.gate, self.shift_projected) if t is not None]

    def rebuilt(self, values: Iterator[torch.Tensor]) -> NormParams:
        """The same structure holding the next tensors of `values` (see `StepConditioning.map`)."""
        optional = (self.shift, self.gate, self.shift_projected)
        return NormParams(next(values), *(None if t is None else next(values) for t in optional))


class RMSNorm(nn.Module):
    """Gemma RMSNorm: `normalize(x) * (1 + weight)` in float32, returned in the input dtype."""

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.zeros(dim))

    def params(self) -> NormParams:
        return NormParams(1 + self.weight)  # (in the weights' dtype: bf16 weights round it, as openpi's)

    def forward(self, x: torch.Tensor, params: NormParams | None = None) -> torch.Tensor:
        return rms_norm(x, self.eps, (self.params() if params is None else params).scale)


class AdaRMSNorm(nn.Module):
    """π0.5 adaptive RMSNorm: the flow-time condition sets scale, shift and a residual gate.

    `params(condition)` = `self.modulation(condition)` split into [scale | shift | gate] (callers compute them once for
    all sampling steps, see `PI0ForActionGeneration.conditioning`); `forward(x, params)` = `normalize(x) * (1 + scale)
    + shift` in float32, returned in the input dtype. `project_normed` applies the projection that follows.
    """

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.modulation = nn.Linear(dim, 3 * dim)

    def params(self, condition: torch.Tensor, projection_weight: torch.Tensor | None = None) -> NormParams:
        """With `projection_weight`, the transposed weight `[D, out]` of the projection after this norm in a sampling
        pass (`SamplingWeights`), also the shift through it (`shift_projected`), for `project_normed` to add in that
        projection's GEMM."""
        scale, shift, gate = self.modulation(condition).chunk(3, dim=-1)
        return NormParams(1 + scale, shift, gate, None if projection_weight is None else shift @ projection_weight)

    def forward(self, x: torch.Tensor, params: NormParams) -> torch.Tensor:
        if params.scale.dim() == 1 and params.scale.dtype == x.dtype:  # one scale for every token (a sampling step)
            return rms_norm(x, self.eps, params.scale) + params.shift  # (2 kernels; bf16: `normed * scale` rounded first)
        return torch.addcmul(params.shift, rms_norm(x.float(), self.eps), params.scale).to(x.dtype)


def rope_cos_sin(positions: torch.Tensor, head_dim: int, theta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """RoPE of `positions` `[B, T]` (frequencies `theta ** (-2k / H)`, angles in float32) for `apply_rope`: `cos`
    repeated over both halves and `sin` signed `(-sin, sin)`, `[B, T, H]` each."""
    exponents = (2.0 / head_dim) * torch.arange(head_dim // 2, dtype=torch.float32, device=positions.device)
    angles = positions.float()[..., None] / theta**exponents  # [B, T, H/2]
    cos, sin = torch.cos(angles), torch.sin(angles)
    return torch.cat([cos, cos], dim=-1), torch.cat([-sin, sin], dim=-1)


def apply_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """Rotate `x` `[..., H]` in the split-halves layout: `[x1 cos - x2 sin, x2 cos + x1 sin]` = `x * cos + (x2, x1) *
    (-sin, sin)` with `rope_cos_sin`'s float32 tables (broadcast against `x`). Computed in float32 (type promotion
    reads a bf16 `x` exactly, without a separate cast) and returned in float32, for the caller to round, or rounded
    by the last kernel itself into `out` (of `x`'s shape and the caller's dtype; no gradients flow through `out=`)."""
    return torch.addcmul(x * cos, x.roll(x.shape[-1] // 2, dims=-1), sin, out=out)


# ----------------------------------------------------------------------------------------------------------------------
# The joint two-expert Gemma
# ----------------------------------------------------------------------------------------------------------------------


class ExpertLayer(nn.Module):
    """One expert's weights in one layer: pre-norms, fused q/k/v, o-projection and the GeGLU MLP (no biases)."""

    def __init__(self, config: PI0Config, width: int, mlp_width: int, adaptive: bool) -> None:
        super().__init__()
        norm = AdaRMSNorm if adaptive else RMSNorm
        heads, kv_heads, head_dim = config.num_attention_heads, config.num_key_value_heads, config.head_dim
        self.attn_norm = norm(width, config.rms_norm_eps)
        self.qkv_proj = nn.Linear(width, (heads + 2 * kv_heads) * head_dim, bias=False)  # rows: q | k | v
        self.o_proj = nn.Linear(heads * head_dim, width, bias=False)
        self.mlp_norm = norm(width, config.rms_norm_eps)
        self.gate_up_proj = nn.Linear(width, 2 * mlp_width, bias=False)  # rows: gate | up
        self.down_proj = nn.Linear(mlp_width, width, bias=False)
        self.heads = (heads, kv_heads, kv_heads)  # of q, k, v

    @staticmethod
    def geglu(gate_up: torch.Tensor) -> torch.Tensor:
        """The MLP between its projections: `gelu_tanh(gate) * up` `[..., mlp_width]` of `gate_up_proj`'s output."""
        gate, up = gate_up.chunk(2, dim=-1)
        return F.gelu(gate, approximate="tanh") * up

    def sampling_weights(self) -> SamplingWeights:
        """The projections' weights for a sampling pass (`SamplingWeights`), or `CALL_MODULES` where running the GEMMs
        on them is not what calling the modules does: a projection that is not a bias-free `nn.Linear` itself (LoRA,
        quantized layers) or whose weight is not a plain parameter (a tensor subclass: quantized weights, FSDP2's
        DTensor shards), a hook or a replaced `forward` on a projection or norm (offloading, pruning, a user's hooks),
        or autocast."""
        projections = (self.qkv_proj, self.o_proj, self.gate_up_proj, self.down_proj)
        if any(type(p) is not nn.Linear or p.bias is not None or type(p.weight) is not nn.Parameter for p in projections):
            return CALL_MODULES
        if any(_runs_extra_code(module) for module in (*projections, self.attn_norm, self.mlp_norm)):
            return CALL_MODULES
        device = self.qkv_proj.weight.device.type
        if torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device):
            return CALL_MODULES
        return SamplingWeights(*(p.weight.t() for p in projections))


def _runs_extra_code(module: nn.Module) -> bool:
    """Whether calling `module` runs more than its own class's `forward`: hooks (its own or global) or a `forward`
    replaced on the instance."""
    if module._forward_hooks or module._forward_pre_hooks or "forward" in module.__dict__:
        return True
    return bool(_global_forward_hooks or _global_forward_pre_hooks)  # (nn.Module's registries, mutated in place)


@dataclass(frozen=True)
class SamplingWeights:
    """One expert layer's projection weights, transposed `[in, out]` (views, taken once per sampling call), for the
    passes of sampling, which run the GEMMs on them instead of calling the modules (`ExpertLayer.sampling_weights`:
    only where that is the same). Per layer and step that saves each projection's transpose and module call, and lets
    the residual stream accumulate the o- and down-projections in place (`add_projection`). `CALL_MODULES` holds
    none: the modules are called."""

    qkv: torch.Tensor | None  # [D, (N + 2K) H]
    o: torch.Tensor | None  # [N H, D]
    gate_up: torch.Tensor | None  # [D, 2 * mlp_width]
    down: torch.Tensor | None  # [mlp_width, D]


CALL_MODULES = SamplingWeights(None, None, None, None)


def project_normed(
    norm: nn.Module, projection: nn.Module, x: torch.Tensor, params: NormParams | None, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """`projection(norm(x, params))`, or in a sampling pass (`weight`: the projection's `SamplingWeights` entry) the
    GEMM on the normed tokens. There a sampling step's adaRMS shift, when `params` holds it through the projection
    (`shift_projected`, for every step at once, see `AdaRMSNorm.params`), is added in the GEMM as its bias instead of
    to the normed tokens: `(normed + shift) W^T = normed W^T + shift W^T`, one kernel fewer (bf16: rounded in another
    order than openpi's, within bf16 rounding)."""
    if weight is None:
        return projection(norm(x, params))
    if params is not None and params.shift_projected is not None:
        return torch.addmm(params.shift_projected, rms_norm(x, norm.eps, params.scale), weight)
    return torch.mm(norm.forward(x, params), weight)  # (no hooks to run: see `ExpertLayer.sampling_weights`)


def add_projection(
    residual: torch.Tensor, projection: nn.Module, y: torch.Tensor, gate: torch.Tensor | None, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """The residual update after attention and after the MLP: `residual + projection(y)` (adaRMS: `residual +
    projection(y) * gate`, one `addcmul`).

    In a sampling pass (`weight`: the projection's `SamplingWeights` entry; the caller never reads `residual` again)
    the projection accumulates into the residual with `addmm_`: one GEMM kernel with beta = 1 instead of a GEMM and
    an add (an out-of-place `addmm` is no better on CUDA: it copies the residual into its output first). The sum is
    then rounded once, where openpi rounds the projection and then the sum: the same in float32 to an ulp, within
    bf16 rounding in bf16.
    """
    if gate is not None:
        return torch.addcmul(residual, projection(y) if weight is None else torch.mm(y, weight), gate)
    if weight is not None:
        return residual.addmm_(y, weight)
    return residual + projection(y)


@dataclass
class StreamPass:
    """How one expert's tokens take part in a pass, the same in every layer: their count per sample, RoPE tables
    `[B or 1, T, 1, H]`, what they attend to, and their k/v slots (`first_slot` on, long `slots` `[T]`)."""

    tokens: int
    cos: torch.Tensor
    sin: torch.Tensor
    attention: AttentionPlan
    first_slot: int
    slots: torch.Tensor


class JointDecoderLayer(GradientCheckpointingLayer):
    """One Gemma layer run by both experts at once: each expert normalises and projects its own tokens, every token's
    k/v go to the pass's k/v slots, each stream attends to its key range, then each expert finishes its own tokens.

    Either stream may be None: the prefix runs alone (π0: with the state token) when its k/v are cached for
    sampling, the action tokens run alone in each sampling step against that cache.

    `forward` runs `run`, or its compiled version once `compile_run` is called: one code object for every decoder
    layer, so regional compilation compiles it once for all of them. A step that is differentiated with `torch.func`
    (`write_cache=False`, RTC guidance) runs eagerly: functorch transforms cannot enter compiled code.
    """

    def __init__(self, config: PI0Config) -> None:
        super().__init__()
        self.vlm = ExpertLayer(config, config.vlm_hidden_size, config.vlm_intermediate_size, adaptive=False)
        self.expert = ExpertLayer(config, config.expert_hidden_size, config.expert_intermediate_size, config.pi05)
        self.head_dim = config.head_dim
        self._compiled_run: Any = None

    def sampling_weights(self, vlm: bool, expert: bool) -> tuple[SamplingWeights, SamplingWeights]:
        """The (VLM, action expert) `SamplingWeights` of a sampling pass that runs the given experts. A compiled layer
        calls its modules (`CALL_MODULES`) and keeps the adds, which Inductor fuses itself; so does a layer with hooks
        or a replaced `forward` of its own (block offloading puts the weights in place in a hook, after this is
        called; a hook that keeps the layer's outputs must not see them updated in place)."""
        if self.compiled or _runs_extra_code(self):
            return CALL_MODULES, CALL_MODULES
        vlm_weights = self.vlm.sampling_weights() if vlm else CALL_MODULES
        return vlm_weights, self.expert.sampling_weights() if expert else CALL_MODULES

    def compile_run(self, **compile_kwargs: Any) -> None:
        """`torch.compile` `run` for this layer (`compile_run(disable=True)`: back to eager)."""
        self._compiled_run = None if compile_kwargs.get("disable") else torch.compile(self.run, **compile_kwargs)

    @property
    def compiled(self) -> bool:
        return self._compiled_run is not None

    def forward(self, *args: Any, **kwargs: Any) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        eager = self._compiled_run is None or not kwargs.get("write_cache", True)
        return (self.run if eager else self._compiled_run)(*args, **kwargs)

    def run(
        self,
        prefix: torch.Tensor | None,  # [B * P, D0]
        suffix: torch.Tensor | None,  # [B * S, D1]
        streams: tuple[StreamPass | None, StreamPass | None],  # (prefix, suffix) of the pass
        cache: tuple[torch.Tensor, torch.Tensor] | None = None,  # this layer's k/v buffers [B, K, slots, H]
        expert_norms: tuple[NormParams, NormParams] | None = None,  # the action expert's (attention, MLP) norms
        keys_only: bool = False,
        write_cache: bool = True,
        weights: tuple[SamplingWeights, SamplingWeights] = (CALL_MODULES, CALL_MODULES),  # (VLM, expert) in sampling
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Returns the updated (prefix, suffix).

        With `cache`, each stream's post-RoPE k/v are written into the buffers at its slots and every stream attends
        to the buffers (`write_cache=False`: to a copy of their first slots with the new k/v after them, the cache
        untouched: a sampling step that is differentiated). Without (a training pass) the streams attend to their own
        k/v. `expert_norms` default to the action expert's own RMSNorm weights (π0; π0.5 passes its adaRMS params).
        `keys_only` stops once the k/v are written (the last layer of the cached prefix: its outputs are never read)
        and returns (None, None). A sampling pass (a cache written, no gradients) runs each expert's GEMMs on its
        `weights` where given (`SamplingWeights`) and updates those residual streams in place (`add_projection`):
        the caller does not read `prefix` / `suffix` again.
        """
        sampling = cache is not None and write_cache and not torch.is_grad_enabled()
        if not sampling:
            weights = (CALL_MODULES, CALL_MODULES)
        layers = ((self.vlm, prefix, None, weights[0]), (self.expert, suffix, expert_norms, weights[1]))
        queries: list[torch.Tensor | None] = [None, None]
        gates: list[torch.Tensor | None] = [None, None]
        new_keys, new_values = [], []  # [B, K, T, H] of the streams that do not write into a cache
        for index, ((expert, x, norms, own), stream) in enumerate(zip(layers, streams)):
            if x is None:
                continue
            attn_params = norms[0] if norms is not None else None
            gates[index] = attn_params.gate if attn_params is not None else None
            qkv = project_normed(expert.attn_norm, expert.qkv_proj, x, attn_params, own.qkv)  # [B * T, (N + 2K) H]
            heads, kv_heads = expert.heads[:2]
            qk, v = qkv.view(-1, stream.tokens, qkv.shape[-1] // self.head_dim, self.head_dim).split(
                (heads + kv_heads, kv_heads), dim=2
            )
            rounded = qk.new_empty(qk.shape) if sampling and qk.dtype != torch.float32 else None  # (bf16 sampling)
            q, k = apply_rope(qk, stream.cos, stream.sin, out=rounded).split((heads, kv_heads), dim=2)  # one rotation
            k, v = k.to(x.dtype).transpose(1, 2), v.transpose(1, 2)  # [B, K, T, H]
            if cache is not None and write_cache:  # (`.to`: under autocast the cache and the streams' dtypes differ)
                cache[0].index_copy_(2, stream.slots, k.to(cache[0].dtype))
                cache[1].index_copy_(2, stream.slots, v.to(cache[1].dtype))
            else:
                new_keys.append(k)
                new_values.append(v)
            if not keys_only:
                queries[index] = q.to(x.dtype).contiguous()  # [B, T, N, H] (its own tensor: `attend` folds heads)
        if cache is None:  # a training pass: its own k/v (prefix slots first)
            keys, values = torch.cat(new_keys, dim=2), torch.cat(new_values, dim=2)
        elif not write_cache:  # the cache's first slots, then the new k/v
            first_slot = next(stream.first_slot for stream in streams if stream is not None)
            keys = torch.cat([cache[0][:, :, :first_slot], *new_keys], dim=2)
            values = torch.cat([cache[1][:, :, :first_slot], *new_values], dim=2)
        else:
            keys, values = cache
        if keys_only:
            return None, None

        outputs: list[torch.Tensor | None] = [None, None]
        for index, ((expert, x, norms, own), stream) in enumerate(zip(layers, streams)):
            if x is None:
                continue
            attended = attend(queries[index], keys, values, stream.attention)  # [B * T, N * H]
            x = add_projection(x, expert.o_proj, attended, gates[index], own.o)
            mlp_params = norms[1] if norms is not None else None
            hidden = expert.geglu(project_normed(expert.mlp_norm, expert.gate_up_proj, x, mlp_params, own.gate_up))
            mlp_gate = mlp_params.gate if mlp_params is not None else None
            outputs[index] = add_projection(x, expert.down_proj, hidden, mlp_gate, own.down)
        return outputs[0], outputs[1]


# ----------------------------------------------------------------------------------------------------------------------
# The model
# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class PI0Output(ModelOutput):
    """Output of [`PI0ForActionGeneration.forward`].

    Attributes:
        loss: scalar flow-matching loss, mean of `(velocity - (noise - actions))^2` over everything (when `actions`
            were given).
        velocity: predicted flow velocity `v_t` `[B, horizon, action_dim]`.
    """

    loss: torch.Tensor | None = None
    velocity: torch.Tensor | None = None


@dataclass
class StepConditioning:
    """What the flow time contributes to the suffix: π0's time half of `action_time_mlp_in` (its bias included),
    added to every action token; π0.5's adaRMS params of every expert norm (per layer: attention norm, MLP norm; then
    the final norm).

    `PI0ForActionGeneration.conditioning` builds it for T flow times at once, every tensor with the time axis first;
    `steps()` gives one per sampling step, `per_token()` spreads per-sample values over the action tokens.
    """

    condition: torch.Tensor | None  # π0: [., D1]
    layer_norms: tuple[tuple[NormParams, NormParams], ...] | None  # π0.5
    final_norm: NormParams | None  # π0.5

    def tensors(self) -> list[torch.Tensor]:
        norms = [params for pair in self.layer_norms or () for params in pair] + ([self.final_norm] if self.final_norm else [])
        return ([self.condition] if self.condition is not None else []) + [t for params in norms for t in params.tensors()]

    def rebuilt(self, values: Iterator[torch.Tensor]) -> StepConditioning:
        """The same structure holding the next tensors of `values` (in the order of `tensors()`)."""
        condition = None if self.condition is None else next(values)
        layer_norms = None if self.layer_norms is None else tuple((a.rebuilt(values), m.rebuilt(values)) for a, m in self.layer_norms)
        return StepConditioning(condition, layer_norms, None if self.final_norm is None else self.final_norm.rebuilt(values))

    def map(self, fn: Callable[..., torch.Tensor], *others: StepConditioning) -> StepConditioning:
        """Apply `fn` to every tensor (with the matching tensors of `others` as further arguments)."""
        return self.rebuilt(iter([fn(*group) for group in zip(self.tensors(), *(other.tensors() for other in others))]))

    def steps(self) -> list[StepConditioning]:
        """One conditioning per flow time (each tensor's time axis unbound once)."""
        columns = [tensor.unbind(0) for tensor in self.tensors()]
        return [self.rebuilt(iter(column[index] for column in columns)) for index in range(len(columns[0]))]

    def per_token(self, tokens: int, committed: torch.Tensor | None = None, clean: StepConditioning | None = None) -> StepConditioning:
        """Per sample `[B, ...]` (or one step's `[...]` with `committed`) -> per action token `[B * tokens, ...]`.
        Tokens where `committed` `[B, tokens]` is set (real-time chunking: their actions are given) take the values of
        `clean` (the conditioning of flow time 0, one step)."""
        if committed is None:
            return self.map(lambda value: value.repeat_interleave(tokens, dim=0))
        return self.map(
            lambda value, clean_value: torch.where(committed[..., None], clean_value, value.unsqueeze(-2)).flatten(0, 1), clean
        )


@dataclass(frozen=True)
class PrefixLayout:
    """How a call lays out its prefix, decided on the host from its checked inputs (see `InputFacts.layout`): the
    cameras that go through the vision tower (those some sample shows, in config order) and `length` prefix slots,
    each sample's valid tokens at their end (the longest sample fills them; `padded`: some sample has fewer)."""

    cameras: tuple[int, ...]
    length: int
    padded: bool


@dataclass(frozen=True)
class InputFacts:
    """What the input checks read from the device, in their one read: which cameras each sample shows and how many
    valid text tokens it has."""

    image_masks: tuple[tuple[bool, ...], ...]
    text_counts: tuple[int, ...]
    text_length: int

    def layout(self, tokens_per_image: int, bucket: int = 1) -> PrefixLayout:
        """The prefix layout, `length` rounded up to a multiple of `bucket` (CUDA graphs: fewer distinct layouts)."""
        cameras = tuple(c for c in range(len(self.image_masks[0])) if any(shown[c] for shown in self.image_masks))
        valid = [tokens_per_image * sum(shown[c] for c in cameras) + text for shown, text in zip(self.image_masks, self.text_counts)]
        total = tokens_per_image * len(cameras) + self.text_length
        length = min(total, -(-max(1, *valid) // bucket) * bucket)
        return PrefixLayout(cameras, length, any(count < length for count in valid))


def compact_prefix(tokens: torch.Tensor, valid: torch.Tensor, layout: PrefixLayout) -> tuple[torch.Tensor, torch.Tensor]:
    """Move each sample's valid tokens, in order, to the end of `layout.length` slots: `tokens` `[B, P, D]`, `valid`
    `[B, P]` -> tokens `[B * length, D]` (a tensor of its own, not a view: a compiled layer sees the same kind of input
    in every layer) and each sample's first valid slot `[B]` (invalid tokens before it).

    Exact: attention only depends on which tokens are valid and their order (positions count valid tokens), and no
    valid token attends to an invalid one.
    """
    first = layout.length - valid.sum(dim=1)
    batch, count = valid.shape
    if count == layout.length and not layout.padded:
        return tokens.flatten(0, 1).clone(), first
    order = valid.to(torch.uint8).sort(dim=1, stable=True).indices[:, -layout.length :]  # invalid first, then valid in order
    rows = order + torch.arange(batch, device=order.device)[:, None] * count
    return tokens.flatten(0, 1).index_select(0, rows.flatten()), first


@dataclass
class PrefixCache:
    """The prefix (π0: and the state token) run once for sampling: every layer's post-RoPE k/v in static buffers
    `[B, K, slots, H]` whose last `action_horizon` slots each step's action tokens fill, and each sample's first
    valid slot `[B]` (its valid prefix tokens end at `layout.length`)."""

    keys: list[torch.Tensor]
    values: list[torch.Tensor]
    first: torch.Tensor
    layout: PrefixLayout

    @property
    def slots(self) -> int:
        return self.keys[0].shape[2]


@dataclass
class ActionPass:
    """What every sampling step shares, built once per call: the cache, the action tokens' stream (RoPE, key range,
    slots), the action expert's `SamplingWeights` of each layer, and π0's time-independent parts (the action half of
    `action_time_mlp_in`, transposed, and the action expert's norm params)."""

    cache: PrefixCache
    stream: StreamPass
    expert_weights: list[SamplingWeights]
    action_weight: torch.Tensor | None  # π0: [D1, D1]
    expert_norms: list[tuple[NormParams, NormParams]] | None  # π0: per layer (attention, MLP)
    final_norm: NormParams | None  # π0


@dataclass
class SamplingInputs:
    """The tensors sampling reads once its inputs are checked (what a CUDA graph holds static copies of)."""

    pixel_values: torch.Tensor  # [B, C', 3, H, W]: the cameras of the layout
    image_masks: torch.Tensor  # bool [B, C']
    input_ids: torch.Tensor  # [B, L]
    attention_mask: torch.Tensor  # [B, L]
    state: torch.Tensor | None  # [B, action_dim] (π0)
    noise: torch.Tensor  # float32 [B, horizon, action_dim]
    times: torch.Tensor  # float32 [steps]: the flow time of each Euler step
    target: torch.Tensor | None = None  # real-time chunking: float32 [B, horizon, action_dim]
    weights: torch.Tensor | None = None  # guidance: float32 [B, horizon]
    committed: torch.Tensor | None = None  # conditioning: bool [B, horizon]


@dataclass(frozen=True)
class SamplingPlan:
    """The host-side settings of one sampling call (a CUDA graph is captured per plan and input shapes)."""

    layout: PrefixLayout
    times: tuple[float, ...]
    rtc_method: str | None = None  # None: plain sampling
    max_guidance: float = 0.0


class PI0PreTrainedModel(PreTrainedModel):
    config_class = PI0Config
    config: PI0Config
    base_model_prefix = "pi0"
    main_input_name = "pixel_values"
    supports_gradient_checkpointing = True
    _no_split_modules = ["JointDecoderLayer", "SiglipEncoderLayer"]
    _supports_sdpa = True

    @torch.no_grad()
    def _init_weights(self, module: nn.Module) -> None:
        std = 0.02
        if isinstance(module, AdaRMSNorm):
            # openpi initialises the adaRMS Dense to zero: unit scale, no shift, closed residual gates.
            nn.init.zeros_(module.modulation.weight)
            nn.init.zeros_(module.modulation.bias)
        elif isinstance(module, RMSNorm):
            nn.init.zeros_(module.weight)
        elif isinstance(module, nn.Linear) and not _is_inside_vision_tower(self, module):
            nn.init.normal_(module.weight, std=std)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding) and not _is_inside_vision_tower(self, module):
            nn.init.normal_(module.weight, std=std)
        else:
            super()._init_weights(module)

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: Any, *args: Any, **kwargs: Any) -> Any:
        """`PreTrainedModel.from_pretrained` that refuses a checkpoint whose tensors do not match the model.

        transformers only warns about missing or unexpected weights and initialises the missing ones randomly; a
        policy with silently random weights is worse than no policy, so any missing, unexpected or mis-shaped
        tensor raises `ValueError` naming them. `ignore_mismatched_sizes=True` is the explicit opt-in to
        re-initialise mis-shaped tensors (e.g. fine-tuning with another `action_dim`). Quiet unless `verbose=True`
        (transformers' "Loading weights" bar).

        A local folder must hold `config.json` (unless a `config` is given); a path that is neither a folder nor a hub
        id `namespace/name` is refused at once, without trying the hub (see `pi0_torch.utils.validation.is_hub_id`).
        """
        config_file = None if kwargs.get("config") else f"{kwargs['subfolder']}/config.json" if kwargs.get("subfolder") else "config.json"
        check_pretrained_location(pretrained_model_name_or_path, config_file, "model")
        want_info = kwargs.pop("output_loading_info", False)
        allow_mismatched = kwargs.pop("ignore_mismatched_sizes", False)  # an explicit opt-in to re-initialise them
        with hub_errors(pretrained_model_name_or_path, "model"), transformers_progress(kwargs.pop("verbose", False)):
            model, info = super().from_pretrained(
                pretrained_model_name_or_path, *args, output_loading_info=True, ignore_mismatched_sizes=True, **kwargs
            )
        problems = {
            "missing": sorted(info.get("missing_keys", ())),
            "unexpected": sorted(info.get("unexpected_keys", ())),
            "mis-shaped": [] if allow_mismatched else sorted(_describe_mismatch(item) for item in info.get("mismatched_keys", ())),
        }
        problems = {kind: names for kind, names in problems.items() if names}
        if problems:
            details = "; ".join(f"{kind}: {', '.join(names[:10])}{' ...' if len(names) > 10 else ''}" for kind, names in problems.items())
            raise ValueError(f"checkpoint {pretrained_model_name_or_path} does not match {cls.__name__}({model.config.model_type}): {details}")
        return (model, info) if want_info else model

    def save_pretrained(self, save_directory: Any, *args: Any, verbose: bool = False, **kwargs: Any) -> Any:
        """`PreTrainedModel.save_pretrained`, quiet unless `verbose=True` (transformers' "Writing model shards" bar).
        The weight files get the permissions of the folder's other files (safetensors would write them 0600)."""
        with transformers_progress(verbose):
            result = super().save_pretrained(save_directory, *args, **kwargs)
        for weights in Path(save_directory).glob("model*.safetensors"):
            files.give_default_mode(weights)
        return result


def _describe_mismatch(item: Any) -> str:
    """transformers reports a mismatch as (name, checkpoint shape, model shape)."""
    if isinstance(item, (tuple, list)) and len(item) == 3:
        name, checkpoint_shape, model_shape = item
        return f"{name} (checkpoint {tuple(checkpoint_shape)}, model {tuple(model_shape)})"
    return str(item)


def _is_inside_vision_tower(model: nn.Module, module: nn.Module) -> bool:
    vision_tower = getattr(model, "vision_tower", None)
    return vision_tower is not None and any(module is m for m in vision_tower.modules())


def sincos_2d_positions(grid: int, width: int, temperature: float = 10_000.0) -> torch.Tensor:
    """big_vision's `posemb_sincos_2d`: `[grid * grid, width]` rows in raster order, `[sin x | cos x | sin y | cos y]`
    over `width // 4` frequencies from 1 down to `1 / temperature` (x the patch column, y its row)."""
    quarter = width // 4
    omega = 1.0 / temperature ** (torch.arange(quarter, dtype=torch.float64) / max(quarter - 1, 1))  # [width / 4]
    rows, columns = torch.meshgrid(torch.arange(grid, dtype=torch.float64), torch.arange(grid, dtype=torch.float64), indexing="ij")
    x = columns.flatten()[:, None] * omega  # [grid^2, width / 4]
    y = rows.flatten()[:, None] * omega
    return torch.cat([x.sin(), x.cos(), y.sin(), y.cos()], dim=1).float()


def siglip_vision_tower(config: Any) -> SiglipVisionModel:
    """The SigLIP tower of π0, π0.5 and π0-FAST from a config's `vision_*` dims, `image_size` and `patch_size`:
    pre-LN blocks with tanh GELU, LayerNorm eps 1e-6, no pooling head (openpi's `pool_type="none"`), patch
    positions initialised by `sincos_2d_positions` (square patch grids and widths divisible by 4, as every preset
    has; otherwise SigLIP's random init)."""
    vision_config = SiglipVisionConfig(
        hidden_size=config.vision_hidden_size,
        intermediate_size=config.vision_intermediate_size,
        num_hidden_layers=config.vision_num_layers,
        num_attention_heads=config.vision_num_heads,
        image_size=config.image_size,
        patch_size=config.patch_size,
        hidden_act="gelu_pytorch_tanh",
        layer_norm_eps=1e-6,
        vision_use_head=False,
        attn_implementation="sdpa",
    )
    tower = SiglipVisionModel(vision_config)
    # A tower trained from scratch starts with big_vision's 2-D sine-cosine patch positions (still a learned table)
    # instead of a random one: where a patch lies is readable from the first step. With the random table the tiny
    # demo policy spent thousands of steps finding where objects are (docs/training.md). Loaded weights replace it.
    table = tower.embeddings.position_embedding.weight  # [patches, width]
    grid = math.isqrt(table.shape[0])
    if grid * grid == table.shape[0] and table.shape[1] % 4 == 0 and table.device.type != "meta":
        with torch.no_grad():
            table.copy_(sincos_2d_positions(grid, table.shape[1]))
    return tower


class SiglipImageEmbedding:
    """Image tokens of the PaliGemma models (π0 / π0.5 and π0-FAST): `self.vision_tower` (`siglip_vision_tower`)
    followed by the linear head `self.image_projection` to the Gemma width."""

    def embed_images(self, pixel_values: torch.Tensor) -> torch.Tensor:
        """SigLIP + linear head: `[B, C, 3, H, W]` in [-1, 1] -> image tokens `[B, C, tokens_per_image, D0]`."""
        batch, cameras = pixel_values.shape[:2]
        images = pixel_values.flatten(0, 1).to(self.image_projection.weight.dtype)  # [B*C, 3, H, W]
        return self.image_projection(self.vision_tower(pixel_values=images).last_hidden_state).unflatten(0, (batch, cameras))


class PI0ForActionGeneration(SiglipImageEmbedding, PI0PreTrainedModel):
    """π0 / π0.5: SigLIP vision tower + VLM Gemma (expert 0) + action expert Gemma (expert 1) + action heads.

    ```python
    >>> import torch
    >>> from pi0_torch import PI0Config, PI0ForActionGeneration
    >>> config = PI0Config.from_preset("pi0_small")
    >>> model = PI0ForActionGeneration(config).eval()
    >>> batch = dict(
    ...     pixel_values=torch.zeros(1, config.num_cameras, 3, 224, 224),
    ...     image_masks=torch.ones(1, config.num_cameras, dtype=torch.bool),
    ...     input_ids=torch.ones(1, config.max_token_len, dtype=torch.long),
    ...     attention_mask=torch.ones(1, config.max_token_len, dtype=torch.bool),
    ...     state=torch.zeros(1, config.action_dim),
    ... )
    >>> model.generate_actions(**batch, generator=torch.Generator().manual_seed(0)).shape
    torch.Size([1, 50, 32])
    >>> model(**batch, actions=torch.zeros(1, 50, 32)).loss.shape
    torch.Size([])

    ```
    """

    # prefix slots of a captured sampling graph are a multiple of this: prompts of similar length share a graph
    GRAPH_PREFIX_BUCKET = 32
    # Regional compilation shares each compiled layer's code among every model, pass, dtype and batch-size class (1, or
    # more) of the process: π0 and π0.5 in float32 and bf16 are 24 decoder-layer graphs. Dynamo's default limit of 8 per
    # code object would fail a `fullgraph` compile after a few of them, so compiled calls raise it to this
    # (`_allow_recompiles`).
    RECOMPILE_LIMIT = 64

    def __init__(self, config: PI0Config) -> None:
        super().__init__(config)
        self.vision_tower = siglip_vision_tower(config)
        self.image_projection = nn.Linear(config.vision_hidden_size, config.vlm_hidden_size)
        self.embed_tokens = nn.Embedding(config.vocab_size, config.vlm_hidden_size)
        self.layers = nn.ModuleList(JointDecoderLayer(config) for _ in range(config.num_hidden_layers))
        self.vlm_final_norm = RMSNorm(config.vlm_hidden_size, config.rms_norm_eps)
        width = config.expert_hidden_size
        self.expert_final_norm = (AdaRMSNorm if config.pi05 else RMSNorm)(width, config.rms_norm_eps)
        self.action_in_proj = nn.Linear(config.action_dim, width)
        self.action_out_proj = nn.Linear(width, config.action_dim)
        if config.pi05:
            self.time_mlp_in = nn.Linear(width, width)
            self.time_mlp_out = nn.Linear(width, width)
        else:
            self.state_proj = nn.Linear(config.action_dim, width)
            self.action_time_mlp_in = nn.Linear(2 * width, width)
            self.action_time_mlp_out = nn.Linear(width, width)
        self._attention_kernel = "auto"
        self._graphs: Any = None  # `SamplingGraphs` once `capture_sampling` is called
        self._device_times: dict[tuple[tuple[float, ...], torch.device], torch.Tensor] = {}
        self.post_init()

    @property
    def attention_kernel(self) -> str:
        """The attention kernel of sampling passes (`pi0_torch.models.attention.KERNELS`): "auto" (FlashAttention's
        varlen kernel on CUDA in bf16 / fp16 where the installed torch has it, else SDPA), "sdpa" or "varlen"."""
        return self._attention_kernel

    @attention_kernel.setter
    def attention_kernel(self, kernel: str) -> None:
        if kernel not in KERNELS:
            raise ValueError(f"attention_kernel must be one of {KERNELS}, got {kernel!r}")
        self._attention_kernel = kernel
        if self._graphs is not None:
            self._graphs.clear()

    # -- prefix: images and text ---------------------------------------------------------------------------------------

    def embed_prefix(
        self, pixel_values: torch.Tensor, image_masks: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Prefix tokens `[B, P, D0]` (each given camera's image tokens, then the scaled text embeddings) and their
        validity `[B, P]`. Image tokens are not scaled; text embeddings are multiplied by sqrt(D0) rounded to the
        weights' dtype (as openpi)."""
        text_tokens = self.embed_tokens(input_ids)
        text_tokens = text_tokens * _rounded_sqrt(text_tokens.shape[-1], text_tokens.dtype)
        valid = attention_mask.bool()
        if pixel_values.shape[1] == 0:  # no sample shows any camera
            return text_tokens, valid
        image_tokens = self.embed_images(pixel_values)  # [B, C, 256, D0]
        image_valid = image_masks[:, :, None].expand(-1, -1, image_tokens.shape[2]).flatten(1)
        return torch.cat([image_tokens.flatten(1, 2), text_tokens], dim=1), torch.cat([image_valid, valid], dim=1)

    def _prefix_stream(self, first: torch.Tensor, layout: PrefixLayout, kernel: str, slots: int) -> StreamPass:
        """The prefix in slots `[0, length)`: sample b's valid tokens from `first[b]` at positions 0, 1, ...; they see
        each other (bidirectional) and nothing after."""
        positions = torch.arange(layout.length, device=first.device)[None, :] - first[:, None]
        return self._stream(positions, first, (layout.length,), layout, kernel, slots, first_slot=0)

    def _suffix_stream(
        self, first: torch.Tensor, layout: PrefixLayout, first_slot: int, group_rows: tuple[int, ...], kernel: str, slots: int
    ) -> StreamPass:
        """Suffix tokens in slots from `first_slot` (after the prefix): positions continue after each sample's valid
        prefix tokens; each group of rows sees the valid prefix and the suffix slots up to its own end."""
        tokens = sum(group_rows)
        positions = (layout.length - first)[:, None] + (first_slot - layout.length) + torch.arange(tokens, device=first.device)
        return self._stream(positions, first, group_rows, layout, kernel, slots, first_slot)

    def _kernel(self, device: torch.device, dtype: torch.dtype, differentiable: bool) -> str:
        """The attention kernel of a pass: SDPA where gradients flow through attention (training, RTC guidance; the
        varlen kernel has no backward with per-sample key counts), else `attention_kernel`'s choice."""
        config = self.config
        return choose_kernel("sdpa" if differentiable else self._attention_kernel, device, dtype,
                             config.num_key_value_heads, config.head_dim)

    def _stream(
        self, positions: torch.Tensor, first: torch.Tensor, group_rows: tuple[int, ...], layout: PrefixLayout,
        kernel: str, slots: int, first_slot: int,
    ) -> StreamPass:
        config = self.config
        cos, sin = rope_cos_sin(positions, config.head_dim, config.rope_theta)
        ends = tuple(first_slot + sum(group_rows[: index + 1]) for index in range(len(group_rows)))
        plan = plan_attention(
            KeyRanges(first, group_rows, ends, padded=layout.padded), config.num_attention_heads,
            config.num_key_value_heads, self.dtype, kernel, key_slots=slots,
        )
        tokens = sum(group_rows)
        slot_index = torch.arange(first_slot, first_slot + tokens, device=first.device)
        return StreamPass(tokens, cos[:, :, None], sin[:, :, None], plan, first_slot, slot_index)

    # -- suffix: state, noisy actions, flow time -----------------------------------------------------------------------

    def time_conditioning(self, time: torch.Tensor) -> torch.Tensor:
        """What the flow time contributes, for any number of times `[T]`.

        π0: the time half of `action_time_mlp_in` (its bias included) `[T, D1]`; π0.5: the adaRMS condition
        `silu(time_mlp_out(silu(time_mlp_in(emb))))` `[T, D1]`. Depends on nothing else, so sampling computes it
        for every step at once.
        """
        config = self.config
        dtype = self.action_in_proj.weight.dtype
        embedding = sincos_time_embedding(time, config.expert_hidden_size, config.time_min_period, config.time_max_period)
        embedding = embedding.to(dtype)
        if config.pi05:
            return F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(embedding))))
        width = config.expert_hidden_size
        return F.linear(embedding, self.action_time_mlp_in.weight[:, width:], self.action_time_mlp_in.bias)

    def conditioning(self, time: torch.Tensor, weights: Sequence[SamplingWeights] | None = None) -> StepConditioning:
        """The suffix's time conditioning for flow times `[T]`, every tensor `[T, ...]` (see `StepConditioning`).
        `weights`: the action expert's `SamplingWeights` of each layer in a sampling pass where each time conditions
        every token alike; π0.5's shifts then also go through the projections after their norms (`project_normed`)."""
        condition = self.time_conditioning(time)
        if not self.config.pi05:
            return StepConditioning(condition, None, None)
        weights = weights or [CALL_MODULES] * len(self.layers)
        layer_norms = tuple(
            (layer.expert.attn_norm.params(condition, own.qkv), layer.expert.mlp_norm.params(condition, own.gate_up))
            for layer, own in zip(self.layers, weights)
        )
        return StepConditioning(None, layer_norms, self.expert_final_norm.params(condition))

    def embed_state(self, state: torch.Tensor) -> torch.Tensor:
        """π0's state token `[B, D1]`."""
        return self.state_proj(state.to(self.state_proj.weight.dtype))

    def embed_actions(
        self, noisy_actions: torch.Tensor, condition: torch.Tensor | None, action_weight: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Action tokens `[B * horizon, D1]` of the noisy actions `[B, horizon, action_dim]`. π0 adds the flow time:
        `action_time_mlp_out(silu(action_time_mlp_in(cat(tokens, time))))` with the time half precomputed
        (`condition` `[D1]`, or per token `[B * horizon, D1]`); `action_weight` is the action half transposed when
        the caller has it."""
        tokens = self.action_in_proj(noisy_actions.to(self.action_in_proj.weight.dtype).flatten(0, 1))
        if self.config.pi05:
            return tokens
        if action_weight is None:
            action_weight = self.action_time_mlp_in.weight[:, : self.config.expert_hidden_size].t()
        return self.action_time_mlp_out(F.silu(torch.addmm(condition, tokens, action_weight)))

    def embed_suffix(self, state: torch.Tensor | None, noisy_actions: torch.Tensor, condition: torch.Tensor | None) -> torch.Tensor:
        """Suffix tokens `[B * S, D1]`: (π0) the state token, then the action tokens (see `embed_actions`)."""
        actions = self.embed_actions(noisy_actions, condition)
        if self.config.pi05:
            return actions
        batch = noisy_actions.shape[0]
        return torch.cat([self.embed_state(state)[:, None], actions.view(batch, -1, actions.shape[-1])], dim=1).flatten(0, 1)

    # -- training forward ----------------------------------------------------------------------------------------------

    def forward(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        actions: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        time: torch.Tensor | None = None,
        inference_delay: torch.Tensor | None = None,
        **unused: Any,
    ) -> PI0Output:
        """Predict the flow velocity at time `time` for `x_t = time * noise + (1 - time) * actions`.

        Args:
            pixel_values: float `[B, C, 3, H, W]` in [-1, 1], cameras in `config.camera_names` order.
            image_masks: bool `[B, C]`, False for a missing camera.
            input_ids: long `[B, L]` (L <= `config.max_token_len`); attention_mask: bool/long `[B, L]`.
            state: float `[B, action_dim]` (required by π0, unused by π0.5).
            actions: float `[B, horizon, action_dim]` normalized target actions; gives `loss`. Without them
                `noise` is used as the noisy input `x_t` directly (with `time`, default 1).
            noise: float `[B, horizon, action_dim]`, drawn from N(0, I) when not given.
            time: float `[B]` flow times, drawn from Beta(1.5, 1) * 0.999 + 0.001 when not given.
            inference_delay: long `[B]` (training-time real-time chunking): the first `d` action steps of each
                sample are given clean (flow time 0, `x_t = actions` there) as the actions a robot executes while
                the next chunk is computed; the loss averages over the other steps only. None: every step is noisy.

        Returns:
            [`PI0Output`] with `velocity` `[B, horizon, action_dim]` and `loss` (scalar, when `actions` is given).
        """
        config = self.config
        horizon = config.action_horizon
        facts = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state, actions=actions, noise=noise, time=time)
        batch, device = len(facts.text_counts), pixel_values.device
        shape = (batch, horizon, config.action_dim)
        if noise is None:
            noise = torch.randn(shape, device=device, dtype=torch.float32)
        if time is None:
            time = (
                sample_flow_time(batch, config.time_beta_alpha, config.time_beta_beta, config.time_scale, config.time_offset, device)
                if actions is not None
                else torch.ones(batch, device=device)
            )

        committed = None
        if inference_delay is not None:
            delay = per_sample_steps(inference_delay, batch, "inference_delay", device)
            if bool(((delay < 0) | (delay >= horizon)).any()):
                raise ValueError(f"inference_delay must lie in [0, action_horizon - 1 = {horizon - 1}], got {delay.tolist()}")
            committed = torch.arange(horizon, device=device)[None, :] < delay[:, None]  # [B, horizon]

        if actions is not None:
            x_t, target = interpolate(actions.float(), noise.float(), time.float())
            if committed is not None:  # flow time 0 there
                x_t = torch.where(committed[..., None], actions.float(), x_t)
        else:
            x_t, target = noise.float(), None

        if self.sampling_compiled:
            _allow_recompiles(self.RECOMPILE_LIMIT)
        layout = facts.layout(config.tokens_per_image)
        prefix, prefix_valid = self.embed_prefix(*self._camera_inputs(pixel_values, image_masks, layout), input_ids, attention_mask)
        prefix, first = compact_prefix(prefix, prefix_valid, layout)
        clean = self.conditioning(torch.zeros(1, device=device)).steps()[0] if committed is not None else None
        conditioning = self.conditioning(time).per_token(horizon, committed, clean)
        suffix = self.embed_suffix(state, x_t, conditioning.condition)
        _, suffix_out = self.run_layers(prefix, suffix, first, layout, conditioning)
        velocity = self.action_out_proj(suffix_out.view(batch, -1, suffix_out.shape[-1])[:, -horizon:]).float()
        if target is None:
            loss = None
        elif committed is None:
            loss = F.mse_loss(velocity, target)
        else:  # the given steps carry no loss
            loss = F.mse_loss(velocity[~committed], target[~committed])
        return PI0Output(loss=loss, velocity=velocity)

    def run_layers(
        self, prefix: torch.Tensor, suffix: torch.Tensor, first: torch.Tensor, layout: PrefixLayout, conditioning: StepConditioning
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Both experts jointly through every layer and their final norms: (prefix_out `[B * length, D0]`,
        suffix_out `[B * S, D1]`).

        `prefix` holds the compacted prefix (`compact_prefix`, first valid slots `first` `[B]`), `suffix` the suffix
        tokens (`embed_suffix`), `conditioning` its time conditioning per token (`StepConditioning.per_token`). π0's
        state token sees the prefix and itself, its action tokens everything; π0.5's action tokens everything.
        """
        config = self.config
        horizon = config.action_horizon
        slots = layout.length + config.suffix_len
        group_rows = (horizon,) if config.pi05 else (1, horizon)
        kernel = self._kernel(prefix.device, prefix.dtype, differentiable=True)
        streams = (
            self._prefix_stream(first, layout, kernel, slots),
            self._suffix_stream(first, layout, layout.length, group_rows, kernel, slots),
        )
        norms = conditioning.layer_norms or (None,) * len(self.layers)
        for layer, layer_norms in zip(self.layers, norms):
            prefix, suffix = layer(prefix, suffix, streams, expert_norms=layer_norms)
        return self.vlm_final_norm(prefix), self.expert_final_norm(suffix, conditioning.final_norm)

    # -- sampling ------------------------------------------------------------------------------------------------------

    def cache_prefix(self, inputs: SamplingInputs, layout: PrefixLayout) -> PrefixCache:
        """Run the prefix once (π0: with the state token) and keep every layer's post-RoPE k/v.

        Exact for sampling because the prefix never attends to the suffix, and π0's state token only to the prefix
        and itself, so neither changes with the noisy actions or the flow time. The buffers have room for the action
        tokens, whose k/v each denoising step writes in place (no per-step copy of the prefix).
        """
        config = self.config
        prefix, valid = self.embed_prefix(inputs.pixel_values, inputs.image_masks, inputs.input_ids, inputs.attention_mask)
        prefix, first = compact_prefix(prefix, valid, layout)
        batch = first.shape[0]
        slots = layout.length + config.suffix_len
        kernel = self._kernel(prefix.device, prefix.dtype, differentiable=False)
        shape = (batch, config.num_key_value_heads, slots, config.head_dim)
        # buffers of their own per layer (views of one shared buffer would alias across a compiled layer's inputs)
        keys, values = ([prefix.new_empty(shape) for _ in self.layers] for _ in range(2))
        streams = (
            self._prefix_stream(first, layout, kernel, slots),
            None if config.pi05 else self._suffix_stream(first, layout, layout.length, (1,), kernel, slots),
        )
        x, state = prefix, None if config.pi05 else self.embed_state(inputs.state)
        for index, (layer, layer_keys, layer_values) in enumerate(zip(self.layers, keys, values)):
            weights = layer.sampling_weights(vlm=True, expert=state is not None)
            x, state = layer(x, state, streams, (layer_keys, layer_values), keys_only=index == len(self.layers) - 1, weights=weights)
        return PrefixCache(keys, values, first, layout)

    def action_pass(self, cache: PrefixCache, differentiable: bool = False) -> ActionPass:
        """What every sampling step shares (see `ActionPass`), computed once per call; `differentiable` for steps that
        are differentiated (RTC guidance)."""
        config = self.config
        first_slot = cache.slots - config.action_horizon
        kernel = self._kernel(cache.first.device, cache.keys[0].dtype, differentiable)
        stream = self._suffix_stream(cache.first, cache.layout, first_slot, (config.action_horizon,), kernel, cache.slots)
        weights = [layer.sampling_weights(vlm=False, expert=not differentiable)[1] for layer in self.layers]
        if config.pi05:
            return ActionPass(cache, stream, weights, None, None, None)
        expert_norms = [(layer.expert.attn_norm.params(), layer.expert.mlp_norm.params()) for layer in self.layers]
        action_weight = self.action_time_mlp_in.weight[:, : config.expert_hidden_size].t()
        return ActionPass(cache, stream, weights, action_weight, expert_norms, self.expert_final_norm.params())

    def denoise_step(
        self, actions: ActionPass, x_t: torch.Tensor, conditioning: StepConditioning, write_cache: bool = True
    ) -> torch.Tensor:
        """Velocity `[B, horizon, action_dim]` (float32) at `x_t` given the cached prefix (in `actions`, from
        `action_pass`) and this step's `conditioning`. `write_cache=False` leaves the cache untouched (a pure function
        of `x_t`, to differentiate through)."""
        tokens = self.embed_actions(x_t, conditioning.condition, actions.action_weight)
        norms = conditioning.layer_norms if self.config.pi05 else actions.expert_norms
        cache = actions.cache
        for layer, keys, values, layer_norms, weights in zip(self.layers, cache.keys, cache.values, norms, actions.expert_weights):
            _, tokens = layer(
                None, tokens, (None, actions.stream), (keys, values), layer_norms, write_cache=write_cache, weights=(CALL_MODULES, weights)
            )
        final_norm = conditioning.final_norm if self.config.pi05 else actions.final_norm
        velocity = self.action_out_proj(self.expert_final_norm(tokens, final_norm))
        return velocity.view(x_t.shape[0], -1, velocity.shape[-1]).float()

    def guided_velocity(
        self,
        actions: ActionPass,
        x_t: torch.Tensor,
        time: float,
        conditioning: StepConditioning,
        target: torch.Tensor,
        weights: torch.Tensor,
        max_guidance: float,
    ) -> torch.Tensor:
        """Inference-time real-time chunking: the velocity at `x_t`, corrected so that the predicted clean chunk
        `x0 = x_t - t * v` moves toward the previous chunk's `target` where the soft mask `weights` asks for it.

        `v' = v - w * J^T (W * (Y - x0))` with `J = dx0 / dx_t` (one vector-Jacobian product through the suffix;
        the prefix cache is a constant) and `w = min(beta, ((1 - t)^2 + t^2) / (t (1 - t)))`. The minus sign is
        openpi's convention: v points from data to noise and the Euler steps go down in t.
        """

        def clean_estimate(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            velocity = self.denoise_step(actions, x, conditioning, write_cache=False)
            return x - time * velocity, velocity

        predicted, pullback, velocity = torch.func.vjp(clean_estimate, x_t, has_aux=True)
        (correction,) = pullback(weights[..., None] * (target - predicted))
        return velocity - guidance_weight(time, max_guidance) * correction

    @torch.no_grad()
    def generate_actions(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        num_steps: int | None = None,
        generator: torch.Generator | None = None,
        previous_actions: torch.Tensor | None = None,
        inference_delay: int | torch.Tensor = 0,
        execution_horizon: int | torch.Tensor | None = None,
        rtc_method: str = "guidance",
        rtc_max_guidance: float = DEFAULT_MAX_GUIDANCE,
        rtc_schedule: str = "exp",
    ) -> torch.Tensor:
        """Sample an action chunk by Euler integration of the flow from noise (t = 1) to actions (t = 0).

        The prefix runs once (`cache_prefix`); each of the `num_steps` steps (default `config.num_inference_steps`)
        runs only the action tokens against the cached k/v. Everything that depends only on the flow time is computed
        for all steps up front. The Euler state is kept in float32 whatever the weights' dtype. The inputs are read on
        the host once, by their checks; after that nothing waits for the device (see `capture_sampling`).

        Real-time chunking (see `pi0_torch.models.rtc`): with `previous_actions`, the new chunk continues the one
        the robot is executing. Its index 0 is the step at which this inference starts, `execution_horizon` (`s`)
        steps after the previous one started, and the robot executes `inference_delay` (`d`) more of the previous
        chunk while this one computes. `rtc_method="guidance"` (inference-time RTC) steers every Euler step toward
        the previous chunk's remaining actions with the soft mask `rtc_schedule` and guidance weight clipped at
        `rtc_max_guidance` (beta; 0 gives plain sampling, bit for bit); `"conditioning"` (training-time RTC, for a
        model trained with `config.rtc_max_delay >= d`) gives the first `d` actions as committed (flow time 0) and
        returns them unchanged.

        Args: as [`forward`], plus `noise` `[B, horizon, action_dim]` (drawn with `generator` when not given),
            `previous_actions` float `[B, horizon, action_dim]` (model space, as this method returned it),
            `inference_delay` / `execution_horizon` ints or long `[B]`.

        Returns:
            float32 `[B, horizon, action_dim]` actions in normalized model space (see `PI0Processor` to map them
            back to robot units).
        """
        config = self.config
        times = tuple(euler_times(config.num_inference_steps if num_steps is None else num_steps))
        facts = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state, noise=noise)
        batch = len(facts.text_counts)
        if noise is None:
            noise = torch.randn(batch, config.action_horizon, config.action_dim, generator=generator, device=pixel_values.device)
        prefix = None
        if previous_actions is not None:
            prefix = self._chunk_prefix(batch, previous_actions, inference_delay, execution_horizon, rtc_method, rtc_max_guidance, rtc_schedule)
        method = None if prefix is None or (rtc_method == "guidance" and rtc_max_guidance == 0) else rtc_method
        graphs = self._graphs if pixel_values.is_cuda and self.replays_graphs(method) else None
        layout = facts.layout(config.tokens_per_image, self.GRAPH_PREFIX_BUCKET if graphs is not None else 1)
        pixel_values, image_masks = self._camera_inputs(pixel_values, image_masks, layout)
        inputs = SamplingInputs(
            pixel_values, image_masks, input_ids, attention_mask, state, noise.float(), self._times_on(times, pixel_values.device),
            target=prefix.target if method is not None else None,
            weights=prefix.weights if method == "guidance" else None,
            committed=prefix.committed if method == "conditioning" else None,
        )
        plan = SamplingPlan(layout, times, method, float(rtc_max_guidance) if method == "guidance" else 0.0)
        if self.sampling_compiled:
            _allow_recompiles(self.RECOMPILE_LIMIT)
        return self._sample(inputs, plan) if graphs is None else graphs.run(inputs, plan)

    def _sample(self, inputs: SamplingInputs, plan: SamplingPlan) -> torch.Tensor:
        """The sampling of `generate_actions` on checked inputs: no host reads, so it can be captured as a CUDA graph."""
        cache = self.cache_prefix(inputs, plan.layout)
        actions = self.action_pass(cache, differentiable=plan.rtc_method == "guidance")
        committed = inputs.committed
        steps = self.conditioning(inputs.times, actions.expert_weights if committed is None else None).steps()
        if committed is not None:  # committed actions take the conditioning of flow time 0
            clean = self.conditioning(inputs.times.new_zeros(1)).steps()[0]
            steps = [step.per_token(self.config.action_horizon, committed, clean) for step in steps]
        dt = -1.0 / len(plan.times)
        x_t = inputs.noise if committed is None else torch.where(committed[..., None], inputs.target, inputs.noise)
        for time, step in zip(plan.times, steps):
            if plan.rtc_method == "guidance":
                velocity = self.guided_velocity(actions, x_t, time, step, inputs.target, inputs.weights, plan.max_guidance)
            else:
                velocity = self.denoise_step(actions, x_t, step)
            x_t = torch.add(x_t, velocity, alpha=dt)
            if committed is not None:  # the committed actions stay as given
                x_t = torch.where(committed[..., None], inputs.target, x_t)
        return x_t

    def _times_on(self, times: tuple[float, ...], device: torch.device) -> torch.Tensor:
        """The Euler times as a float32 tensor on `device`, made once (no host-to-device copy per call)."""
        key = (times, device)
        if key not in self._device_times:
            self._device_times[key] = torch.tensor(times, dtype=torch.float32, device=device)
        return self._device_times[key]

    @staticmethod
    def _camera_inputs(pixel_values: torch.Tensor, image_masks: torch.Tensor, layout: PrefixLayout) -> tuple[torch.Tensor, torch.Tensor]:
        """The images and masks of the layout's cameras (all of them, usually: the tensors themselves)."""
        if len(layout.cameras) == pixel_values.shape[1]:
            return pixel_values, image_masks
        if not layout.cameras:
            return pixel_values[:, :0], image_masks[:, :0]
        return (torch.cat([pixel_values[:, c : c + 1] for c in layout.cameras], dim=1),
                torch.cat([image_masks[:, c : c + 1] for c in layout.cameras], dim=1))

    def _chunk_prefix(
        self,
        batch: int,
        previous_actions: torch.Tensor,
        inference_delay: int | torch.Tensor,
        execution_horizon: int | torch.Tensor | None,
        rtc_method: str,
        rtc_max_guidance: float,
        rtc_schedule: str,
    ) -> ChunkPrefix:
        """Check the real-time chunking arguments of `generate_actions` (previous chunk and guidance clip within
        `pi0_torch.models.rtc`'s bounds) and build the new chunk's prefix."""
        config = self.config
        _check_tensor("previous_actions", previous_actions, (batch, config.action_horizon, config.action_dim), floating=True)
        if execution_horizon is None:
            raise ValueError("execution_horizon is required with previous_actions: the steps of the previous chunk executed "
                             "between its inference start and this one's")
        if not isinstance(rtc_method, str) or rtc_method not in METHODS:
            raise ValueError(f"rtc_method must be one of {METHODS}, got {rtc_method!r:.60}")
        check_rtc_inputs("previous_actions", previous_actions, rtc_max_guidance)
        prefix = chunk_prefix(previous_actions.to(self.device), inference_delay, execution_horizon, rtc_schedule)
        longest = int(prefix.committed.sum(dim=1).max())
        if rtc_method == "conditioning" and longest > config.rtc_max_delay:
            raise ValueError(
                f"rtc_method='conditioning' needs a model trained with delays up to the inference delay ({longest}); this "
                f"one was trained with rtc_max_delay={config.rtc_max_delay} (train with --rtc-max-delay, or use 'guidance')"
            )
        return prefix

    # -- fast paths: compiled layers and CUDA graphs ---------------------------------------------------------------------

    @property
    def sampling_compiled(self) -> bool:
        """Whether the repeated layers run compiled (see `compile_sampling`)."""
        return any(layer.compiled for layer in self.layers)

    @property
    def sampling_captured(self) -> bool:
        """Whether `generate_actions` on CUDA replays CUDA graphs (see `capture_sampling`)."""
        return self._graphs is not None

    def replays_graphs(self, rtc_method: str | None = None) -> bool:
        """Whether `generate_actions` on CUDA replays CUDA graphs for chunks sampled with this real-time chunking method
        (None: plain sampling); see `capture_sampling`."""
        return self._graphs is not None and self._graphs.covers(rtc_method)

    def compile_sampling(self, disable: bool = False, **compile_kwargs: Any) -> None:
        """Opt in to `torch.compile`, regionally: each repeated layer (a joint decoder layer's `run`, a SigLIP encoder
        layer) is compiled once and the compiled code is reused by every layer of its kind; the rest stays eager.
        Seconds of compiling (a handful of graphs: each pass's layer, batch 1 and larger batches) instead of minutes
        for the whole unrolled sampling, and no recompiling for another prompt length or batch size.

        `compile_kwargs` go to `torch.compile`, with `fullgraph=True` and `dynamic=True` unless given.
        `mode="reduce-overhead"` means: compile, and (on CUDA) replay the whole sampling as one CUDA graph
        (`capture_sampling`), which then holds the compiled kernels; graphs switched on before stay on, captured
        again with the compiled layers. For inference: a compiled decoder layer skips gradient checkpointing.
        `compile_sampling(disable=True)` goes back to eager layers (and no graphs). Raises
        Dynamo's recompile limit to `RECOMPILE_LIMIT` when it is lower, here and in every thread that calls the model
        (Dynamo's settings are per thread): the compiled layers of every model in the process share their code.
        """
        vision_layers = self.vision_tower.encoder.layers
        if disable:
            self._graphs = None
            for layer in self.layers:
                layer.compile_run(disable=True)
            for layer in vision_layers:
                layer._compiled_call_impl = None  # (what `nn.Module.compile` set)
            return
        graph = compile_kwargs.get("mode") == "reduce-overhead"
        if graph:
            compile_kwargs.pop("mode")
        compile_kwargs.setdefault("fullgraph", True)
        compile_kwargs.setdefault("dynamic", True)  # one graph for every prompt length and batch size above 1
        _allow_recompiles(self.RECOMPILE_LIMIT)
        for layer in self.layers:
            layer.compile_run(**compile_kwargs)
        for layer in vision_layers:
            layer.compile(**compile_kwargs)
        if self._graphs is not None:
            self._graphs.clear()  # (they hold the eager layers' kernels)
        elif graph and self.device.type == "cuda":
            self.capture_sampling()

    def capture_sampling(self, disable: bool = False, batch_sizes: Sequence[int] | None = None, guidance: bool = True) -> None:
        """Opt in to CUDA graphs for `generate_actions` on CUDA: the sampling of each (batch size, step count, prompt
        length, prefix layout, real-time chunking method) is captured once (two warm-up runs, then the capture: its
        first call takes a few eager calls' time) and replayed after that, so the CPU launches one graph instead of
        thousands of kernels. Inputs are copied into the graph's static buffers; each call returns a tensor of its
        own. Plain sampling and both real-time chunking methods are captured, RTC "guidance" with its
        vector-Jacobian product per step (`guidance=False`: guided chunks sample eagerly). A model moved to another
        device or dtype captures again. Works with `compile_sampling` (the graphs then replay the compiled kernels;
        guidance's differentiated steps run the eager layers). With `batch_sizes`, another batch size is refused
        (`ValueError`) rather than captured mid-run. Should CUDA refuse a capture, the call raises
        `SamplingCaptureError`, except for guidance: a warning, and guided chunks sample eagerly from then on.
        `capture_sampling(disable=True)` goes back to eager.
        """
        from pi0_torch.models.sampling_graphs import SamplingGraphs

        sizes = None if batch_sizes is None else tuple(check_int("batch_sizes", size, minimum=1) for size in batch_sizes)
        self._graphs = None if disable else SamplingGraphs(self, sizes, guidance)

    def _apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """`nn.Module._apply` (what `.to()`, `.cuda()`, `.half()` ... run): captured graphs read the old tensors, so
        they are dropped and captured again on the next call."""
        if getattr(self, "_graphs", None) is not None:
            self._graphs.clear()
        self._device_times = {}
        return super()._apply(fn, *args, **kwargs)

    # -- input checks --------------------------------------------------------------------------------------------------

    def _check_placement(self) -> None:
        """Refuse a model that `from_pretrained(..., device_map=...)` split across devices or offloaded ("cpu" or
        "disk" among several places): offloaded weights stay on the `meta` device until the module holding them runs,
        and this model reads some outside their module's `forward` (the flow-time terms and the action expert's norm
        scales it computes once for every sampling step)."""
        places = {_place_name(place) for place in (getattr(self, "hf_device_map", None) or {}).values()}
        if len(places) > 1 or places & {"disk", "meta"}:
            raise ValueError(
                f"{type(self).__name__} was loaded with a device_map placing its weights on {sorted(places)}; it runs with "
                "every weight on one device: load it onto one (device_map=\"cuda\", or no device_map and then "
                ".to(device); a full-size model in bf16 needs about 7 GB of GPU memory)"
            )

    def _check_inputs(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None,
        **floats: torch.Tensor | None,
    ) -> InputFacts:
        """Validate the model inputs and read, in one device-to-host copy, every value their checks and the prefix
        layout need. Errors name the argument, expected and actual.

        `floats` are further float tensors to check when given: `noise` / `actions` `[B, horizon, action_dim]`, `time`
        `[B]` (all finite). Every tensor must be on the model's device.
        """
        config, device = self.config, self.device
        self._check_placement()
        if not isinstance(pixel_values, torch.Tensor) or pixel_values.dim() != 5:
            raise ValueError(
                f"pixel_values must be a float tensor [B, num_cameras={config.num_cameras}, 3, {config.image_size}, "
                f"{config.image_size}], got {describe(pixel_values)}"
            )
        batch = pixel_values.shape[0]
        if batch == 0:
            raise ValueError("pixel_values: a batch of 0 samples; expected at least one")
        image_shape = (batch, config.num_cameras, 3, config.image_size, config.image_size)
        _check_tensor("pixel_values", pixel_values, image_shape, floating=True, finite=False, device=device)
        _check_tensor("image_masks", image_masks, (batch, config.num_cameras), dtypes=(torch.bool,), device=device)
        if (not isinstance(input_ids, torch.Tensor) or input_ids.dim() != 2 or input_ids.shape[0] != batch
                or not 1 <= input_ids.shape[1] <= config.max_token_len):
            raise ValueError(
                f"input_ids must be a torch.Tensor [B={batch}, L] with 1 <= L <= max_token_len={config.max_token_len}, "
                f"got {describe(input_ids)}"
            )
        _check_tensor("input_ids", input_ids, tuple(input_ids.shape), dtypes=(torch.long, torch.int32), device=device)
        _check_tensor("attention_mask", attention_mask, tuple(input_ids.shape), dtypes=(torch.bool, torch.long, torch.int32), device=device)
        if not config.pi05 or state is not None:
            if state is None:
                raise ValueError(f"state is required by pi0: a float tensor [B={batch}, action_dim={config.action_dim}]")
            floats = {"state": state, **floats}
        shapes = {"state": (batch, config.action_dim), "time": (batch,)}
        checked = {name: value for name, value in floats.items() if value is not None}
        for name, value in checked.items():
            _check_tensor(name, value, shapes.get(name, (batch, config.action_horizon, config.action_dim)), floating=True, finite=False, device=device)

        # the one read: pixel range, token id range, finiteness, cameras shown and text tokens per sample
        ranges = torch.cat([torch.stack(pixel_values.aminmax()).float(), torch.stack(input_ids.aminmax()).float()])
        finite = [torch.isfinite(value).all() for value in checked.values()]
        read = torch.cat([
            ranges, torch.stack(finite).float() if finite else ranges.new_empty(0), image_masks.flatten().float(),
            attention_mask.sum(dim=1).float(),
        ]).cpu().tolist()
        pixel_low, pixel_high, id_low, id_high = read[:4]
        if not -1.001 <= pixel_low <= pixel_high <= 1.001:  # (NaN fails every comparison)
            raise ValueError(
                f"pixel_values must lie in [-1, 1] (uint8 images map to x / 255 * 2 - 1), got range [{pixel_low:.4g}, {pixel_high:.4g}]"
            )
        if id_low < 0 or id_high >= config.vocab_size:
            raise ValueError(
                f"input_ids must be token ids in [0, vocab_size={config.vocab_size}), got values in "
                f"[{int(id_low)}, {int(id_high)}] (a tokenizer larger than the model's vocabulary?)"
            )
        for (name, value), is_finite in zip(checked.items(), read[4 : 4 + len(checked)]):
            if not is_finite:
                raise nonfinite_error(name, value)
        masks_start = 4 + len(checked)
        cameras = config.num_cameras
        shown = read[masks_start : masks_start + batch * cameras]
        return InputFacts(
            image_masks=tuple(tuple(bool(v) for v in shown[b * cameras : (b + 1) * cameras]) for b in range(batch)),
            text_counts=tuple(int(v) for v in read[masks_start + batch * cameras :]),
            text_length=input_ids.shape[1],
        )


def _allow_recompiles(limit: int) -> None:
    """Raise Dynamo's recompile limit per code object to `limit` where it is lower, for the calling thread: torch keeps
    a user's Dynamo settings per thread, so a server's model thread needs its own."""
    config = torch._dynamo.config
    name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"  # (torch < 2.7)
    if getattr(config, name) < limit:
        setattr(config, name, limit)


def _place_name(place: int | str | torch.device) -> str:
    """A device map's place as one name per device: "cuda:0" for 0 (on a CUDA machine), "cuda" and "cuda:0"; "disk"
    as it is."""
    try:
        device = torch.device(place)
    except RuntimeError:  # "disk"; an index where no accelerator is
        return str(place)
    return device.type if device.type in ("cpu", "meta") else f"{device.type}:{device.index or 0}"


@functools.lru_cache(maxsize=None)
def _rounded_sqrt(width: int, dtype: torch.dtype) -> float:
    """sqrt(width) rounded to `dtype` (openpi scales text embeddings by `sqrt(D).astype(x.dtype)`)."""
    return float(torch.tensor(math.sqrt(width), dtype=dtype))
