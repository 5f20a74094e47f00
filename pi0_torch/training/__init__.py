"""Fine-tuning with the Hugging Face `Trainer` (one process or many through `accelerate`).

`python -m pi0_torch.training ...` is `pi0-torch train ...` (handy after `accelerate launch -m`).
"""

from pi0_torch.training.trainer import (
    EMACallback,
    PI0DataCollator,
    PI0Trainer,
    TrainSettings,
    apply_lora,
    freeze,
    merge_lora,
    train_policy,
)

__all__ = ["EMACallback", "PI0DataCollator", "PI0Trainer", "TrainSettings", "apply_lora", "freeze", "merge_lora", "train_policy"]
