"""Sampling in the fused ops of `pi0_torch.kernels`.

- Each Euler step of the action expert (`FusedSteps`): the action tokens in one launch (π0: with the action/time MLP),
  then per decoder layer five launches (norm + q/k/v + RoPE + cache write, attention over the key range, o-projection
  + residual, norm + gate/up + GeGLU, down-projection + residual; `sampling_kernels="persistent"`: every layer of the
  step in one persistent launch, `kernels.persistent.expert_layers_`), then the final norm, `action_out_proj` and the
  Euler update in one.
- The prefix pass (`prefix_layer`): the VLM's GEMMs stay cuBLAS's (compute-bound at 800+ rows) with RoPE and the cache
  write, and the GeGLU, fused around them (nine launches per layer instead of fifteen; π0's state token runs with the
  first step's action tokens, `FusedSteps`). SigLIP runs `vision_pass` (nine launches per encoder layer, not twelve).

It computes what `ActionSampling.denoise_step` followed by `x_t += dt * velocity` computes, with fewer roundings in
bf16 (the fused epilogues round once). Used for plain sampling on CUDA in bf16 / fp16 (`ActionSampling.sampling_kernels`,
"auto"); what decides that it may run, and verifies it, is `pi0_torch.inference.checks`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference.attention import attend
from pi0_torch.inference.conditioning import NormParams, StepConditioning
from pi0_torch.kernels import ops
from pi0_torch.kernels.reference import rms_norm

if TYPE_CHECKING:
    from pi0_torch.inference.layer_pass import SamplingWeights
    from pi0_torch.inference.layout import StreamPass
    from pi0_torch.inference.sampling import ActionPass
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

@dataclass
class FusedSteps:
    """What every fused step of one call shares: each step's `expert_layers_` arguments (stacked `[L, ...]` for the
    persistent launch, lists of each layer's views for five launches per layer), the action embedding's weights and
    each step's bias (π0: action_in_proj folded into the action half of action_time_mlp_in, the step's time half in
    the bias), and the final norm's scale and bias of each step (`action_out_proj`'s, plus π0.5's adaRMS shift).

    π0's state token (`PrefixCache.state`) runs with the first step's action tokens, ahead of them in its slot: it
    sees the prefix and itself, they see it too, and its keys and values stay in the caches for the other steps. So
    the action expert's weights are read once less per chunk than with a pass of its own (as openpi's suffix computes
    it, where every step recomputes it)."""

    persistent: bool
    layer_arguments: list[tuple[Any, ...]]  # per step (π0: the first step's with the state token ahead of its tokens)
    state: torch.Tensor | None  # π0: the state token [B, D1], run by the first step
    in_weight: torch.Tensor  # [A, D1]
    in_biases: torch.Tensor  # [steps or 1, D1]
    mlp_out: tuple[torch.Tensor, torch.Tensor] | None  # π0: action_time_mlp_out's weight [D1, D1] (transposed), bias
    out_weight: torch.Tensor  # [D1, A]
    final_scales: torch.Tensor  # [steps or 1, D1]
    final_biases: torch.Tensor  # [steps or 1, A]
    eps: float  # the norms'

    @classmethod
    def build(cls, model: PI0ForActionGeneration, actions: ActionPass, conditioning: StepConditioning, steps: int,
              persistent: bool = False) -> FusedSteps:
        """`conditioning`: every step's, with the time axis first (`ActionSampling.step_conditioning`)."""
        config = model.config
        cache, stream = actions.cache, actions.stream
        norms = conditioning.layer_norms if config.pi05 else actions.expert_norms  # per layer: (attention, MLP)
        names = ((0, "scale"), (1, "scale"))  # (π0.5: then its adaRMS biases and gates)
        names += ((0, "shift_projected"), (0, "gate"), (1, "shift_projected"), (1, "gate")) if config.pi05 else ()
        if persistent:  # (stacked: [L, ...] per step, the caches [L, B, S, H])
            keys, values = (buffer[:, :, 0] for buffer in cache.buffers)
            stacked = [torch.stack([getattr(pair[index], name) for pair in norms], dim=-2) for index, name in names]
            per_step = [[each[step] if config.pi05 else each for each in stacked] for step in range(steps)]
        else:  # (lists of each layer's, the caches [B, S, H] views)
            keys, values = ([each[:, 0] for each in buffers] for buffers in (cache.keys, cache.values))
            step_norms = [step.layer_norms for step in conditioning.steps()] if config.pi05 else [norms] * steps
            per_step = [[[getattr(pair[index], name) for pair in layer_norms] for index, name in names]
                        for layer_norms in step_norms]
        qkv, o, gate_up, down = (list(each) for each in zip(*((own.qkv, own.o, own.gate_up, own.down)
                                                               for own in actions.expert_weights)))
        device = cache.first.device
        first_slot = stream.first_slot
        slotted = [((stream.cos[:, :, 0], stream.sin[:, :, 0]), torch.full((stream.tokens,), cache.slots, device=device),
                    first_slot)] * steps  # per step: the RoPE tables, each token's key end, the first slot
        if cache.state is not None:  # (the state token's slot, then the action tokens': it sees only up to itself)
            first_slot -= 1
            joint_ends = torch.full((1 + stream.tokens,), cache.slots, device=device)
            joint_ends[0] = first_slot + 1
            slotted[0] = (tuple(table[:, first_slot : cache.slots] for table in cache.rope), joint_ends, first_slot)
        layer_arguments = [(scales, qkv, o, mlp_scales, gate_up, down, *tables, keys, values, cache.first, ends, slot,
                            config.rms_norm_eps, *(adarms or (None,) * 4))
                           for (scales, mlp_scales, *adarms), (tables, ends, slot) in zip(per_step, slotted)]
        out_weight = model.action_out_proj.weight.t()
        final: NormParams = conditioning.final_norm if config.pi05 else actions.final_norm
        final_biases = model.action_out_proj.bias[None]
        if final.shift is not None:
            final_biases = torch.addmm(final_biases, final.shift, out_weight)  # [steps, A]
        in_weight, in_biases, mlp_out = model.action_in_proj.weight.t(), model.action_in_proj.bias[None], None
        if not config.pi05:  # (x W_in + b_in) W_a + c = x (W_in W_a) + (b_in W_a + c)
            in_biases = torch.addmm(conditioning.condition, in_biases.expand(steps, -1), actions.action_weight)  # [steps, D1]
            in_weight = torch.mm(in_weight, actions.action_weight)
            mlp_out = (model.action_time_mlp_out.weight.t(), model.action_time_mlp_out.bias)
        return cls(persistent, layer_arguments, cache.state, in_weight, in_biases, mlp_out, out_weight,
                   final.scale.view(-1, final.scale.shape[-1]), final_biases, config.rms_norm_eps)

    def step_(self, x_t: torch.Tensor, index: int, dt: float) -> None:
        """The `index`-th Euler step of the call at `x_t` (float32 `[B, horizon, A]`, updated in place)."""
        row = index if self.in_biases.shape[0] > 1 else 0  # (π0: a time half per step)
        tokens = ops.call(ops.embed_actions, x_t, self.in_weight, self.in_biases[row], *(self.mlp_out or (None, None)))  # [B * T, D1]
        joint = tokens
        if index == 0 and self.state is not None:  # [B * (1 + T), D1]: each sample's state token, then its action tokens
            batch, width = self.state.shape
            joint = torch.cat((self.state[:, None], tokens.view(batch, -1, width)), dim=1).view(-1, width)
        if self.persistent:
            ops.call(ops.expert_layers_, joint, *self.layer_arguments[index])
        else:
            ops.expert_layers_op_by_op_(joint, *self.layer_arguments[index])
        if joint is not tokens:  # (a view at batch 1, a copy else)
            tokens = joint.view(batch, -1, width)[:, 1:].reshape(-1, width)
        row = index if self.final_scales.shape[0] > 1 else 0  # (π0.5: a final norm per step)
        ops.call(ops.norm_linear_euler_, x_t, tokens, self.final_scales[row], self.final_biases[row], self.out_weight, dt,
                 self.eps)


def prefix_layer(
    prefix: torch.Tensor,  # [B * P, D0], updated in place
    stream: StreamPass,  # the prefix's
    cache: tuple[torch.Tensor, torch.Tensor],  # [B, 1, S, H]
    scales: list[torch.Tensor],  # the VLM's attention and MLP norm scales (1 + weight)
    weights: SamplingWeights,  # the VLM's
    eps: float,
    keys_only: bool,
) -> torch.Tensor | None:
    """`sampling_layer_pass` of the prefix in the fused ops around cuBLAS's GEMMs; returns the prefix (None with
    `keys_only`: the last layer writes its keys and values, and nothing reads its output)."""
    keys, values = cache[0][:, 0], cache[1][:, 0]  # [B, S, H]
    batch, head_dim = keys.shape[0], keys.shape[-1]
    qkv = torch.mm(rms_norm(prefix, eps, scales[0]), weights.qkv)
    q = ops.call(ops.rope_cache_write, qkv, stream.cos[:, :, 0], stream.sin[:, :, 0], keys, values, 0)
    if keys_only:
        return None
    attended = attend(q.view(batch, stream.tokens, -1, head_dim), cache[0], cache[1], stream.attention)
    prefix.addmm_(attended, weights.o)
    prefix.addmm_(ops.call(ops.geglu, torch.mm(rms_norm(prefix, eps, scales[1]), weights.gate_up)), weights.down)
    return prefix
