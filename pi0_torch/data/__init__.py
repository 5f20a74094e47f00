"""Episode data: LeRobot datasets on disk as training samples, and the synthetic dataset of the tests (imported on
first use; LeRobot datasets need `pip install 'pi0-torch[train]'`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.data.lerobot_dataset import LeRobotDatasetError, LeRobotEpisodeDataset

_EXPORTS = {
    "LeRobotDatasetError": "pi0_torch.data.lerobot_dataset",
    "LeRobotEpisodeDataset": "pi0_torch.data.lerobot_dataset",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
