"""The layers of π0 / π0.5's two-expert Gemma, as openpi's `gemma.py` computes them: RMSNorm and adaRMS, RoPE, one
expert's weights, and one decoder layer run by both experts at once.

Shapes: B batch, T tokens of a stream, N query heads, K kv heads, H head size, D an expert's width. Inside a layer
each expert's tokens are 2-D, `[B * T, D]`, the layout its projections take without reshaping.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn
from transformers.modeling_layers import GradientCheckpointingLayer

from pi0_torch.inference.attention import attend

if TYPE_CHECKING:
    from pi0_torch.inference.attention import AttentionPlan
    from pi0_torch.models.configuration_pi0 import PI0Config

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
    # the inference engine's: `shift @ W^T` of the projection after the norm, added in its GEMM (see
    # `pi0_torch.inference.layer_pass.project_normed`)
    shift_projected: torch.Tensor | None = None

    def tensors(self) -> list[torch.Tensor]:
        return [t for t in (self.scale, self.shift, self.gate, self.shift_projected) if t is not None]

    def rebuilt(self, values: Iterator[torch.Tensor]) -> NormParams:
        """The same structure holding the next tensors of `values` (see `StepConditioning.map`)."""
        optional = (self.shift, self.gate, self.shift_projected)
        return NormParams(next(values), *(None if t is None else next(values) for t in optional))


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

    `params(condition)` = `self.modulation(condition)` split into [scale | shift | gate] (computed once for all
    sampling steps, see `PI0ForActionGeneration.conditioning`); `forward(x, params)` = `normalize(x) * (1 + scale)
    + shift` in float32, returned in the input dtype.
    """

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.modulation = nn.Linear(dim, 3 * dim)

    def params(self, condition: torch.Tensor) -> NormParams:
        scale, shift, gate = self.modulation(condition).chunk(3, dim=-1)
        return NormParams(1 + scale, shift, gate)

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


def gated_residual(residual: torch.Tensor, y: torch.Tensor, gate: torch.Tensor | None) -> torch.Tensor:
    """The residual update after attention and after the MLP: `residual + y`, or (adaRMS) `residual + y * gate`."""
    return residual + y if gate is None else torch.addcmul(residual, y, gate)


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
    """

    def __init__(self, config: PI0Config) -> None:
        super().__init__()
        self.vlm = ExpertLayer(config, config.vlm_hidden_size, config.vlm_intermediate_size, adaptive=False)
        self.expert = ExpertLayer(config, config.expert_hidden_size, config.expert_intermediate_size, config.pi05)
        self.head_dim = config.head_dim

    def forward(
        self,
        prefix: torch.Tensor | None,  # [B * P, D0]
        suffix: torch.Tensor | None,  # [B * S, D1]
        streams: tuple[StreamPass | None, StreamPass | None],  # (prefix, suffix) of the pass
        cache: tuple[torch.Tensor, torch.Tensor] | None = None,  # this layer's k/v buffers [B, K, slots, H]
        expert_norms: tuple[NormParams, NormParams] | None = None,  # the action expert's (attention, MLP) norms
        keys_only: bool = False,
        write_cache: bool = True,
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Returns the updated (prefix, suffix).

        With `cache`, each stream's post-RoPE k/v are written into the buffers at its slots and every stream attends
        to the buffers (`write_cache=False`: to a copy of their first slots with the new k/v after them, the cache
        untouched: a sampling step that is differentiated). Without (a training pass) the streams attend to their own
        k/v. `expert_norms` default to the action expert's own RMSNorm weights (π0; π0.5 passes its adaRMS params).
        `keys_only` stops once the k/v are written (the last layer of the cached prefix: its outputs are never read)
        and returns (None, None).
        """
        layers = ((self.vlm, prefix, None), (self.expert, suffix, expert_norms))
        queries: list[torch.Tensor | None] = [None, None]
        new_keys, new_values = [], []  # [B, K, T, H] of the streams that do not write into a cache
        for index, ((expert, x, norms), stream) in enumerate(zip(layers, streams)):
            if x is None:
                continue
            qkv = expert.qkv_proj(expert.attn_norm(x, norms[0] if norms is not None else None))  # [B * T, (N + 2K) H]
            heads, kv_heads = expert.heads[:2]
            qk, v = qkv.view(-1, stream.tokens, qkv.shape[-1] // self.head_dim, self.head_dim).split(
                (heads + kv_heads, kv_heads), dim=2
            )
            q, k = apply_rope(qk, stream.cos, stream.sin).split((heads, kv_heads), dim=2)  # one rotation for both
            k, v = k.to(x.dtype).transpose(1, 2), v.transpose(1, 2)  # [B, K, T, H]
            if cache is not None and write_cache:  # (`.to`: under autocast the cache and the streams' dtypes differ)
                cache[0].index_copy_(2, stream.slots, k.to(cache[0].dtype))
                cache[1].index_copy_(2, stream.slots, v.to(cache[1].dtype))
            else:
                new_keys.append(k)
                new_values.append(v)
            if not keys_only:
                queries[index] = q.to(x.dtype).contiguous()  # [B, T, N, H] (its own tensor: `attend` folds heads)
        if keys_only:
            return None, None
        keys, values = _pass_keys(cache, write_cache, streams, new_keys, new_values)

        outputs: list[torch.Tensor | None] = [None, None]
        for index, ((expert, x, norms), stream) in enumerate(zip(layers, streams)):
            if x is None:
                continue
            attn_params, mlp_params = norms if norms is not None else (None, None)
            attended = attend(queries[index], keys, values, stream.attention)  # [B * T, N * H]
            x = gated_residual(x, expert.o_proj(attended), attn_params.gate if attn_params is not None else None)
            hidden = expert.geglu(expert.gate_up_proj(expert.mlp_norm(x, mlp_params)))
            outputs[index] = gated_residual(x, expert.down_proj(hidden), mlp_params.gate if mlp_params is not None else None)
        return outputs[0], outputs[1]


def _pass_keys(
    cache: tuple[torch.Tensor, torch.Tensor] | None,
    write_cache: bool,
    streams: tuple[StreamPass | None, StreamPass | None],
    new_keys: list[torch.Tensor],
    new_values: list[torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The k/v a pass attends to `[B, K, slots, H]`: its own (a training pass, prefix slots first), the cache's first
    slots and then its own (`write_cache=False`), or the cache it wrote into."""
    if cache is None:
        return torch.cat(new_keys, dim=2), torch.cat(new_values, dim=2)
    if not write_cache:
        first_slot = next(stream.first_slot for stream in streams if stream is not None)
        return (torch.cat([cache[0][:, :, :first_slot], *new_keys], dim=2),
                torch.cat([cache[1][:, :, :first_slot], *new_values], dim=2))
    return cache
