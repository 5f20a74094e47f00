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

import io
import json
import shutil
import tempfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

import av
import datasets
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

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


def _encode_video(path: Path, frames: list[np.ndarray], fps: int, codec: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(codec, rate=fps)
        height, width = frames[0].shape[:2]
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.time_base = Fraction(1, fps)
        stream.codec_context.gop_size = 10
        if codec in ("libx264", "h264"):
            stream.options = {"crf": "8", "bf": "0"}
        for number, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(frame, format="rgb24")
            picture.pts = number
            container.mux(stream.encode(picture))
        container.mux(stream.encode(None))


def _png(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def _vector_stats(values: np.ndarray) -> dict[str, list[float]]:
    return {
        "mean": values.mean(0).tolist(), "std": values.std(0).tolist(), "min": values.min(0).tolist(),
        "max": values.max(0).tolist(), "count": [len(values)],
        "q01": np.quantile(values, 0.01, axis=0).tolist(), "q99": np.quantile(values, 0.99, axis=0).tolist(),
    }


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
        `root` as a `Path`. The folder is assembled in a temporary sibling and renamed at the end, so a failure
        leaves nothing behind.
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
    task_index = {task: i for i, task in enumerate(tasks)}
    root.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{root.name}-", dir=root.parent))
    try:
        _write(staging, scenes, lengths, task_index, image_size, fps, storage, episodes_per_file, codec, num_heldout)
        staging.rename(root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return root


def _write(
    root: Path,
    scenes: list[Scene],
    lengths: list[int],
    task_index: dict[str, int],
    image_size: int,
    fps: int,
    storage: str,
    episodes_per_file: int,
    codec: str,
    num_heldout: int,
) -> None:
    camera_feature = {
        "dtype": storage,
        "shape": [image_size, image_size, 3],
        "names": ["height", "width", "channels"],
    }
    if storage == "video":
        camera_feature["info"] = {
            "video.height": image_size, "video.width": image_size, "video.codec": codec, "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False, "video.fps": fps, "video.channels": 3, "has_audio": False,
        }
    elif storage != "image":
        raise ValueError(f"storage must be 'video' or 'image', got {storage!r}")
    features = {
        CAMERA_KEY: camera_feature,
        "observation.state": {"dtype": "float32", "shape": [2], "names": ["x", "y"]},
        "action": {"dtype": "float32", "shape": [2], "names": ["dx", "dy"]},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    hf_features = datasets.Features(
        {
            **({CAMERA_KEY: datasets.Image()} if storage == "image" else {}),
            "observation.state": datasets.Sequence(datasets.Value("float32"), length=2),
            "action": datasets.Sequence(datasets.Value("float32"), length=2),
            "timestamp": datasets.Value("float32"),
            "frame_index": datasets.Value("int64"),
            "episode_index": datasets.Value("int64"),
            "index": datasets.Value("int64"),
            "task_index": datasets.Value("int64"),
        }
    )
    data_template = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    video_template = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"

    episode_rows: list[dict[str, Any]] = []
    all_states, all_actions = [], []
    global_index = 0
    for file_index, first in enumerate(range(0, len(scenes), episodes_per_file)):
        columns: dict[str, list[Any]] = {name: [] for name in hf_features}
        video_frames: list[np.ndarray] = []
        for episode_index in range(first, min(first + episodes_per_file, len(scenes))):
            scene, length = scenes[episode_index], lengths[episode_index]
            states, actions = rollout(scene, length)
            all_states.append(states)
            all_actions.append(actions)
            images = [render(scene, state, image_size) for state in states]
            episode_rows.append(
                {
                    "episode_index": episode_index,
                    "tasks": [scene.prompt],
                    "length": length,
                    "data/chunk_index": 0,
                    "data/file_index": file_index,
                    "dataset_from_index": global_index,
                    "dataset_to_index": global_index + length,
                    **(
                        {
                            f"videos/{CAMERA_KEY}/chunk_index": 0,
                            f"videos/{CAMERA_KEY}/file_index": file_index,
                            f"videos/{CAMERA_KEY}/from_timestamp": len(video_frames) / fps,
                            f"videos/{CAMERA_KEY}/to_timestamp": (len(video_frames) + length) / fps,
                        }
                        if storage == "video"
                        else {}
                    ),
                    "meta/episodes/chunk_index": 0,
                    "meta/episodes/file_index": 0,
                    **{
                        f"stats/{name}/{stat}": value
                        for name, values in (("observation.state", states), ("action", actions))
                        for stat, value in _vector_stats(values).items()
                    },
                }
            )
            for t in range(length):
                columns["observation.state"].append(states[t].tolist())
                columns["action"].append(actions[t].tolist())
                columns["timestamp"].append(t / fps)
                columns["frame_index"].append(t)
                columns["episode_index"].append(episode_index)
                columns["index"].append(global_index + t)
                columns["task_index"].append(task_index[scene.prompt])
                if storage == "image":
                    columns[CAMERA_KEY].append({"bytes": _png(images[t]), "path": None})
            if storage == "video":
                video_frames.extend(images)
            global_index += length
        data_path = root / data_template.format(chunk_index=0, file_index=file_index)
        data_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pydict(columns, schema=hf_features.arrow_schema), data_path)
        if storage == "video":
            _encode_video(root / video_template.format(video_key=CAMERA_KEY, chunk_index=0, file_index=file_index), video_frames, fps, codec)

    meta = root / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(episode_rows), meta / "episodes" / "chunk-000" / "file-000.parquet")
    # LeRobot's tasks table: a pandas frame indexed by the task string, one column task_index
    pd.DataFrame({"task_index": list(task_index.values())}, index=pd.Index(list(task_index), name="task")).to_parquet(
        meta / "tasks.parquet"
    )
    stats = {"observation.state": _vector_stats(np.concatenate(all_states)), "action": _vector_stats(np.concatenate(all_actions))}
    (meta / "stats.json").write_text(json.dumps(stats, indent=2))
    num_episodes = len(scenes)
    splits = {"train": f"0:{num_episodes - num_heldout}"}
    if num_heldout:
        splits["heldout"] = f"{num_episodes - num_heldout}:{num_episodes}"
    info = {
        "codebase_version": "v3.0",
        "robot_type": "synthetic_reacher",
        "total_episodes": num_episodes,
        "total_frames": global_index,
        "total_tasks": len(task_index),
        "chunks_size": 1000,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 500,
        "fps": fps,
        "splits": splits,
        "data_path": data_template,
        "video_path": video_template if storage == "video" else None,
        "features": features,
    }
    (meta / "info.json").write_text(json.dumps(info, indent=4))



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
    from pi0_torch.training.trainer import TrainSettings

    values: dict[str, Any] = dict(
        dataset=str(dataset), model="pi0_small", output_dir=str(output_dir), config_overrides=dict(DEMO_POLICY_CONFIG),
        tokenizer="test", train_split="train", max_steps=max_steps, batch_size=64, learning_rate=2e-3,
        end_learning_rate=2e-4, warmup_steps=100, decay_steps=DEMO_STEPS, logging_steps=50, save_steps=max_steps, seed=0,
    )
    values.update(overrides)
    return TrainSettings(**values)
