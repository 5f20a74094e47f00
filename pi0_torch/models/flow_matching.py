"""Flow matching pieces shared by training and sampling (t = 1 is noise, t = 0 is data)."""

from __future__ import annotations

import math

import numpy as np
import torch

from pi0_torch.models.configuration_pi0 import MAX_INFERENCE_STEPS
from pi0_torch.utils.validation import check_int


def sincos_time_embedding(time: torch.Tensor, dim: int, min_period: float, max_period: float) -> torch.Tensor:
    """openpi's sine/cosine embedding of the flow time, float32.

    Args:
        time: `[B]` flow times.
        dim: embedding width (even); the first half holds the sines, the second half the cosines.

    Returns:
        float32 `[B, dim]`.
    """
    fraction = torch.linspace(0.0, 1.0, dim // 2, dtype=torch.float32, device=time.device)
    period = min_period * (max_period / min_period) ** fraction
    angular_frequency = 1.0 / period * (2 * math.pi)  # same operation order as openpi
    angles = time.float()[:, None] * angular_frequency[None, :]
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def sample_flow_time(
    batch_size: int, alpha: float, beta: float, scale: float, offset: float, device: torch.device | str
) -> torch.Tensor:
    """Training flow times `Beta(alpha, beta) * scale + offset`, float32 `[B]` (openpi: Beta(1.5, 1) * 0.999 + 0.001)."""
    distribution = torch.distributions.Beta(
        torch.tensor(alpha, dtype=torch.float32, device=device), torch.tensor(beta, dtype=torch.float32, device=device)
    )
    return distribution.sample((batch_size,)) * scale + offset


def interpolate(actions: torch.Tensor, noise: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The noisy actions `x_t = t * noise + (1 - t) * actions` and the target velocity `u = noise - actions`."""
    t = time[:, None, None]
    return t * noise + (1 - t) * actions, noise - actions


def euler_times(num_steps: int) -> list[float]:
    """Flow times visited by openpi's Euler sampler: from t = 1 with dt = -1/num_steps while t >= -dt/2.

    The arithmetic is float32, exactly as openpi's loop, so the times match its trajectory bit for bit.
    `num_steps` is an integer in `[1, MAX_INFERENCE_STEPS]` (2.5 or True are refused, naming it).
    """
    check_int("num_steps", num_steps, minimum=1, maximum=MAX_INFERENCE_STEPS)
    dt = np.float32(-1.0 / num_steps)
    t = np.float32(1.0)
    times = []
    while t >= -dt / np.float32(2):
        times.append(float(t))
        t = np.float32(t + dt)
    return times
