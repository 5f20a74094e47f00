"""Where the engine decides what may run fast, in one place: every gate, every tolerance a fast path is verified
against, and the self-checks of the fused ops.

One convention for every gate: `<what>_reason(...)` returns None where `<what>` may run, else one sentence saying why
not; that sentence is what a refusal logs and what `SamplingRoute` reports. A setting that asks for a fast path by
name ("triton", "persistent") turns a reason into a `ValueError` (`setting_reason`); "auto" runs the next path.

Triton compiles a kernel anew for each class of its arguments (block sizes chosen by row count, an integer equal to 1
or divisible by 16), so the batch sizes and prompt lengths of real calls launch variants no fixed self-check runs. So
each fused sampling plan and input shapes is verified once more, on its first call (`verify_fused_sampling`: the call
unfused and fused, the actions compared).

Tolerances are relative: max |difference| / max |reference|. Each fused op's self-check case is paired with the op
object itself (`sampling_cases`, `decoding_cases`); `tests/test_kernels.py` checks that every op the fused paths
launch has one.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.kernels import ops, reference
from pi0_torch.kernels.ops import op_name
from pi0_torch.kernels.reference import rope_cos_sin

if TYPE_CHECKING:
    from pi0_torch.inference.layer_pass import ModelSamplingWeights, SamplingWeights
    from pi0_torch.inference.plan import SamplingInputs, SamplingPlan

logger = logging.getLogger(__name__)

Case = tuple[Any, Callable[[], tuple]]  # (a custom op of `pi0_torch.kernels.ops`, a maker of its arguments)

# -- tolerances ------------------------------------------------------------------------------------------------------

# A fused op against its torch reference on random inputs (`ops_reason`)
SELF_CHECK_TOLERANCE = {torch.float32: 1e-4, torch.bfloat16: 3e-2, torch.float16: 1e-2}
# A plan's fused actions against its unfused ones on the same inputs (`verify_fused_sampling`). The openpi fixtures'
# bounds (tests/test_parity.py): float32 1e-4; in bf16 / fp16 both paths round, differently (the fused epilogues round
# less often), and each differs from float32 by 3.8e-3-5.5e-3 there, so 3e-2 leaves room for full-size models. A wrong
# kernel is off by the actions' own size.
FUSED_TOLERANCE = {torch.float32: 1e-4, torch.bfloat16: 3e-2, torch.float16: 3e-2}
# A CUDA graph's first replay (and compiled decoding's first calls) against eager runs of the same inputs. Both run the
# same kernels, so they agree to rounding; a wrong graph is off by the actions' own size (guidance: 1.1-1.2). float32
# agrees with openpi to 1e-4; bf16 sampling differs from float32 by 3.8e-3-5.5e-3 there, and 1e-2 is twice that (fp16
# likewise).
VERIFY_TOLERANCE = {torch.float32: 1e-4, torch.bfloat16: 1e-2, torch.float16: 1e-2}


def bound(tolerance: dict[torch.dtype, float], dtype: torch.dtype) -> float:
    """A tolerance table's bound for `dtype` (float32's for any other dtype)."""
    return tolerance.get(dtype, tolerance[torch.float32])


def relative_deviation(got: torch.Tensor, want: torch.Tensor) -> float:
    """max |got - want| / max |want| (inf where `got` is not finite)."""
    got, want = got.float(), want.float()
    if not bool(torch.isfinite(got).all()):
        return float("inf")
    return float((got - want).abs().max() / want.abs().max().clamp(min=1e-12))


# -- gates -----------------------------------------------------------------------------------------------------------


def setting_reason(setting: str, name: str, device: torch.device, dtype: torch.dtype, check: Callable[[], str | None],
                   unsupported: str | None = None) -> str | None:
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


def layers_reason(kv_heads: int, head_dim: int, weights: Sequence[SamplingWeights], compiled: bool = False,
                  plain_action_linears: bool = True) -> str | None:
    """Why the fused kernels cannot run a model's layers at all (None: they can): the fused attention folds the query
    heads onto one kv head, and its head size is a power of two >= 16; then (π0's steps) compiled layers; then each
    layer's `SamplingWeights` (the call's plain-weights check, `layer_pass`: the action expert's or the decoder's); then
    (π0's steps) the action projections, as `ModelSamplingWeights.plain_action_linears` says."""
    if kv_heads != 1:
        return f"the fused attention folds the query heads onto one kv head; this model has {kv_heads}"
    if head_dim < 16 or head_dim & (head_dim - 1):
        return f"the fused kernels need a head size that is a power of two >= 16, not {head_dim}"
    if compiled:
        return "the layers are compiled (compile_sampling)"
    if not all(each.usable for each in weights):
        return "a layer's projections are not plain weights (LoRA, quantized or hooked layers, autocast)"
    if not plain_action_linears:
        return "an action projection is not a plain linear layer (LoRA, quantized or hooked layers)"
    return None


@functools.lru_cache(maxsize=None)
def sampling_ops_reason(device: torch.device, dtype: torch.dtype, width: int, heads: int, head_dim: int, mlp_width: int,
                        action_dim: int, vision_width: int) -> str | None:
    """Why the fused ops of sampling may not run on `device` in `dtype` (None: they may): triton is unusable there, or
    one of them, run once at these sizes on random inputs (`sampling_cases`), differs from its torch reference by more
    than `SELF_CHECK_TOLERANCE` or fails. Checked once per device, dtype and sizes (which compiles the kernels too); a
    refusal is logged once, and the unfused path runs instead."""
    cases = lambda: sampling_cases(device, dtype, width, heads, head_dim, mlp_width, action_dim, vision_width)  # noqa: E731
    return ops_reason(device, dtype, cases, "sampling runs the unfused torch path")


@functools.lru_cache(maxsize=None)
def decoding_ops_reason(device: torch.device, dtype: torch.dtype, heads: int, head_dim: int, mlp_width: int,
                        batch: int, slots: int) -> str | None:
    """Why the fused ops of a decoded token may not run on `device` in `dtype` for `batch` rows over caches of `slots`
    (None: they may): triton is unusable there, or one of them, run once on random inputs shaped exactly as
    decoding's (one row per sample, the slot a device value, a key range that ends before the cache does), differs
    from its torch reference or fails. Checked once per batch size and cache length (triton's classes of arguments:
    the module docstring; the number of key parts); a refusal is logged once."""
    cases = lambda: decoding_cases(device, dtype, heads, head_dim, mlp_width, batch, slots)  # noqa: E731
    return ops_reason(device, dtype, cases, "π0-FAST decodes through the modules")


def verify_fused_sampling(model: Any, inputs: SamplingInputs, plan: SamplingPlan, weights: ModelSamplingWeights,
                          unfused: torch.Tensor | None = None) -> tuple[str | None, torch.Tensor]:
    """Sample `inputs` with `plan`'s fused steps and unfused (unless `unfused` holds those actions already: the
    verification of a refused persistent plan sampled them), eagerly: why the fused sampling is refused for inputs of
    these shapes (None: it may run), and the actions to return (the fused ones where it may, else the unfused).
    Refused where it raises (a kernel variant that does not compile or does not fit the device), where a persistent
    launch abandoned a wait (`kernels.persistent.watchdog`), or where its actions deviate from the unfused ones by
    more than `FUSED_TOLERANCE` (a non-finite action deviates infinitely)."""
    if unfused is None:
        unfused = model.sample_planned(inputs, replace(plan, steps="torch"), weights)
    try:
        fused = model.sample_planned(inputs, plan, weights)
    except Exception as error:  # (the inputs were checked and the unfused path ran them: what fails is the kernels)
        return f"it failed ({type(error).__name__}: {str(error)[:300]})", unfused
    if plan.persistent and persistent_abandoned(fused.device):
        return PERSISTENT_ABANDONED, unfused
    deviation = relative_deviation(fused, unfused)
    limit = bound(FUSED_TOLERANCE, model.dtype)
    if deviation <= limit:
        return None, fused
    return f"its actions deviate from the unfused path's by {deviation:.3g} of the largest action (bound {limit:g})", unfused


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


# -- the fused ops' self-checks --------------------------------------------------------------------------------------


def ops_reason(device: torch.device, dtype: torch.dtype, cases: Callable[[], list[Case]], fallback: str) -> str | None:
    """Why the Triton kernels of `cases()` may not run on `device` (None: each equals its torch reference on them,
    within `SELF_CHECK_TOLERANCE`); a refusal on CUDA is logged after `fallback` (what runs instead)."""
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


def sampling_cases(device: torch.device, dtype: torch.dtype, width: int, heads: int, head_dim: int, mlp_width: int,
                   action_dim: int, vision_width: int) -> list[Case]:
    """The self-check of every fused op variant plain sampling runs, at the model's sizes (`sampling_ops_reason`)."""
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
        (ops.norm_qkv_rope, lambda: (x, scale, None, qkv_weight, cos, sin, *caches(), 11, 1e-6)),
        (ops.norm_qkv_rope, lambda: (x, scale, random((heads + 2) * head_dim), qkv_weight, cos, sin, *caches(), 11, 1e-6)),
        (ops.rope_cache_write, lambda: (random(batch * tokens, (heads + 2) * head_dim), cos, sin, *caches(), 3)),
        (ops.norm_gate_up_geglu, lambda: (x, scale, None, gate_up_weight, 1e-6)),
        (ops.norm_gate_up_geglu, lambda: (x, scale, random(2 * mlp_width), gate_up_weight, 1e-6)),
        (ops.geglu, lambda: (random(batch * tokens, 2 * mlp_width),)),
        (ops.matmul_residual_, lambda: (x.clone(), random(batch * tokens, mlp_width), down_weight, None)),
        (ops.matmul_residual_, lambda: (x.clone(), random(batch * tokens, mlp_width), down_weight, random(width))),
        (ops.range_attention, lambda: (random(batch, tokens, heads, head_dim), *caches(), torch.tensor([2, 7], device=device),
                                     torch.full((tokens,), slots, device=device))),
        # π0's state token: one row per sample (a batch of one is a row count of one, which triton compiles apart), its
        # attention's keys in parts
        (ops.norm_qkv_rope, lambda: (x[:1], scale, None, qkv_weight, cos[:1, :1], sin[:1, :1], random(1, slots, head_dim),
                                   random(1, slots, head_dim), 11, 1e-6)),
        (ops.norm_gate_up_geglu, lambda: (x[:1], scale, None, gate_up_weight, 1e-6)),
        (ops.matmul_residual_, lambda: (x[:1].clone(), random(1, mlp_width), down_weight, None)),
        *((ops.range_attention, lambda samples=samples: (random(samples, 1, heads, head_dim), random(samples, 900, head_dim),
                                                       random(samples, 900, head_dim), torch.tensor([2, 70], device=device)[:samples],
                                                       torch.tensor([880], device=device)))
          for samples in (1, 2)),
        (ops.norm_linear_euler_, lambda: (x_t.clone(), x, scale, random(action_dim), random(action_dim, width, scale=width**-0.5).t(),
                                        -0.1, 1e-6)),
        (ops.embed_actions, lambda: (x_t, in_weight, random(width), None, None)),
        (ops.embed_actions, lambda: (x_t, in_weight, random(width), random(width, width, scale=width**-0.5).t(), random(width))),
        (ops.add_layer_norm_, lambda: (random(batch * tokens, vision_width), random(batch * tokens, vision_width),
                                     1 + random(vision_width, scale=0.1), random(vision_width, scale=0.1), 1e-6)),
    ]


def decoding_cases(device: torch.device, dtype: torch.dtype, heads: int, head_dim: int, mlp_width: int, batch: int,
                   slots: int) -> list[Case]:
    """The self-check of every fused op a decoded token runs, shaped as decoding's (`decoding_ops_reason`)."""
    random = seeded_random(device, dtype)
    end = slots - 1 - slots // 32  # the token decoded into slot end - 1; the slots after it not written yet
    positions = torch.arange(batch, device=device)[:, None] * 7 + end // 2  # [B, 1]
    cos, sin = rope_cos_sin(positions, head_dim, 10_000.0)  # [B, 1, H]
    first = torch.arange(batch, device=device) * 13 % max(1, end // 2)  # [B]

    def cache() -> torch.Tensor:  # [B, S, H]: NaN after the token's slot (never read)
        nan = torch.full((batch, slots - end, head_dim), float("nan"), device=device, dtype=dtype)
        return torch.cat([random(batch, end, head_dim), nan], dim=1)

    return [
        (ops.rope_cache_write, lambda: (random(batch, (heads + 2) * head_dim), cos, sin, cache(), cache(), 0,
                                      torch.tensor([end - 1], device=device))),
        (ops.range_attention, lambda: (random(batch, 1, heads, head_dim), cache(), cache(), first,
                                     torch.tensor([end], device=device))),
        (ops.geglu, lambda: (random(batch, 2 * mlp_width),)),
    ]


def _compare(cases: list[Case], device: torch.device, dtype: torch.dtype) -> str | None:
    """Run each case's op (its Triton kernel, on the arguments' GPU: `ops.call`) and its torch reference on the same
    arguments: why they differ (None: they agree)."""
    for op, make in cases:
        name = op_name(op)
        arguments = make()
        theirs = [a.clone() if isinstance(a, torch.Tensor) else a for a in arguments]
        ours = ops.call(op, *arguments)
        expected = getattr(reference, name)(*theirs)
        compared = [(ours, expected)] if ours is not None else []
        compared += [(a, b) for a, b in zip(arguments, theirs) if isinstance(a, torch.Tensor) and not torch.equal(a.nan_to_num(), b.nan_to_num())]
        for got, want in compared:  # the result and every tensor the op wrote (NaN: cache slots not written yet)
            got, want = got.float(), want.float()
            difference = torch.where(got.isnan() & want.isnan(), 0.0, got - want).nan_to_num(nan=float("inf"))
            error = float(difference.abs().max() / want.nan_to_num().abs().max().clamp(min=1e-12))
            if not error <= bound(SELF_CHECK_TOLERANCE, dtype):
                return f"the fused kernel {name} differs from its torch reference on {device} in {dtype} (relative error {error:.2e})"
    return None
