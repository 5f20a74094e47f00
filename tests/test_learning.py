"""End to end: a tiny π0 trained from scratch with the real pipeline learns the synthetic reaching task.

The task (`pi0_torch.data.synthetic_data`): up to three colored discs, the instruction names one, the action chunk moves
the effector toward it. The held-out episodes have new layouts and always three discs, so neither the image alone
nor the instruction alone gives the action: a policy that ignored the instruction would pick a wrong disc most of
the time, and with flow sampling score worse than the mean-action baseline.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pi0_torch import PI0ForActionGeneration
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset, split_episodes
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.data.synthetic_data import DEMO_DATASET, demo_train_settings, write_synthetic_dataset
from pi0_torch.training.evaluation import evaluate_policy
from pi0_torch.training.trainer import train_policy

STEPS = 2500  # the first 2,500 of the demo policy's 6,000 steps (same data, seed and learning-rate schedule)


@pytest.mark.slow  # ~3 minutes; make test covers the trained demo policy acting in closed loop (test_examples.py)
def test_tiny_policy_learns_to_reach_the_named_object(tmp_path: Path) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the model is tiny; a DataLoader worker prepares batches on the other core
    try:
        root = write_synthetic_dataset(tmp_path / "reach", **DEMO_DATASET)
        result = train_policy(
            demo_train_settings(root, tmp_path / "run", max_steps=STEPS, num_workers=1, logging_steps=250, progress=False)
        )
        model = PI0ForActionGeneration.from_pretrained(tmp_path / "run")
        processor = PI0Processor.from_pretrained(tmp_path / "run")
        heldout = LeRobotEpisodeDataset(root, model.config.action_horizon, episodes=split_episodes(root, "heldout"), progress=False)
        evaluation = evaluate_policy(model, processor, heldout, seed=0, progress=False)
    finally:
        torch.set_num_threads(threads)
    curve = [(e["step"], round(e["loss"], 3)) for e in result["log_history"] if "loss" in e]
    print(f"\ntraining loss: {curve}\nheld-out: {evaluation.summary()}")
    # the flow-matching loss fell by an order of magnitude ...
    assert curve[-1][1] < 0.2 * curve[0][1]
    # ... and on held-out layouts the policy's error is a small fraction of the mean-action baseline's
    assert evaluation.error_ratio < 0.25, evaluation.summary()
