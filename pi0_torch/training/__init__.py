"""Fine-tuning with the Hugging Face `Trainer` (one process or many through `accelerate`); imported on first use,
and needs `pip install 'pi0-torch[train]'`.

`python -m pi0_torch.training ...` is `pi0-torch train ...` (handy after `accelerate launch -m`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.training.batches import PI0DataCollator
    from pi0_torch.training.pi0_trainer import EMACallback, PI0Trainer
    from pi0_torch.training.settings import TrainSettings
    from pi0_torch.training.lora import apply_lora, merge_lora
    from pi0_torch.training.trainable import freeze
    from pi0_torch.training.trainer import train_policy

_EXPORTS = {
    "EMACallback": "pi0_torch.training.pi0_trainer",
    "PI0DataCollator": "pi0_torch.training.batches",
    "PI0Trainer": "pi0_torch.training.pi0_trainer",
    "TrainSettings": "pi0_torch.training.settings",
    "apply_lora": "pi0_torch.training.lora",
    "freeze": "pi0_torch.training.trainable",
    "merge_lora": "pi0_torch.training.lora",
    "train_policy": "pi0_torch.training.trainer",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
