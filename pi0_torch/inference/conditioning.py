"""What the flow time contributes to a sampling step, as the engine passes it around: the Euler times, each norm's
parameters (`NormParams`) and a step's whole conditioning (`StepConditioning`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from pi0_torch.utils.limits import SIZE_LIMITS
from pi0_torch.utils.validation import check_int


def euler_times(num_steps: int) -> list[float]:
    """Flow times visited by openpi's Euler sampler: from t = 1 with dt = -1/num_steps while t >= -dt/2.

    The arithmetic is float32, exactly as openpi's loop, so the times match its trajectory bit for bit.
    `num_steps` is an integer in `[1, SIZE_LIMITS["num_inference_steps"]]` (2.5 or True are refused, naming it).
    """
    check_int("num_steps", num_steps, minimum=1, maximum=SIZE_LIMITS["num_inference_steps"])
    dt = np.float32(-1.0 / num_steps)
    t = np.float32(1.0)
    times = []
    while t >= -dt / np.float32(2):
        times.append(float(t))
        t = np.float32(t + dt)
    return times


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
