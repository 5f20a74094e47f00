"""Sampling in the fused ops of `pi0_torch.kernels`.

- Each Euler step of the action expert (`FusedSteps`): the action tokens in one launch (π0: with the action/time MLP),
  then per decoder layer five launches (norm + q/k/v + RoPE + cache write, attention over the key range, o-projection
  + residual, norm + gate/up + GeGLU, down-projection + residual; `sampling_kernels="persistent"`: every layer of the
  step in one persistent launch, `kernels.persistent.expert_layers_`), then the final norm, `action_out_proj` and the
  Euler update in one.
- The prefix pass (`prefix_layer`): the VLM's GEMMs stay cuBLAS's (compute-bound at 800+ rows) with RoPE and the cache
  write, and the GeGLU, fused around them (nine launches per layer instead of fifteen). π0's state token, one row
  that sees the prefix and itself, runs with the first step's action tokens (`FusedSteps`). SigLIP runs
  `vision_pass` (nine launches per encoder layer instead of twelve).

It computes what `ActionSampling.denoise_step` followed by `x_t += dt * velocity` computes, with fewer roundings in
bf16 (the fused epilogues round once). Used for plain sampling on CUDA in bf16 / fp16 (`ActionSampling.sampling_kernels`,
"auto"), after `fused_kernels_reason` found the kernels equal to their torch references at the model's own sizes on
that device (once per device, dtype and sizes); real-time chunking's steps run unfused.

Triton compiles a kernel anew for each class of its arguments (block sizes chosen by row count, an integer equal to
1 or divisible by 16), so the batch sizes and prompt lengths of real calls launch variants no fixed self-check runs.
Each plan and input shapes is therefore verified once, on its first call: `verify_fused_sampling` runs the call
unfused and fused and compares the actions (`FUSED_TOLERANCE`); under "auto" a plan that fails or deviates samples
unfused from then on (a persistent one first falls back to five launches per layer, verified in turn), and a setting
that names its kernels ("triton", "persistent") raises instead.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference.attention import attend
from pi0_torch.inference.graphs import relative_deviation
from pi0_torch.inference.layer_pass import plain_linear, runs_extra_code, runs_its_weights
from pi0_torch.kernels import ops, reference
from pi0_torch.inference.conditioning import NormParams, StepConditioning
from pi0_torch.kernels.reference import rms_norm, rope_cos_sin

if TYPE_CHECKING:
    from pi0_torch.inference.layer_pass import SamplingWeights
    from pi0_torch.inference.layout import StreamPass
    from pi0_torch.inference.plan import SamplingInputs, SamplingPlan
    from pi0_torch.inference.sampling import ActionPass
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

logger = logging.getLogger(__name__)

SELF_CHECK_TOLERANCE = {torch.float32: 1e-4, torch.bfloat16: 3e-2, torch.float16: 1e-2}  # max error / max |reference|
# A plan's fused actions against its unfused ones on the same inputs, max |difference| / max |unfused action|
# (`verify_fused_sampling`). The openpi fixtures' bounds (tests/test_parity.py): float32 1e-4; in bf16 / fp16 both
# paths round, differently (the fused epilogues round less often), and each differs from float32 by 3.8e-3-5.5e-3
# there, so 3e-2 leaves room for full-size models. A wrong kernel is off by the actions' own size.
FUSED_TOLERANCE = {torch.float32: 1e-4, torch.bfloat16: 3e-2, torch.float16: 3e-2}


def kernels_setting_reason(setting: str, name: str, device: torch.device, dtype: torch.dtype,
                           check: Callable[[], str | None], unsupported: str | None = None) -> str | None:
    """Why a model's fused-kernels setting `name` (`setting`: "auto", "torch", or a kernel set asked for by name:
    "triton", sampling's "persistent") does not run them on `device` in `dtype` (None: it does): "torch"; then
    `unsupported` (what the call asks for that they do not do); "auto" off CUDA in bf16 / fp16; then `check()` (the
    model and the kernels), which a setting asked for by name turns into a `ValueError`."""
    if setting == "torch":
        return f"{name} is 'torch'"
    if unsupported is not None:
        return unsupported
    if setting == "auto" and not (device.type == "cuda" and dtype in (torch.bfloat16, torch.float16)):
        return f"the fused kernels run on CUDA in bf16 / fp16 ({name}='triton' to force them)"
    reason = check()
    if reason is not None and setting != "auto":
        raise ValueError(f"{name}={setting!r} cannot run: {reason}")
    return reason


def attention_shape_reason(kv_heads: int, head_dim: int) -> str | None:
    """Why the fused attention cannot run a model's heads (None: it can): it folds the query heads onto one kv head,
    and its head size is a power of two >= 16."""
    if kv_heads != 1:
        return f"the fused attention folds the query heads onto one kv head; this model has {kv_heads}"
    if head_dim < 16 or head_dim & (head_dim - 1):
        return f"the fused kernels need a head size that is a power of two >= 16, not {head_dim}"
    return None


def structural_reason(model: PI0ForActionGeneration) -> str | None:
    """Why the fused step cannot run this model's layers at all (None: it can)."""
    config = model.config
    if (reason := attention_shape_reason(config.num_key_value_heads, config.head_dim)) is not None:
        return reason
    if model.sampling_compiled:
        return "the layers are compiled (compile_sampling)"
    if any(runs_extra_code(layer) or not runs_its_weights(layer.expert) for layer in model.layers):
        return "a layer's projections are not plain weights (LoRA, quantized or hooked layers, autocast)"
    action_linears = (model.action_in_proj, model.action_out_proj) + (
        () if config.pi05 else (model.action_time_mlp_in, model.action_time_mlp_out))
    if not all(plain_linear(linear, bias=True) for linear in action_linears):
        return "an action projection is not a plain linear layer (LoRA, quantized or hooked layers)"
    return None


@functools.lru_cache(maxsize=None)
def fused_kernels_reason(device: torch.device, dtype: torch.dtype, width: int, heads: int, head_dim: int, mlp_width: int,
                         action_dim: int, vision_width: int) -> str | None:
    """Why the fused kernels may not run on `device` in `dtype` (None: they may): triton is unusable there, or one of
    them, run once at these sizes on random inputs, differs from its torch reference by more than
    `SELF_CHECK_TOLERANCE` or fails. Checked once per device, dtype and sizes (which compiles the kernels too); a
    refusal is logged once, and the unfused path runs instead."""
    cases = lambda: _sampling_cases(device, dtype, width, heads, head_dim, mlp_width, action_dim, vision_width)  # noqa: E731
    return kernels_reason(device, dtype, cases, "sampling runs the unfused torch path")


def verify_fused_sampling(model: PI0ForActionGeneration, inputs: SamplingInputs, plan: SamplingPlan,
                          unfused: torch.Tensor | None = None) -> tuple[str | None, torch.Tensor]:
    """Sample `inputs` with `plan`'s fused steps and unfused (unless `unfused` holds those actions already: the
    verification of a refused persistent plan sampled them), eagerly: why the fused sampling is refused for inputs of
    these shapes (None: it may run), and the actions to return (the fused ones where it may, else the unfused).
    Refused where it raises (a kernel variant that does not compile or does not fit the device), where a persistent
    launch abandoned a wait (`kernels.persistent.watchdog`), or where its actions deviate from the unfused ones by
    more than `FUSED_TOLERANCE` (a non-finite action deviates infinitely)."""
    if unfused is None:
        unfused = model.sample_planned(inputs, replace(plan, fused=False, persistent=False))
    try:
        fused = model.sample_planned(inputs, plan)
    except Exception as error:  # (the inputs were checked and the unfused path ran them: what fails is the kernels)
        return f"it failed ({type(error).__name__}: {str(error)[:300]})", unfused
    if plan.persistent and persistent_abandoned(fused.device):
        return PERSISTENT_ABANDONED, unfused
    deviation = relative_deviation(fused, unfused)
    bound = FUSED_TOLERANCE.get(model.dtype, FUSED_TOLERANCE[torch.float32])
    if deviation <= bound:
        return None, fused
    return f"its actions deviate from the unfused path's by {deviation:.3g} of the largest action (bound {bound:g})", unfused


PERSISTENT_ABANDONED = ("its persistent launch abandoned a wait that did not end (a synchronization fault of "
                        "pi0_torch.kernels.persistent on this GPU: please report it); its launches return NaN in this "
                        "process from now on")


def persistent_abandoned(device: torch.device) -> bool:
    """Whether a persistent launch on `device` abandoned a wait (`kernels.persistent.abandoned`; False where none
    ran or none can run). Reads the GPU."""
    if ops.triton_reason(device) is not None:
        return False
    from pi0_torch.kernels import persistent

    return persistent.abandoned(device)


_AVOIDED: set[torch.device] = set()  # devices whose abandoned persistent launch `auto_avoids_persistent` logged


def auto_avoids_persistent(device: torch.device) -> bool:
    """Whether "auto" leaves the persistent launch on `device` from now on: a persistent launch there abandoned a wait
    (`persistent_abandoned`, which reads the GPU once a persistent launch has run there), so every later one returns
    NaN. Logged once per device."""
    if not persistent_abandoned(device):
        return False
    if device not in _AVOIDED:
        _AVOIDED.add(device)
        logger.warning("a persistent launch on %s abandoned a wait that did not end (a synchronization fault of "
                       "pi0_torch.kernels.persistent on this GPU: please report it); sampling_kernels='auto' runs five "
                       "launches per decoder layer there from now on", device)
    return True


def kernels_reason(device: torch.device, dtype: torch.dtype, cases: Callable[[], list[tuple[str, Callable[[], tuple]]]],
                   fallback: str) -> str | None:
    """Why the Triton kernels of `cases()` (name, argument maker) may not run on `device` (None: each equals its torch
    reference on them, within `SELF_CHECK_TOLERANCE`); a refusal on CUDA is logged after `fallback` (what runs
    instead)."""
    reason = ops.triton_reason(device)
    if reason is None:
        try:
            reason = _compare(cases(), device, dtype)
        except Exception as error:  # a triton that cannot compile them, a device they do not fit
            reason = f"the fused kernels failed on {device} ({type(error).__name__}: {str(error)[:300]})"
    if reason is not None and device.type == "cuda":
        logger.warning("%s: %s", fallback, reason)
    return reason


def seeded_random(device: torch.device, dtype: torch.dtype) -> Callable[..., torch.Tensor]:
    """`random(*shape, scale=1.0, dtype=dtype)`: seeded normal values on `device` (the same on every device)."""
    generator = torch.Generator(device="cpu").manual_seed(0)

    def random(*shape: int, scale: float = 1.0, dtype: torch.dtype = dtype) -> torch.Tensor:
        return (torch.randn(*shape, generator=generator) * scale).to(device=device, dtype=dtype)

    return random


def _sampling_cases(device, dtype, width, heads, head_dim, mlp_width, action_dim, vision_width) -> list[tuple[str, Callable[[], tuple]]]:
    random = seeded_random(device, dtype)
    batch, tokens, slots = 2, 5, 24
    x, scale = random(batch * tokens, width), 1 + random(width, scale=0.1)
    cos, sin = rope_cos_sin(torch.arange(tokens, device=device)[None] + torch.tensor([[3], [9]], device=device), head_dim, 10_000.0)
    qkv_weight = random((heads + 2) * head_dim, width, scale=width**-0.5).t()
    gate_up_weight = random(2 * mlp_width, width, scale=width**-0.5).t()
    down_weight = random(width, mlp_width, scale=mlp_width**-0.5).t()
    in_weight = random(width, action_dim, scale=action_dim**-0.5).t()
    x_t = random(batch, tokens, action_dim, dtype=torch.float32)

    def caches() -> tuple[torch.Tensor, torch.Tensor]:
        return random(batch, slots, head_dim), random(batch, slots, head_dim)

    return [  # every variant sampling runs (with and without adaRMS's bias / gate; π0's and π0.5's action tokens)
        ("norm_qkv_rope", lambda: (x, scale, None, qkv_weight, cos, sin, *caches(), 11, 1e-6)),
        ("norm_qkv_rope", lambda: (x, scale, random((heads + 2) * head_dim), qkv_weight, cos, sin, *caches(), 11, 1e-6)),
        ("rope_cache_write", lambda: (random(batch * tokens, (heads + 2) * head_dim), cos, sin, *caches(), 3)),
        ("norm_gate_up_geglu", lambda: (x, scale, None, gate_up_weight, 1e-6)),
        ("norm_gate_up_geglu", lambda: (x, scale, random(2 * mlp_width), gate_up_weight, 1e-6)),
        ("geglu", lambda: (random(batch * tokens, 2 * mlp_width),)),
        ("matmul_residual_", lambda: (x.clone(), random(batch * tokens, mlp_width), down_weight, None)),
        ("matmul_residual_", lambda: (x.clone(), random(batch * tokens, mlp_width), down_weight, random(width))),
        ("range_attention", lambda: (random(batch, tokens, heads, head_dim), *caches(), torch.tensor([2, 7], device=device),
                                     torch.full((tokens,), slots, device=device))),
        # π0's state token: one row per sample (a batch of one is a row count of one, which triton compiles apart), its
        # attention's keys in parts
        ("norm_qkv_rope", lambda: (x[:1], scale, None, qkv_weight, cos[:1, :1], sin[:1, :1], random(1, slots, head_dim),
                                   random(1, slots, head_dim), 11, 1e-6)),
        ("norm_gate_up_geglu", lambda: (x[:1], scale, None, gate_up_weight, 1e-6)),
        ("matmul_residual_", lambda: (x[:1].clone(), random(1, mlp_width), down_weight, None)),
        *(("range_attention", lambda samples=samples: (random(samples, 1, heads, head_dim), random(samples, 900, head_dim),
                                                       random(samples, 900, head_dim), torch.tensor([2, 70], device=device)[:samples],
                                                       torch.tensor([880], device=device)))
          for samples in (1, 2)),
        ("norm_linear_euler_", lambda: (x_t.clone(), x, scale, random(action_dim), random(action_dim, width, scale=width**-0.5).t(),
                                        -0.1, 1e-6)),
        ("embed_actions", lambda: (x_t, in_weight, random(width), None, None)),
        ("embed_actions", lambda: (x_t, in_weight, random(width), random(width, width, scale=width**-0.5).t(), random(width))),
        ("add_layer_norm_", lambda: (random(batch * tokens, vision_width), random(batch * tokens, vision_width),
                                     1 + random(vision_width, scale=0.1), random(vision_width, scale=0.1), 1e-6)),
    ]


def _compare(cases: list[tuple[str, Callable[[], tuple]]], device: torch.device, dtype: torch.dtype) -> str | None:
    """Run each case's op (its Triton kernel, on the arguments' GPU: `ops.call`) and its torch reference on the same
    arguments: why they differ (None: they agree)."""
    for name, make in cases:
        arguments = make()
        theirs = [a.clone() if isinstance(a, torch.Tensor) else a for a in arguments]
        ours = ops.call(getattr(ops, name), *arguments)
        expected = getattr(reference, name)(*theirs)
        compared = [(ours, expected)] if ours is not None else []
        compared += [(a, b) for a, b in zip(arguments, theirs) if isinstance(a, torch.Tensor) and not torch.equal(a.nan_to_num(), b.nan_to_num())]
        for got, want in compared:  # the result and every tensor the op wrote (NaN: cache slots not written yet)
            got, want = got.float(), want.float()
            difference = torch.where(got.isnan() & want.isnan(), 0.0, got - want).nan_to_num(nan=float("inf"))
            error = float(difference.abs().max() / want.nan_to_num().abs().max().clamp(min=1e-12))
            if not error <= SELF_CHECK_TOLERANCE[dtype]:
                return f"the fused kernel {name} differs from its torch reference on {device} in {dtype} (relative error {error:.2e})"
    return None


@dataclass
class FusedSteps:
    """What every fused step of one call shares: the decoder layers' arguments of each step after its action tokens
    (`expert_layers_`'s: the layers' weights, their norms' scales and π0.5's adaRMS biases and gates of the step, the
    caches, the action tokens' RoPE tables `[B, T, H]` and key range; stacked `[L, ...]` for the persistent launch,
    lists of each layer's views for five launches per layer), whether a step's layers run as one persistent launch,
    the action embedding's weights and each step's bias (π0: action_in_proj folded into the action half of
    action_time_mlp_in, the step's time half in the bias), and the final norm's scale and bias of each step
    (`action_out_proj`'s bias, plus π0.5's final adaRMS shift through it).

    π0's state token (`PrefixCache.state`) runs with the first step's action tokens, ahead of them in its slot: it
    sees the prefix and itself, they see it too, and its keys and values stay in the caches for the other steps. So
    the action expert's weights are read once less per chunk than with a pass of its own (as openpi's suffix computes
    it, where every step recomputes it)."""

    model: PI0ForActionGeneration
    persistent: bool
    layer_arguments: list[tuple[Any, ...]]  # per step (π0: the first step's with the state token ahead of its tokens)
    state: torch.Tensor | None  # π0: the state token [B, D1], run by the first step
    in_weight: torch.Tensor  # [A, D1]
    in_biases: torch.Tensor  # [steps or 1, D1]
    mlp_out: tuple[torch.Tensor, torch.Tensor] | None  # π0: action_time_mlp_out's weight [D1, D1] (transposed), bias
    out_weight: torch.Tensor  # [D1, A]
    final_scales: torch.Tensor  # [steps or 1, D1]
    final_biases: torch.Tensor  # [steps or 1, A]

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
        qkv, o, gate_up, down = projection_lists(actions.expert_weights)
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
        return cls(model, persistent, layer_arguments, cache.state, in_weight, in_biases, mlp_out, out_weight,
                   final.scale.view(-1, final.scale.shape[-1]), final_biases)

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
            reference.layer_by_layer_(ops.runner(joint.device), joint, *self.layer_arguments[index])
        if joint is not tokens:  # (a view at batch 1, a copy else)
            tokens = joint.view(batch, -1, width)[:, 1:].reshape(-1, width)
        row = index if self.final_scales.shape[0] > 1 else 0  # (π0.5: a final norm per step)
        ops.call(ops.norm_linear_euler_, x_t, tokens, self.final_scales[row], self.final_biases[row], self.out_weight, dt,
                 self.model.config.rms_norm_eps)


def projection_lists(weights: list[SamplingWeights]) -> tuple[list[torch.Tensor], ...]:
    """Each layer's q/k/v, o, gate/up and down weights (transposed) as four lists, `expert_layers_`'s arguments."""
    return tuple(list(each) for each in zip(*((own.qkv, own.o, own.gate_up, own.down) for own in weights)))


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
