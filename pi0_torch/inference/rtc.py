"""Real-time chunking (RTC): a new action chunk that continues the one the robot is executing.

Timing (control steps): the previous chunk `prev` [H] started at its inference's start; `s` of its actions ran
before this inference started (the execution horizon) and `d` more run while this inference computes (the delay).
Index 0 of the new chunk is the step at which its inference starts, so its first `d` actions are executed from the
previous chunk anyway, and positions `0 .. H-s-1` overlap the rest of it: the target is `Y[i] = prev[s + i]`.

Two ways to make the new chunk agree with `Y` (conventions of `pi0_torch.models.flow_matching`: `x_t = t * noise +
(1 - t) * actions`, Euler from t = 1 to t = 0; the clean chunk predicted at `x_t` is `x0 = x_t - t * v(x_t, t)`):

- *guidance* (inference-time RTC, Black, Galliker, Levine 2025): each Euler step pulls `x0` toward `Y` with a
  vector-Jacobian product through the model, weighted by a soft mask `W` (1 on the delayed steps, decaying over the
  overlap, 0 after it) and by `min(beta, ((1 - t)^2 + t^2) / (t (1 - t)))`;
- *conditioning* (training-time RTC, Black, Ren, Equi, Levine 2025): a model trained with simulated delays takes the
  first `d` actions as given (flow time 0 per token) and only integrates the rest; no guidance cost.

Bounds ([`check_rtc_inputs`]): the previous chunk must lie within `MAX_PREVIOUS_ACTION` of zero in the model's
normalized action space (a chunk a policy returned lies within a few units there: z-scores, or the q01..q99 span
mapped to [-1, 1]; a value of 1e3 is not one, and guidance toward it returned actions of 980 even past the overlap,
toward 1e20 all NaN), and the guidance clip `beta` within `[0, MAX_GUIDANCE]` (inf or 1e30 returned NaN; the paper
uses 5).

```python
>>> import torch
>>> prefix = chunk_prefix(torch.arange(8.0).view(1, 8, 1), inference_delay=2, execution_horizon=3)
>>> prefix.target[0, :, 0].tolist()  # prev[3:], zero past the overlap
[3.0, 4.0, 5.0, 6.0, 7.0, 0.0, 0.0, 0.0]
>>> [round(w, 3) for w in prefix.weights[0].tolist()]  # ones on the delay, exponential decay, zero after
[1.0, 1.0, 0.488, 0.189, 0.041, 0.0, 0.0, 0.0]
>>> prefix.committed[0].tolist()
[True, True, False, False, False, False, False, False]

```
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from pi0_torch.utils.validation import check_float

SCHEDULES = ("exp", "linear", "ones", "hard")
METHODS = ("guidance", "conditioning")
DEFAULT_MAX_GUIDANCE = 5.0  # the paper's beta
MAX_GUIDANCE = 100.0  # 20 times the paper's beta; 1e3 still behaved, 1e30 gave NaN
MAX_PREVIOUS_ACTION = 100.0  # |previous action| in the model's normalized space (see the module docstring)


@dataclass
class ChunkPrefix:
    """What the previous chunk asks of the new one, per sample (all `[B, H, ...]`, index 0 = this inference's start)."""

    target: torch.Tensor  # [B, H, A] float32: prev[s + i] on the overlap, 0 after it
    weights: torch.Tensor  # [B, H] float32 soft mask W
    committed: torch.Tensor  # [B, H] bool: i < d, the steps executed while this chunk is computed


def check_rtc_inputs(name: str, previous_actions: Any, max_guidance: Any) -> None:
    """Refuse (`ValueError` naming the argument) a previous chunk (model space, finite) beyond
    `MAX_PREVIOUS_ACTION` or a guidance clip outside `[0, MAX_GUIDANCE]`: inputs that drive the guided flow to huge
    or NaN actions."""
    check_float("rtc_max_guidance", max_guidance, minimum=0.0, maximum=MAX_GUIDANCE)
    values = torch.as_tensor(previous_actions)
    largest = float(values.abs().max()) if values.numel() else 0.0
    if largest > MAX_PREVIOUS_ACTION:
        where = tuple(int(i) for i in (values.abs() == values.abs().max()).nonzero()[0])
        raise ValueError(f"{name}: values up to {largest:.3g} (at index {where}) in the model's normalized action "
                         f"space; a chunk this policy returned lies within ±{MAX_PREVIOUS_ACTION:g} (wrong units, "
                         "another robot's chunk, or a corrupted message?)")


def per_sample_steps(value: int | torch.Tensor, batch: int, name: str, device: torch.device) -> torch.Tensor:
    """An int or an integer tensor `[B]` as a long tensor `[B]`."""
    if isinstance(value, bool) or not isinstance(value, (int, torch.Tensor)):
        raise ValueError(f"{name} must be an int or an integer tensor [B={batch}], got {type(value).__name__}")
    tensor = torch.as_tensor(value, device=device)
    if tensor.is_floating_point() or tensor.dtype == torch.bool or tensor.dim() > 1 or tensor.numel() not in (1, batch):
        raise ValueError(f"{name} must be an int or an integer tensor [B={batch}], got {tuple(tensor.shape)} {tensor.dtype}")
    return tensor.long().reshape(-1).expand(batch)


def prefix_weights(inference_delay: torch.Tensor, overlap: torch.Tensor, horizon: int, schedule: str = "exp") -> torch.Tensor:
    """The soft mask `W` `[B, H]` for per-sample delays `d` and overlaps `H - s` (both `[B]`).

    `exp`: 1 for i < d; for d <= i < H - s, `c * (exp(c) - 1) / (e - 1)` with `c = (H - s - i) / (H - s - d + 1)`;
    0 after. `linear`: `c` itself. `ones`: 1 on the whole overlap. `hard`: 1 for i < d only.
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"rtc_schedule must be one of {SCHEDULES}, got {schedule!r}")
    i = torch.arange(horizon, device=inference_delay.device)[None, :].float()  # [1, H]
    d, end = inference_delay[:, None].float(), overlap[:, None].float()  # [B, 1]
    c = ((end - i) / (end - d + 1)).clamp(0.0, 1.0)
    decay = {"exp": c * torch.expm1(c) / (math.e - 1), "linear": c, "ones": torch.ones_like(c), "hard": torch.zeros_like(c)}[schedule]
    return torch.where(i < d, 1.0, torch.where(i < end, decay, 0.0))


def chunk_prefix(
    previous_actions: torch.Tensor,
    inference_delay: int | torch.Tensor,
    execution_horizon: int | torch.Tensor,
    schedule: str = "exp",
) -> ChunkPrefix:
    """Target, soft mask and committed steps for a new chunk from the previous one.

    Args:
        previous_actions: float `[B, H, A]` the previous chunk as generated (model space; index 0 = the step its
            inference started).
        inference_delay: `d`, control steps this inference takes (int or long `[B]`), `0 <= d <= H - s`.
        execution_horizon: `s`, actions of the previous chunk executed before this inference started (int or long
            `[B]`), `0 <= s < H`.
        schedule: the soft mask's decay over the overlap (see [`prefix_weights`]).
    """
    batch, horizon = previous_actions.shape[:2]
    device = previous_actions.device
    delay = per_sample_steps(inference_delay, batch, "inference_delay", device)
    executed = per_sample_steps(execution_horizon, batch, "execution_horizon", device)
    if bool(((executed < 0) | (executed >= horizon)).any()):
        raise ValueError(f"execution_horizon must lie in [0, {horizon - 1}] (the chunk has {horizon} steps), got {executed.tolist()}")
    if bool(((delay < 0) | (delay > horizon - executed)).any()):
        raise ValueError(
            f"inference_delay must lie in [0, H - execution_horizon] (the steps left of the previous chunk), got "
            f"delay {delay.tolist()} with execution_horizon {executed.tolist()} and H = {horizon}"
        )
    steps = torch.arange(horizon, device=device)[None, :]  # [1, H]
    source = (steps + executed[:, None]).clamp(max=horizon - 1)  # [B, H]: prev index of each new step
    overlap = horizon - executed
    target = previous_actions.float().gather(1, source[..., None].expand(-1, -1, previous_actions.shape[-1]))
    target = torch.where((steps < overlap[:, None])[..., None], target, 0.0)
    return ChunkPrefix(target, prefix_weights(delay, overlap, horizon, schedule), steps < delay[:, None])


def guidance_weight(time: float, max_guidance: float) -> float:
    """`min(beta, ((1 - t)^2 + t^2) / (t (1 - t)))`: the paper's `(1 - tau) / (tau r^2)` with `tau = 1 - t`; beta at
    t = 1 (and t = 0), where the expression is infinite."""
    if time <= 0.0 or time >= 1.0:
        return max_guidance
    return min(max_guidance, ((1 - time) ** 2 + time**2) / (time * (1 - time)))
