"""Shared test helpers: the openpi reference fixtures (see tests/fixtures/openpi/README.md) and a tiny π0 policy."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

if TYPE_CHECKING:
    from pi0_torch.runtime.policy import PI0Policy

# Keep the suite predictable on small CI machines.
torch.set_num_threads(min(2, os.cpu_count() or 1))
# (Without a GPU the fused Triton kernels run in triton's interpreter: the conftest.py of the repository sets it.)

FIXTURES = Path(__file__).parent / "fixtures" / "openpi"
# the scripts that made the fixtures run in openpi's JAX environment, not here: not collected (`--doctest-modules`)
collect_ignore_glob = ["fixtures/*.py"]
# Seconds a test waits for a subprocess, a socket or a kernel before calling it a hang. Generous on purpose: a loaded
# machine only makes things slower, never wrong (make test's --timeout bounds each whole test at 1800 s).
HANG_S = 900
VARIANTS = ("pi0_small", "pi05_small")
HORIZON = 8  # of `tiny_policy`'s chunks


class OpenpiReference:
    """A fixture variant: its openpi weights, inputs in our layout, and openpi's outputs."""

    def __init__(self, variant: str) -> None:
        from pi0_torch.conversion.openpi_weights import config_from_openpi_shapes

        self.variant = variant
        self.dir = FIXTURES / variant
        self.params = dict(np.load(self.dir / "params_flat.npz"))
        self.arrays = dict(np.load(self.dir / "reference.npz"))
        self.config = config_from_openpi_shapes({k: v.shape for k, v in self.params.items()})

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def tensor(self, key: str) -> torch.Tensor:
        return torch.from_numpy(np.asarray(self.arrays[key]))

    def model(self, dtype: torch.dtype = torch.float32):
        from pi0_torch import PI0ForActionGeneration
        from pi0_torch.conversion.openpi_weights import load_openpi_params

        model = PI0ForActionGeneration(self.config).eval()
        load_openpi_params(model, self.params)
        return model.to(dtype)

    def model_inputs(self) -> dict[str, torch.Tensor]:
        """`inputs/*` in the model's layout (images channels-first, cameras stacked in config order)."""
        cameras = self.config.camera_names
        images = np.stack([self.arrays[f"inputs/images/{c}"] for c in cameras], axis=1)  # [B, C, H, W, 3]
        masks = np.stack([self.arrays[f"inputs/image_masks/{c}"] for c in cameras], axis=1)
        return dict(
            pixel_values=torch.from_numpy(images).permute(0, 1, 4, 2, 3).contiguous(),
            image_masks=torch.from_numpy(masks),
            input_ids=self.tensor("inputs/tokenized_prompt").long(),
            attention_mask=self.tensor("inputs/tokenized_prompt_mask"),
            state=self.tensor("inputs/state"),
        )


def enable_checkpointing(model: torch.nn.Module) -> None:
    """Activation checkpointing on: transformers >= 5.23 names it `activation_checkpointing_enable` (the old
    `gradient_checkpointing_enable` warns there)."""
    enable = getattr(model, "activation_checkpointing_enable", None) or model.gradient_checkpointing_enable
    enable()


def relative_error(ours: torch.Tensor | np.ndarray, reference: np.ndarray) -> float:
    """max|ours - ref| / max|ref|."""
    ours_np = ours.detach().float().cpu().numpy() if isinstance(ours, torch.Tensor) else np.asarray(ours)
    reference = np.asarray(reference, dtype=np.float64)
    return float(np.abs(ours_np - reference).max() / np.abs(reference).max())


@pytest.fixture(scope="session", params=VARIANTS)
def reference(request: pytest.FixtureRequest) -> OpenpiReference:
    return OpenpiReference(request.param)


@pytest.fixture(scope="session")
def references() -> dict[str, OpenpiReference]:
    return {variant: OpenpiReference(variant) for variant in VARIANTS}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked `gpu` need CUDA: skipped (with the reason) where there is none."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


def tiny_policy(action_dim: int = 3, rtc_max_delay: int = 3, low: float = -1.0, high: float = 1.0,
                cameras: tuple[str, ...] = ("base_0_rgb", "left_wrist_0_rgb")) -> PI0Policy:
    """A seeded π0 policy small enough for any test (chunks of `HORIZON` actions, 2 steps), with a test tokenizer and
    norm stats that map [low, high] to about [-2, 2]; it needs the core install only."""
    from pi0_torch import PI0Config, PI0ForActionGeneration, PI0Processor
    from pi0_torch.processing.normalization import NormStats
    from pi0_torch.processing.tokenization import build_test_tokenizer
    from pi0_torch.runtime.policy import PI0Policy

    torch.manual_seed(0)
    config = PI0Config.from_preset(
        "pi0_small", image_size=28, max_token_len=16, action_horizon=HORIZON, action_dim=4, camera_names=list(cameras),
        vision_num_layers=1, num_hidden_layers=2, rtc_max_delay=rtc_max_delay, vocab_size=512,
    )
    centre, spread = np.full(action_dim, (low + high) / 2), np.full(action_dim, (high - low) / 4)
    stats = {key: NormStats(mean=centre, std=spread) for key in ("state", "actions")}
    processor = PI0Processor.from_config(config, tokenizer=build_test_tokenizer(), norm_stats=stats)
    return PI0Policy(PI0ForActionGeneration(config), processor, num_steps=2, seed=0)
