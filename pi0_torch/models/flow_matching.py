"""Flow matching pieces shared by training and sampling (t = 1 is noise, t = 0 is data)."""

from __future__ import annotations

import math

import torch

from pi0_torch.inference.conditioning import euler_times  # noqa: F401 (the sampler's; re-exported: older import path)


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
