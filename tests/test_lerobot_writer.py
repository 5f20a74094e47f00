"""The LeRobot v3.0 writer and `pi0-torch demos`: round trips through our reader, and a dataset that trains."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import torch

from pi0_torch.cli import main
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset, read_info
from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.envs import make_expert
from pi0_torch.envs.demos import record_demos
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

CAMERA_KEY, WRIST_KEY = "observation.images.base_0_rgb", "observation.images.left_wrist_0_rgb"

HORIZON = 4
VECTORS = {"observation.state": ["x", "y", "gripper"], "action": ["target_x", "target_y", "gripper"]}


def _expert_run(env_id: str, seed: int, image_size: int) -> tuple[list, list, list, str]:
    """The observations' images and states, the actions and the prompt of one expert episode, replayed directly."""
    env = gymnasium.make(env_id, image_size=image_size)
    observation, _ = env.reset(seed=seed)
    expert = make_expert(env)
    expert.reset(seed)
    images, states, actions, done = [], [], [], False
    while not done:
        action = expert.act(env)
        images.append(observation["images"]["base_0_rgb"])
        states.append(observation["state"])
        actions.append(action)
        observation, _, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
    return images, states, actions, observation["prompt"]


@pytest.mark.parametrize("storage", ["image", "video"])
def test_demos_round_trip_through_our_reader(tmp_path: Path, storage: str) -> None:
    root = tmp_path / "pickplace"
    summary = record_demos("pi0_torch/PickPlace-v0", 3, root, seed=10, image_size=32, storage=storage, episodes_per_file=2)
    assert summary.episodes == 3 and summary.failed_seeds == []
    info = read_info(root)
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10 and info["total_episodes"] == 3
    for key in (CAMERA_KEY, WRIST_KEY):  # both of the env's cameras
        assert info["features"][key]["dtype"] == storage and info["features"][key]["shape"] == [32, 32, 3]
    assert info["features"]["action"]["names"] == VECTORS["action"] and info["total_frames"] == summary.frames
    assert (root / "data" / "chunk-000" / "file-001.parquet").is_file()  # two episodes per file
    assert ((root / "videos" / CAMERA_KEY / "chunk-000" / "file-001.mp4").is_file()) == (storage == "video")
    episodes = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pandas()
    assert episodes["seed"].tolist() == [10, 11, 12]
    tasks = pd.read_parquet(root / "meta" / "tasks.parquet")
    dataset = LeRobotEpisodeDataset(root, HORIZON, progress=False)
    assert len(dataset) == summary.frames
    position = 0
    for episode_number, seed in enumerate((10, 11, 12)):
        images, states, actions, prompt = _expert_run("pi0_torch/PickPlace-v0", seed, 32)
        assert prompt in tasks.index and episodes["tasks"][episode_number].tolist() == [prompt]
        for t in range(len(actions)):
            sample = dataset[position + t]
            assert sample["prompt"] == prompt
            np.testing.assert_array_equal(sample["state"], states[t])
            np.testing.assert_array_equal(sample["actions"][0], actions[t])
            image = sample["images"][CAMERA_KEY]
            if storage == "image":
                np.testing.assert_array_equal(image, images[t])
            else:  # h264 (crf 8, yuv420p: chroma at half resolution blurs the small discs' edges)
                error = np.abs(image.astype(int) - images[t].astype(int))
                assert np.median(error) <= 2 and error.mean() < 12
        position += len(actions)


def test_writer_refuses_bad_episodes_and_leaves_nothing(tmp_path: Path) -> None:
    good = EpisodeRecord("wave", {"cam": np.zeros((3, 8, 8, 3), np.uint8)},
                         {"observation.state": np.zeros((3, 3)), "action": np.zeros((3, 3))})
    bad_vector = EpisodeRecord("wave", {"cam": np.zeros((3, 8, 8, 3), np.uint8)},
                               {"observation.state": np.zeros((3, 2)), "action": np.zeros((3, 3))})
    bad_image = EpisodeRecord("wave", {"cam": np.zeros((3, 8, 8, 3), np.float32)},
                              {"observation.state": np.zeros((3, 3)), "action": np.zeros((3, 3))})
    for episodes, message in (([good, bad_vector], r"observation.state must have shape \(3, 3\)"),
                              ([good, bad_image], "cam must be uint8"), ([], "no episodes")):
        with pytest.raises(ValueError, match=message):
            write_lerobot_dataset(tmp_path / "out", episodes, fps=10, vector_names=VECTORS, storage="image")
        assert list(tmp_path.iterdir()) == []


def test_demos_cli_writes_a_dataset_that_trains(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "pickplace"
    assert main(["demos", "--env", "pi0_torch/PickPlace-v0", "--episodes", "2", "--output-dir", str(root),
                 "--storage", "image", "--image-size", "28", "--seed", "5"]) == 0
    assert "wrote 2 episodes" in capsys.readouterr().out
    tiny = dict(
        image_size=28, vision_hidden_size=16, vision_intermediate_size=32, vision_num_layers=1, vision_num_heads=2,
        vlm_hidden_size=32, vlm_intermediate_size=64, expert_hidden_size=16, expert_intermediate_size=32,
        num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1, head_dim=8, vocab_size=512,
        action_dim=3, action_horizon=HORIZON, max_token_len=16, camera_names=["base_0_rgb", "left_wrist_0_rgb"],
    )
    assert sorted(LeRobotEpisodeDataset(root, HORIZON, progress=False).camera_keys) == [CAMERA_KEY, WRIST_KEY]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", "--dataset", str(root), "--model", "pi0_small", "--config-overrides", json.dumps(tiny),
                     "--tokenizer", "test", "--output-dir", str(tmp_path / "policy"), "--max-steps", "2",
                     "--batch-size", "4", "--warmup-steps", "1", "--logging-steps", "1", "--save-steps", "1000",
                     "--cpu"]) == 0
    finally:
        torch.set_num_threads(threads)
    assert PI0ForActionGeneration.from_pretrained(tmp_path / "policy").config.action_dim == 3


def test_demos_cli_unknown_env_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="unknown env 'Nope'; known: pi0_torch/Reach-v0, pi0_torch/PickPlace-v0"):
        main(["demos", "--env", "Nope", "--episodes", "1", "--output-dir", str(tmp_path / "x")])
    assert not (tmp_path / "x").exists()
