"""Episode data: LeRobot datasets on disk as training samples, and the synthetic dataset of the tests."""

from pi0_torch.data.lerobot_dataset import LeRobotDatasetError, LeRobotEpisodeDataset

__all__ = ["LeRobotDatasetError", "LeRobotEpisodeDataset"]
