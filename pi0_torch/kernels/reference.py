"""The fused ops of a sampling step, in plain torch: what each Triton kernel computes, the oracle it is tested against,
and the path every device without the kernels runs (the CPU: the same ops, in the same order, as the engine's
unfused sampling pass, so its numbers stay bit for bit what they were). First the math the model's layers and the
kernels share: Gemma's RMSNorm, RoPE and GeGLU.

Shapes: M = B * T token rows (sample-major), D the expert's width, N query heads, one kv head, H head size, F the MLP
width, S the k/v cache's slots, A the action dim. Weights are the projections' weights transposed (`[in, out]`
views, as `pi0_torch.inference.layer_pass.SamplingWeights` holds them).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F

# -- the shared math: Gemma's RMSNorm, RoPE and GeGLU (`pi0_torch.models.layers` builds the layers on them) ----------

_FUSED_RMS_NORM = getattr(torch.ops.aten, "_fused_rms_norm", None)  # one kernel (recent torch); else the formula


def rms_norm(x: torch.Tensor, eps: float, weight: torch.Tensor | None = None) -> torch.Tensor:
    """`x * rsqrt(mean(x^2) + eps)`, times `weight` if given, in float32 arithmetic; returned in `x`'s dtype."""
    if _FUSED_RMS_NORM is not None and (weight is None or weight.dtype == x.dtype):
        return _FUSED_RMS_NORM(x, [x.shape[-1]], weight, eps)[0]
    x32 = x.float()
    normed = x32 * torch.rsqrt(x32.pow(2).mean(dim=-1, keepdim=True) + eps)
    return (normed if weight is None else normed * weight).to(x.dtype)


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


def geglu(gate_up: torch.Tensor) -> torch.Tensor:
    """`gelu_tanh(gate) * up` `[M, F]` of a gate/up projection's output `[M, 2F]` (the MLP between its projections)."""
    gate, up = gate_up.chunk(2, dim=-1)
    return F.gelu(gate, approximate="tanh") * up


# -- the fused ops ---------------------------------------------------------------------------------------------------


def embed_actions(
    x_t: torch.Tensor,  # float32 [B, horizon, A]
    weight: torch.Tensor,  # [A, D]: action_in_proj's weight transposed (π0: times the action half of action_time_mlp_in)
    bias: torch.Tensor,  # [D]
    out_weight: torch.Tensor | None,  # π0: action_time_mlp_out's weight transposed [D, D]; π0.5: None
    out_bias: torch.Tensor | None,  # π0: [D]
) -> torch.Tensor:
    """The action tokens `[B * horizon, D]` of a sampling step: π0.5 `x_t W + b` (action_in_proj), π0
    `silu(x_t W + b) W_out + b_out`, where `W` and `b` fold action_in_proj into the action half of action_time_mlp_in
    and `b` holds the step's time half (two linear maps in a row are one); `x_t` is read in the weights' dtype."""
    tokens = torch.addmm(bias, x_t.flatten(0, 1).to(weight.dtype), weight)
    return tokens if out_weight is None else torch.addmm(out_bias, F.silu(tokens), out_weight)


def add_layer_norm_(
    residual: torch.Tensor,  # [M, D], updated in place
    y: torch.Tensor,  # [M, D]
    weight: torch.Tensor,  # [D]
    bias: torch.Tensor,  # [D]
    eps: float,
) -> torch.Tensor:
    """SigLIP's residual update and the LayerNorm after it: `residual += y`, returns `layer_norm(residual)` `[M, D]`."""
    residual.add_(y)
    return F.layer_norm(residual, residual.shape[-1:], weight, bias, eps)


def norm_qkv_rope(
    x: torch.Tensor,  # [M, D]
    scale: torch.Tensor,  # [D]: the norm's (1 + weight) or adaRMS (1 + scale)
    bias: torch.Tensor | None,  # [(N + 2) H]: adaRMS `shift @ W`, or None
    weight: torch.Tensor,  # [D, (N + 2) H], columns q | k | v
    cos: torch.Tensor,  # [B or 1, T, H] float32, `rope_cos_sin`'s tables
    sin: torch.Tensor,
    key_cache: torch.Tensor,  # [B, S, H]: written at slots first_slot + t
    value_cache: torch.Tensor,
    first_slot: int,
    eps: float,
) -> torch.Tensor:
    """RMSNorm, the q/k/v projection, RoPE on q and k; k and v written into the caches. Returns q `[M, N * H]`."""
    qkv = normed_projection(x, scale, bias, weight, eps)  # [M, (N + 2) H]
    return rope_cache_write(qkv, cos, sin, key_cache, value_cache, first_slot)


def normed_projection(
    x: torch.Tensor,  # [M, D]
    scale: torch.Tensor,  # [D]
    bias: torch.Tensor | None,  # [C]: adaRMS `shift @ W`, or None
    weight: torch.Tensor,  # [D, C]
    eps: float,
) -> torch.Tensor:
    """`rms_norm(x) * scale @ weight (+ bias)` `[M, C]`, rounded once after the norm and once after the GEMM."""
    normed = rms_norm(x, eps, scale)
    return torch.mm(normed, weight) if bias is None else torch.addmm(bias, normed, weight)


def rope_cache_write(
    qkv: torch.Tensor,  # [M, (N + 2) H]: a q/k/v projection's output
    cos: torch.Tensor,  # [B or 1, T, H] float32
    sin: torch.Tensor,
    key_cache: torch.Tensor,  # [B, S, H]: written at slots first_slot + t
    value_cache: torch.Tensor,
    first_slot: int,
    slot: torch.Tensor | None = None,  # long [1]: the first slot as a device value (π0-FAST's decoding), for first_slot
) -> torch.Tensor:
    """RoPE on q and k (one rotation for both, float32, rounded once); k and v written into the caches. Returns q
    `[M, N * H]`."""
    batch, slots, head_dim = key_cache.shape
    tokens = qkv.shape[0] // batch
    qk, v = qkv.view(batch, tokens, -1, head_dim).split((qkv.shape[-1] // head_dim - 1, 1), dim=2)
    rounded = qk.new_empty(qk.shape) if qk.dtype != torch.float32 else None  # (bf16: the rotation rounds itself)
    q, k = apply_rope(qk, cos[:, :, None], sin[:, :, None], out=rounded).split((qk.shape[2] - 1, 1), dim=2)
    cache_rows = torch.arange(tokens, device=qkv.device) + (first_slot if slot is None else slot)
    key_cache.index_copy_(1, cache_rows, k[:, :, 0].to(key_cache.dtype))
    value_cache.index_copy_(1, cache_rows, v[:, :, 0])
    return q.to(qkv.dtype).reshape(qkv.shape[0], -1).contiguous()  # (one token: the reshape alone is a strided view)


def norm_gate_up_geglu(
    x: torch.Tensor,  # [M, D]
    scale: torch.Tensor,  # [D]
    bias: torch.Tensor | None,  # [2F]: adaRMS `shift @ W`, or None
    weight: torch.Tensor,  # [D, 2F], columns gate | up
    eps: float,
) -> torch.Tensor:
    """RMSNorm, the gate/up projection and the GeGLU between the MLP's projections: `gelu_tanh(gate) * up` `[M, F]`."""
    return geglu(normed_projection(x, scale, bias, weight, eps))


def matmul_residual_(
    residual: torch.Tensor,  # [M, D], updated in place
    y: torch.Tensor,  # [M, K]
    weight: torch.Tensor,  # [K, D]
    gate: torch.Tensor | None,  # [D]: adaRMS's residual gate, or None
) -> None:
    """`residual += y @ weight` (adaRMS: `residual += (y @ weight) * gate`), in place."""
    if gate is None:
        residual.addmm_(y, weight)
    else:
        residual.addcmul_(torch.mm(y, weight), gate)


def range_attention(
    query: torch.Tensor,  # [B, T, N, H] post-RoPE, unscaled
    key_cache: torch.Tensor,  # [B, S, H]
    value_cache: torch.Tensor,
    first: torch.Tensor,  # long [B]: each sample's first visible key
    row_ends: torch.Tensor,  # long [T]: the key where each token's range ends (exclusive)
) -> torch.Tensor:
    """Attention of every query head over its token's key range `[first[b], row_ends[t])` of the one kv head, logits
    scaled by `H ** -0.5`, softmax in float32. Returns `[B * T, N * H]`."""
    batch, tokens, heads, head_dim = query.shape
    keys = torch.arange(key_cache.shape[1], device=query.device)
    visible = (keys[None, None, :] >= first[:, None, None]) & (keys[None, None, :] < row_ends[None, :, None])  # [B, T, S]
    read = visible.any(dim=1)[..., None]  # [B, S, 1]: the slots some row sees (the others may hold anything, NaN too)
    logits = torch.einsum("btnh,bsh->btns", query.float(), key_cache.float().masked_fill(~read, 0)) * head_dim**-0.5
    logits = logits.masked_fill(~visible[:, :, None, :], float("-inf"))
    weights = torch.softmax(logits, dim=-1)
    attended = torch.einsum("btns,bsh->btnh", weights, value_cache.float().masked_fill(~read, 0))
    return attended.to(query.dtype).reshape(batch * tokens, heads * head_dim)


def norm_linear_euler_(
    x_t: torch.Tensor,  # float32 [B, horizon, A], updated in place
    tokens: torch.Tensor,  # [B * horizon, D]: the action tokens after the last layer
    scale: torch.Tensor,  # [D]: the final norm's scale
    bias: torch.Tensor,  # [A]: action_out_proj's bias (π0.5: plus the final adaRMS `shift @ W`)
    weight: torch.Tensor,  # [D, A]: action_out_proj's weight, transposed
    dt: float,
    eps: float,
) -> None:
    """The last of a sampling step: the final norm, `action_out_proj` and the Euler update `x_t += dt * velocity`."""
    velocity = torch.addmm(bias, rms_norm(tokens, eps, scale), weight)
    x_t.add_(velocity.view(x_t.shape).float(), alpha=dt)


def expert_layers_(
    x: torch.Tensor,  # [M, D], updated in place
    attention_scales: torch.Tensor,  # [L, D]: each layer's attention norm scale (adaRMS: this step's)
    qkv: list[torch.Tensor],  # L x [D, (N + 2) H]
    o: list[torch.Tensor],  # L x [N H, D]
    mlp_scales: torch.Tensor,  # [L, D]
    gate_up: list[torch.Tensor],  # L x [D, 2 F]
    down: list[torch.Tensor],  # L x [F, D]
    cos: torch.Tensor,  # [B or 1, T, H] float32
    sin: torch.Tensor,
    key_cache: torch.Tensor,  # [L, B, S, H], the action tokens' slots written here
    value_cache: torch.Tensor,
    first: torch.Tensor,  # long [B]
    row_ends: torch.Tensor,  # long [T]
    first_slot: int,
    eps: float,
    qkv_bias: torch.Tensor | None = None,  # π0.5: [L, (N + 2) H]
    o_gate: torch.Tensor | None = None,  # π0.5: [L, D]
    gate_up_bias: torch.Tensor | None = None,  # π0.5: [L, 2 F]
    down_gate: torch.Tensor | None = None,  # π0.5: [L, D]
    implementations: tuple[Callable[..., Any], ...] | None = None,
) -> None:
    """Every decoder layer of the action expert in one sampling step, on the action tokens `x` (`B` samples of `T`):
    per layer `norm_qkv_rope`, `range_attention`, `matmul_residual_` (o), `norm_gate_up_geglu`, `matmul_residual_`
    (down), π0.5's adaRMS biases and gates from the layer's rows. The stacked arguments may also be lists of each
    layer's. `implementations`: what runs those four ops (`ops.expert_layers_op_by_op_` passes their kernels; by
    default these references)."""
    norm_qkv, attention, matmul_residual, norm_mlp = implementations or (
        norm_qkv_rope, range_attention, matmul_residual_, norm_gate_up_geglu)
    batch, head_dim = key_cache[0].shape[0], key_cache[0].shape[-1]
    for layer in range(len(qkv)):
        keys, values = key_cache[layer], value_cache[layer]
        bias, gate = (None, None) if qkv_bias is None else (qkv_bias[layer], o_gate[layer])
        q = norm_qkv(x, attention_scales[layer], bias, qkv[layer], cos, sin, keys, values, first_slot, eps)
        attended = attention(q.view(batch, -1, q.shape[-1] // head_dim, head_dim), keys, values, first, row_ends)
        matmul_residual(x, attended, o[layer], gate)
        bias, gate = (None, None) if qkv_bias is None else (gate_up_bias[layer], down_gate[layer])
        matmul_residual(x, norm_mlp(x, mlp_scales[layer], bias, gate_up[layer], eps), down[layer], gate)
