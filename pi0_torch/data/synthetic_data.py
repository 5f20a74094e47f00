"""A small synthetic LeRobot v3.0 dataset whose correct action depends on the image AND the instruction.

Scene: a plain dark background with three discs of different colors (out of red, green, blue, yellow), each in
its own cell of a 4 x 4 grid, and a white square "end effector" anywhere. The instruction names one color ("move to
the red object"); the effector moves toward the disc of that color with a proportional controller,
`a_t = gain * (target - p_t)`, `p_{t+1} = p_t + a_t`. Coordinates are (x, y) in [-1, 1] (x to the right, y down).

- state: the effector position `p_t` (2 values); action: the step `a_t` (2 values).
- Neither the image alone (three candidate discs) nor the instruction alone (the disc's position differs in every
  episode) determines the action; a policy must read both. Each episode has its own random layout, so the
  held-out episodes (the `heldout` split in `meta/info.json`) show layouts never seen in training.

The folder is written the way LeRobot v3.0 writes datasets (`meta/info.json`, `meta/tasks.parquet`,
`meta/episodes/chunk-000/file-000.parquet`, `meta/stats.json`, `data/chunk-000/file-XXX.parquet`, and one mp4 per
group of episodes under `videos/observation.images.base/chunk-000/`, encoded with PyAV), or with the camera stored
as PNG images inside the parquet (`storage="image"`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset

COLORS: dict[str, tuple[int, int, int]] = {
    "red": (220, 40, 40),
    "green": (40, 180, 60),
    "blue": (50, 90, 235),
    "yellow": (235, 210, 40),
}
BACKGROUND = (70, 70, 70)
EFFECTOR_COLOR = (255, 255, 255)
CAMERA_KEY = "observation.images.base"
PROMPT_TEMPLATE = "move to the {color} object"

MAX_OBJECTS = 3  # scenes hold 1..MAX_OBJECTS discs (the held-out split: always MAX_OBJECTS)
GRID_CELLS = 4  # discs sit at the centers of a GRID_CELLS x GRID_CELLS grid over the image
OBJECT_RADIUS = 0.18  # in [-1, 1] units (a cell is 0.5 wide)
EFFECTOR_HALF_SIZE = 0.07
GAIN = 0.25


@dataclass(frozen=True)
class Scene:
    """One episode's layout: disc colors and centers, the named color, the effector's start."""

    colors: tuple[str, ...]
    centers: np.ndarray  # float32 [objects, 2]
    target_color: str
    start: np.ndarray  # float32 [2]

    @property
    def target(self) -> np.ndarray:
        return self.centers[self.colors.index(self.target_color)]

    @property
    def prompt(self) -> str:
        return PROMPT_TEMPLATE.format(color=self.target_color)


def sample_scene(rng: np.random.Generator, num_objects: int = MAX_OBJECTS) -> Scene:
    """A random layout: `num_objects` distinct colors in distinct grid cells; the effector starts away from the target."""
    colors = tuple(str(c) for c in rng.choice(list(COLORS), size=num_objects, replace=False))
    cells = rng.choice(GRID_CELLS * GRID_CELLS, size=num_objects, replace=False)
    cell_centers = (np.arange(GRID_CELLS) + 0.5) / GRID_CELLS * 2 - 1
    centers = np.stack([cell_centers[cells % GRID_CELLS], cell_centers[cells // GRID_CELLS]], axis=1)
    target_color = colors[int(rng.integers(num_objects))]
    target = centers[colors.index(target_color)]
    while True:
        start = rng.uniform(-0.9, 0.9, size=2)
        if np.linalg.norm(start - target) > 0.6:
            break
    return Scene(colors, centers.astype(np.float32), target_color, start.astype(np.float32))


def rollout(scene: Scene, length: int) -> tuple[np.ndarray, np.ndarray]:
    """Effector positions (states) `[length, 2]` and steps (actions) `[length, 2]` of the scripted reach."""
    states = np.zeros((length, 2), np.float32)
    actions = np.zeros((length, 2), np.float32)
    position = scene.start.astype(np.float32)
    for t in range(length):
        step = GAIN * (scene.target - position)
        states[t], actions[t] = position, step
        position = (position + step).astype(np.float32)
    return states, actions


def render(scene: Scene, effector: np.ndarray, image_size: int) -> np.ndarray:
    """The camera image, uint8 `[image_size, image_size, 3]`."""
    pixel = (np.arange(image_size) + 0.5) / image_size * 2 - 1  # pixel centers in [-1, 1]
    x, y = np.meshgrid(pixel, pixel)  # [H, W], y down the rows
    image = np.empty((image_size, image_size, 3), np.uint8)
    image[:] = BACKGROUND
    for color, center in zip(scene.colors, scene.centers):
        image[(x - center[0]) ** 2 + (y - center[1]) ** 2 <= OBJECT_RADIUS**2] = COLORS[color]
    square = (np.abs(x - effector[0]) <= EFFECTOR_HALF_SIZE) & (np.abs(y - effector[1]) <= EFFECTOR_HALF_SIZE)
    image[square] = EFFECTOR_COLOR
    return image


def write_synthetic_dataset(
    root: str | Path,
    *,
    num_episodes: int = 120,
    num_heldout: int = 0,
    episode_length: int = 20,
    image_size: int = 64,
    fps: int = 10,
    seed: int = 0,
    storage: Literal["video", "image"] = "video",
    episodes_per_file: int = 50,
    codec: str = "libx264",
    episode_lengths: list[int] | None = None,
    min_objects: int = 1,
) -> Path:
    """Write the colored-disc reaching dataset to `root` (which must not exist) in LeRobot v3.0 layout.

    Args:
        num_episodes: episodes in total; the last `num_heldout` form the `heldout` split of `meta/info.json`
            (`splits: {"train": "0:N", "heldout": "N:M"}`).
        min_objects: training scenes hold between `min_objects` and 3 discs (scenes with one disc teach "go to
            the disc"; with several, only the instruction tells which); held-out scenes always hold 3.
        episode_length: frames per episode (`episode_lengths` gives each episode its own length instead).
        image_size: camera resolution (square, even for yuv420p video).
        storage: "video" (mp4 per group of `episodes_per_file` episodes) or "image" (PNG bytes in the parquet).
        codec: PyAV encoder for the videos (LeRobot uses libsvtav1 by default; h264 decodes everywhere).

    Returns:
        `root` as a `Path`. Written by `pi0_torch.data.lerobot_writer` (assembled aside and renamed into place, so
        a failure leaves nothing behind).
    """
    root = Path(root)
    if root.exists():
        raise FileExistsError(f"{root} already exists")
    if image_size % 2:
        raise ValueError(f"image_size must be even (yuv420p video), got {image_size}")
    lengths = list(episode_lengths) if episode_lengths is not None else [episode_length] * num_episodes
    if len(lengths) != num_episodes or min(lengths) < 1:
        raise ValueError(f"need {num_episodes} positive episode lengths, got {lengths}")
    if not 0 <= num_heldout < num_episodes:
        raise ValueError(f"num_heldout must be in [0, num_episodes), got {num_heldout}")
    if not 1 <= min_objects <= MAX_OBJECTS:
        raise ValueError(f"min_objects must be in [1, {MAX_OBJECTS}], got {min_objects}")

    rng = np.random.default_rng(seed)
    num_train = num_episodes - num_heldout
    scenes = [
        sample_scene(rng, int(rng.integers(min_objects, MAX_OBJECTS + 1)) if index < num_train else MAX_OBJECTS)
        for index in range(num_episodes)
    ]
    tasks = sorted({scene.prompt for scene in scenes})
    return write_lerobot_dataset(
        root, _episodes(scenes, lengths, image_size), fps=fps, vector_names={"observation.state": ["x", "y"], "action": ["dx", "dy"]},
        storage=storage, codec=codec, episodes_per_file=episodes_per_file, robot_type="synthetic_reacher",
        num_heldout=num_heldout, tasks=tasks,
    )


def _episodes(scenes: list[Scene], lengths: list[int], image_size: int) -> Iterator[EpisodeRecord]:
    for scene, length in zip(scenes, lengths):
        states, actions = rollout(scene, length)
        frames = np.stack([render(scene, state, image_size) for state in states])  # [T, H, W, 3]
        yield EpisodeRecord(scene.prompt, {CAMERA_KEY: frames}, {"observation.state": states, "action": actions})


# ----------------------------------------------------------------------------------------------------------------
# The demo task: the dataset `make demo`'s policy was trained on, the tiny π0 that learns it, and the recipe.
# ----------------------------------------------------------------------------------------------------------------

# write_synthetic_dataset arguments of the demo's training data (the last 60 episodes, 3 discs each, are held out)
DEMO_DATASET = dict(num_episodes=960, num_heldout=60, episode_length=12, image_size=56, seed=0, episodes_per_file=320)

# the held-out scenes `make demo` evaluates on: 24 new layouts (another seed), 3 discs each
DEMO_HELDOUT = dict(num_episodes=24, num_heldout=0, episode_length=12, image_size=56, seed=1000, min_objects=3)

# `PI0Config.from_preset("pi0_small", **DEMO_POLICY_CONFIG)`: ~0.2 M parameters, one 56 x 56 camera (4 x 4 patches
# of 14), 3 joint layers, the robot's 2 action dims, chunks of 8
DEMO_POLICY_CONFIG: dict[str, Any] = dict(
    image_size=56, patch_size=14,
    vision_hidden_size=32, vision_intermediate_size=64, vision_num_layers=1, vision_num_heads=2,
    vlm_hidden_size=64, vlm_intermediate_size=128, expert_hidden_size=32, expert_intermediate_size=64,
    num_hidden_layers=3, num_attention_heads=2, num_key_value_heads=1, head_dim=32, vocab_size=512,
    action_dim=2, action_horizon=8, max_token_len=16, num_inference_steps=10, camera_names=["base_0_rgb"],
)


DEMO_STEPS = 6000


def demo_train_settings(dataset: str | Path, output_dir: str | Path, max_steps: int = DEMO_STEPS, **overrides: Any) -> Any:
    """The `TrainSettings` of the demo policy (a tiny model from scratch: a higher learning rate and batch than
    openpi's fine-tuning recipe, which starts from a pretrained model). The learning rate follows the schedule of the
    full `DEMO_STEPS` run whatever `max_steps` is, so a shorter run is the start of the demo policy's run."""
    from pi0_torch.training.settings import TrainSettings

    values: dict[str, Any] = dict(
        dataset=str(dataset), model="pi0_small", output_dir=str(output_dir), config_overrides=dict(DEMO_POLICY_CONFIG),
        tokenizer="test", train_split="train", max_steps=max_steps, batch_size=64, learning_rate=2e-3,
        end_learning_rate=2e-4, warmup_steps=100, decay_steps=DEMO_STEPS, logging_steps=50, save_steps=max_steps, seed=0,
    )
    values.update(overrides)
    return TrainSettings(**values)
