"""`pi0-torch demos`: record scripted-expert demonstrations of a tabletop env as a LeRobot v3.0 dataset.

```
pi0-torch demos --env pi0_torch/PickPlace-v0 --episodes 500 --output-dir data/pickplace [--storage video|image]
                [--seed 0] [--image-size 96]
```

The expert runs with seeds S, S+1, ... until `--episodes` episodes have succeeded (failed seeds are skipped; each
episode's seed is the `seed` column of `meta/episodes`). Features: `observation.images.base_0_rgb` and
`observation.images.left_wrist_0_rgb` (video or PNG images; the env's cameras), `observation.state`
`[x, y, gripper]`, `action` `[target_x, target_y, gripper]`; one task per instruction; fps = the env's control rate.

>>> import tempfile
>>> summary = record_demos("pi0_torch/Reach-v0", 2, tempfile.mkdtemp() + "/reach", image_size=32, storage="image")
>>> summary.episodes, summary.failed_seeds
(2, [])
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from tqdm.auto import tqdm

from pi0_torch.data.lerobot_writer import EpisodeRecord, Storage, write_lerobot_dataset
from pi0_torch.envs import ENV_IDS, make_expert
STATE_NAMES = ["x", "y", "gripper"]
ACTION_NAMES = ["target_x", "target_y", "gripper"]
MAX_ATTEMPTS_FACTOR = 2  # give up after this many times the wanted episodes (plus 10) without enough successes


@dataclass
class DemosSummary:
    """What `record_demos` wrote."""

    root: Path
    episodes: int = 0
    frames: int = 0
    failed_seeds: list[int] = field(default_factory=list)


def expert_episode(env: gymnasium.Env, seed: int) -> tuple[EpisodeRecord, bool]:
    """Run the scripted expert for one episode of `env` with `seed`; the recording and whether it succeeded."""
    observation, info = env.reset(seed=seed)
    expert = make_expert(env)
    expert.reset(seed)
    frames: dict[str, list[np.ndarray]] = {camera: [] for camera in observation["images"]}
    states, actions = [], []
    done = False
    while not done:
        action = expert.act(env)
        for camera, frame in observation["images"].items():
            frames[camera].append(frame)
        states.append(observation["state"])
        actions.append(action)
        observation, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    record = EpisodeRecord(
        observation["prompt"], {f"observation.images.{camera}": np.stack(shots) for camera, shots in frames.items()},
        {"observation.state": np.stack(states), "action": np.stack(actions)}, {"seed": seed},
    )
    return record, bool(info["is_success"])


def successful_episodes(env: gymnasium.Env, count: int, seed: int = 0,
                        failed_seeds: list[int] | None = None) -> Iterator[EpisodeRecord]:
    """The first `count` successful expert episodes of `env` from seeds `seed`, `seed + 1`, ...; failed seeds are
    skipped (and appended to `failed_seeds`). Raises once `MAX_ATTEMPTS_FACTOR * count + 10` seeds did not give
    `count` successes."""
    failed = [] if failed_seeds is None else failed_seeds
    kept, limit = 0, seed + MAX_ATTEMPTS_FACTOR * count + 10
    for next_seed in range(seed, limit):
        if kept == count:
            return
        record, success = expert_episode(env, next_seed)
        if not success:
            failed.append(next_seed)
            continue
        kept += 1
        yield record
    if kept < count:
        raise RuntimeError(f"the expert failed {len(failed)} of {limit - seed} episodes of {getattr(env.spec, 'id', env)}")


def record_demos(
    env_id: str,
    num_episodes: int,
    output_dir: str | Path,
    *,
    seed: int = 0,
    image_size: int = 96,
    storage: Storage = "video",
    episodes_per_file: int = 100,
    overwrite: bool = False,
    progress: bool = False,
    env_kwargs: dict[str, Any] | None = None,
) -> DemosSummary:
    """Write `num_episodes` successful expert episodes of `env_id` (seeds `seed`, `seed + 1`, ...) to `output_dir`."""
    if env_id not in ENV_IDS:
        raise ValueError(f"unknown env {env_id!r}; known: {', '.join(ENV_IDS)}")
    if num_episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {num_episodes}")
    if storage == "video" and image_size % 2:
        raise ValueError(f"image size must be even for video storage (yuv420p), got {image_size}")
    env = gymnasium.make(env_id, image_size=image_size, **(env_kwargs or {}))
    summary = DemosSummary(Path(output_dir))

    def episodes() -> Iterator[EpisodeRecord]:
        bar = tqdm(total=num_episodes, desc=env_id, unit="episode", disable=not progress)
        for record in successful_episodes(env, num_episodes, seed, summary.failed_seeds):
            summary.episodes += 1
            summary.frames += len(record)
            bar.update()
            yield record
        bar.close()

    write_lerobot_dataset(
        output_dir, episodes(), fps=env.unwrapped.control_hz,
        vector_names={"observation.state": STATE_NAMES, "action": ACTION_NAMES}, storage=storage,
        episodes_per_file=episodes_per_file, robot_type="pi0_torch_tabletop", overwrite=overwrite,
    )
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--env", required=True, help=f"environment id, one of {', '.join(ENV_IDS)}")
    parser.add_argument("--episodes", type=int, required=True, help="successful episodes to record")
    parser.add_argument("--output-dir", required=True, help="the dataset folder to write (absent or empty)")
    parser.add_argument("--storage", choices=["video", "image"], default="video", help="camera as mp4 video or PNG images in the parquet")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (then seed+1, ...)")
    parser.add_argument("--image-size", type=int, default=96, help="camera image side in pixels")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir")


def run(args: argparse.Namespace) -> int:
    try:
        summary = record_demos(
            args.env, args.episodes, args.output_dir, seed=args.seed, image_size=args.image_size, storage=args.storage,
            overwrite=args.overwrite, progress=True,
        )
    except ValueError as error:
        raise SystemExit(f"pi0-torch demos: error: {error}") from None
    attempts = summary.episodes + len(summary.failed_seeds)
    print(
        f"wrote {summary.episodes} episodes ({summary.frames} frames) of {args.env} to {summary.root}; "
        f"the expert succeeded in {summary.episodes}/{attempts} seeds"
    )
    return 0
