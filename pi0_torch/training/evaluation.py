"""A trained policy against the ground truth of a dataset: [`evaluate_policy`] predicts the action chunk of every frame
and compares it with the recorded one and with the mean-action baseline ([`PolicyEvaluation`]).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.robot_spaces import get_conversion
from pi0_torch.training.batches import PI0DataCollator, default_camera_map


@dataclass
class PolicyEvaluation:
    """Predicted vs true action chunks of every frame of a dataset, in robot units, and the mean-action baseline."""

    predictions: np.ndarray  # [N, horizon, A]
    targets: np.ndarray  # [N, horizon, A]
    baseline: np.ndarray  # [N, horizon, A]: the training data's mean action at every step
    prompts: list[str]
    episode_index: np.ndarray  # [N]

    @property
    def mse(self) -> float:
        return float(np.mean((self.predictions - self.targets) ** 2))

    @property
    def baseline_mse(self) -> float:
        return float(np.mean((self.baseline - self.targets) ** 2))

    @property
    def error_ratio(self) -> float:
        """Policy MSE / baseline MSE (0 = perfect, 1 = no better than always predicting the mean action)."""
        return self.mse / self.baseline_mse

    def summary(self) -> str:
        return (
            f"{len(self.targets)} frames: policy MSE {self.mse:.3g}, mean-action baseline MSE {self.baseline_mse:.3g}, "
            f"ratio {self.error_ratio:.3f}"
        )


@torch.no_grad()
def evaluate_policy(
    model: PI0ForActionGeneration,
    processor: PI0Processor,
    dataset: LeRobotEpisodeDataset,
    camera_map: Mapping[str, str] | None = None,
    *,
    batch_size: int = 64,
    seed: int = 0,
    num_steps: int | None = None,
    progress: bool = False,
) -> PolicyEvaluation:
    """Run `generate_actions` through the processor on every frame of `dataset` and compare with its action chunks.

    The noise of batch k comes from `torch.Generator().manual_seed(seed + k)`, so the result is reproducible. The
    baseline predicts the mean action of the processor's statistics (the training data) at every step.
    """
    from pi0_torch.utils.progress import tqdm

    model.eval()
    camera_map = dict(camera_map) if camera_map is not None else default_camera_map(dataset.camera_keys, model.config.camera_names)
    collator = PI0DataCollator(processor, camera_map)
    action_stats = processor.norm_stats["actions"] if processor.norm_stats else None
    mean = np.zeros(processor.action_dim_robot) if action_stats is None else action_stats.mean[: processor.action_dim_robot]
    if processor.value_conversion is not None:  # the statistics describe converted actions
        mean = get_conversion(processor.value_conversion).actions_to_robot(mean)
    predictions, targets, baselines, prompts, episodes = [], [], [], [], []
    starts = range(0, len(dataset), batch_size)
    for number, start in enumerate(tqdm(starts, desc="evaluating", disable=not progress)):
        samples = [dataset[i] for i in range(start, min(start + batch_size, len(dataset)))]
        batch = collator(samples)
        generator = torch.Generator().manual_seed(seed + number)
        inputs = {k: batch[k].to(model.device) for k in ("pixel_values", "image_masks", "input_ids", "attention_mask", "state")}
        actions = model.generate_actions(**inputs, num_steps=num_steps, generator=generator).cpu()
        raw_state = np.stack([s["state"] for s in samples])
        predictions.append(processor.postprocess_actions(actions.numpy(), state=raw_state if processor.delta_action_mask else None))
        targets.append(np.stack([s["actions"] for s in samples]))
        baselines.append(np.broadcast_to(mean, targets[-1].shape).astype(np.float32))
        prompts += [s["prompt"] for s in samples]
        episodes += [s["episode_index"] for s in samples]
    return PolicyEvaluation(
        np.concatenate(predictions), np.concatenate(targets), np.concatenate(baselines), prompts, np.asarray(episodes)
    )
