"""The batches of a fine-tuning run: LeRobot dataset samples -> model inputs ([`PI0DataCollator`], dataset cameras
renamed to model cameras by [`default_camera_map`]), and each sample's flow-matching draws ([`flow_draws`]: noise,
time and, for training-time real-time chunking, an inference delay, from a generator keyed by the sample, so that a
run gives the same losses on one process or several and after a resume).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.processing.processing_pi0 import PI0Processor


def default_camera_map(dataset_cameras: Sequence[str], model_cameras: Sequence[str], overrides: Mapping[str, str] | None = None) -> dict[str, str]:
    """dataset camera key -> model camera name. Default: the dataset's cameras in order onto the model's.

    `overrides` maps model camera name -> dataset key (the CLI's `--camera base_0_rgb=observation.images.top`);
    when given it is the whole map. Model cameras left without a dataset camera are fed as absent (mask False).
    """
    if overrides:
        unknown_model = sorted(set(overrides) - set(model_cameras))
        unknown_data = sorted(set(overrides.values()) - set(dataset_cameras))
        if unknown_model or unknown_data:
            raise ValueError(
                f"camera map: model cameras {unknown_model} not in {list(model_cameras)}; dataset cameras "
                f"{unknown_data} not in {list(dataset_cameras)}"
            )
        return {data_key: model_name for model_name, data_key in overrides.items()}
    if len(dataset_cameras) > len(model_cameras):
        raise ValueError(
            f"the dataset has {len(dataset_cameras)} cameras {list(dataset_cameras)} but the model only "
            f"{len(model_cameras)} {list(model_cameras)}; choose them with a camera map (--camera MODEL=DATASET)"
        )
    return dict(zip(dataset_cameras, model_cameras))


@dataclass
class PI0DataCollator:
    """`LeRobotEpisodeDataset` samples -> a batch of `PI0ForActionGeneration.forward` inputs (torch tensors).

    Cameras are renamed with `camera_map` (dataset key -> model camera name; unmapped dataset cameras are dropped).
    The batch also holds `sample_index` (the samples' dataset indices, used by [`PI0Trainer`] for evaluation draws).
    """

    processor: PI0Processor
    camera_map: dict[str, str]

    def __call__(self, samples: Sequence[Mapping[str, Any]]) -> dict[str, torch.Tensor]:
        observations = [
            {
                "images": {self.camera_map[key]: frame for key, frame in sample["images"].items() if key in self.camera_map},
                "prompt": sample["prompt"],
                "state": sample["state"],
                "actions": sample["actions"],
            }
            for sample in samples
        ]
        batch = dict(self.processor(observations, return_tensors="pt"))
        batch["sample_index"] = torch.tensor([int(sample["index"]) for sample in samples], dtype=torch.long)
        return batch


def flow_draws(config: PI0Config, keys: Sequence[Sequence[int]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Flow-matching noise `[B, horizon, action_dim]` and times `[B]` (Beta(a, b) * scale + offset, as the model's own
    sampler), one independent numpy generator per sample seeded with that sample's key (a tuple of ints); with
    `config.rtc_max_delay > 0` (training-time real-time chunking) also an inference delay per sample, uniform in
    `[0, rtc_max_delay]` (long `[B]`; None otherwise), drawn after the noise and time so those stay the same."""
    noise, time, delay = [], [], []
    for key in keys:
        rng = np.random.default_rng([int(k) for k in key])
        noise.append(rng.standard_normal((config.action_horizon, config.action_dim)))
        time.append(rng.beta(config.time_beta_alpha, config.time_beta_beta) * config.time_scale + config.time_offset)
        delay.append(rng.integers(0, config.rtc_max_delay + 1))
    delays = torch.tensor(delay, dtype=torch.long) if config.rtc_max_delay > 0 else None
    return torch.tensor(np.stack(noise), dtype=torch.float32), torch.tensor(time, dtype=torch.float32), delays
