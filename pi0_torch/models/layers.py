"""The layers of π0 / π0.5's two-expert Gemma, as openpi's `gemma.py` computes them: RMSNorm and adaRMS, RoPE, one
expert's weights, and one decoder layer run by both experts at once.

Shapes: B batch, T tokens of a stream, N query heads, K kv heads, H head size, D an expert's width. Inside a layer
each expert's tokens are 2-D, `[B * T, D]`, the layout its projections take without reshaping.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.triton_guard import set_aside_broken_triton

set_aside_broken_triton()  # (before transformers' model layers import torch's compiler, which imports triton)
import torch  # noqa: E402
from torch import nn  # noqa: E402
from transformers.modeling_layers import GradientCheckpointingLayer  # noqa: E402

from pi0_torch.inference.attention import attend  # noqa: E402
from pi0_torch.inference.conditioning import NormParams, StepConditioning  # noqa: E402, F401 (re-exported: older path)
from pi0_torch.inference.layout import StreamPass  # noqa: E402
from pi0_torch.kernels.reference import apply_rope, geglu, rms_norm, rope_cos_sin  # noqa: E402, F401 (re-exported)

if TYPE_CHECKING:
    from pi0_torch.models.configuration_pi0 import PI0Config

# ----------------------------------------------------------------------------------------------------------------------
# Normalisation (the math itself, `rms_norm`, RoPE and GeGLU, is `pi0_torch.kernels.reference`'s, shared with the kernels)
# ----------------------------------------------------------------------------------------------------------------------

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

    geglu = staticmethod(geglu)  # the MLP between its projections: `gelu_tanh(gate) * up` of `gate_up_proj`'s output


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
