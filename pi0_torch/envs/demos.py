"""`pi0-torch demos`: record scripted-expert demonstrations of a tabletop env (or a Meta-World task) as a LeRobot
v3.0 dataset.

```
pi0-torch demos --env pi0_torch/PickPlace-v0 --episodes 500 --output-dir data/pickplace [--storage video|image]
                [--seed 0] [--image-size 96] [--max-steps N]
pi0-torch demos --env metaworld/drawer-open-v3 --episodes 100 --output-dir data/drawer --image-size 64
```

The expert runs with seeds S, S+1, ... until `--episodes` episodes have succeeded (failed seeds are skipped; each
episode's seed is the `seed` column of `meta/episodes`). Features: `observation.images.<camera>` (video or PNG
images; the env's cameras), `observation.state` and `action` (tabletop: `[x, y, gripper]` and
`[target_x, target_y, gripper]`; Meta-World: `pi0_torch.envs.metaworld`); one task per instruction; fps = the env's
control rate.

Nothing recorded is lost: episodes are written in files of `EPISODES_PER_FILE`, each flushed to disk with a progress
record, into `.NAME.partial-resumable` beside the output folder, which appears whole at the end
([`pi0_torch.data.lerobot_writer.LeRobotDatasetWriter`]). After a kill, a full disk or Ctrl-C, the same command with
`--resume` continues after the last flushed file. `--overwrite` replaces only a folder pi0-torch wrote, never one
with other files in it, the working directory or its parents (`pi0_torch.utils.files.check_output_dir`).

>>> import tempfile
>>> summary = record_demos("pi0_torch/Reach-v0", 2, tempfile.mkdtemp() + "/reach", image_size=32, storage="image")
>>> summary.episodes, summary.failed_seeds
(2, [])
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from pi0_torch.utils.progress import tqdm

from pi0_torch.data.lerobot_writer import EpisodeRecord, LeRobotDatasetWriter, Storage, partial_dataset_episodes
from pi0_torch.envs import ENV_IDS, make_expert
from pi0_torch.envs.benchmarks import make_benchmark_env
from pi0_torch.utils.validation import MAX_SEED, check_int, first_line

STATE_NAMES = ["x", "y", "gripper"]  # (the tabletop envs')
ACTION_NAMES = ["target_x", "target_y", "gripper"]
MAX_ATTEMPTS_FACTOR = 2  # give up after this many times the wanted episodes (plus 10) without enough successes
EPISODES_PER_FILE = 50  # episodes per data file, flushed together: what an interruption can cost
MAX_EPISODES = 1_000_000
MAX_IMAGE_SIZE = 1_024


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
    episodes_per_file: int = EPISODES_PER_FILE,
    overwrite: bool = False,
    resume: bool = False,
    progress: bool = False,
    env_kwargs: Mapping[str, Any] | None = None,
) -> DemosSummary:
    """Write `num_episodes` successful expert episodes of `env_id` (seeds `seed`, `seed + 1`, ...) to `output_dir`.

    Every setting is checked before anything is recorded. Episodes are flushed in files of `episodes_per_file`;
    after an interruption, `resume=True` continues the partial dataset (same settings) after its last flushed file
    (see the module docstring)."""
    if env_id not in ENV_IDS and not env_id.startswith("metaworld/"):
        raise ValueError(f"unknown env {env_id!r}; known: {', '.join(ENV_IDS)}, metaworld/<task>-v3")
    check_int("--episodes", num_episodes, 1, MAX_EPISODES)
    check_int("--seed", seed, 0, MAX_SEED - MAX_ATTEMPTS_FACTOR * num_episodes - 10)  # every seed it may try fits int64
    check_int("--image-size", image_size, 8, MAX_IMAGE_SIZE)
    if storage == "video" and image_size % 2:
        raise ValueError(f"image size must be even for video storage (yuv420p), got {image_size}")
    if env_kwargs is not None and not isinstance(env_kwargs, Mapping):
        raise ValueError(f"env_kwargs must be a dict of env settings, got {type(env_kwargs).__name__}")
    try:
        make = make_benchmark_env if env_id.startswith("metaworld/") else gymnasium.make
        env = make(env_id, image_size=image_size, **(env_kwargs or {}))
    except TypeError as error:  # a setting the env does not take
        raise ValueError(f"{env_id} cannot be made with the settings {sorted(env_kwargs or {})}: {first_line(error)}") from None
    summary = DemosSummary(Path(output_dir))
    run = {"env": env_id, "seed": seed, "image_size": image_size, "env_kwargs": dict(env_kwargs or {})}
    with LeRobotDatasetWriter(
        output_dir, fps=env.unwrapped.control_hz,
        vector_names={"observation.state": getattr(env.unwrapped, "state_names", STATE_NAMES),
                      "action": getattr(env.unwrapped, "action_names", ACTION_NAMES)},
        storage=storage, episodes_per_file=episodes_per_file,
        robot_type=getattr(env.unwrapped, "robot_type", "pi0_torch_tabletop"), overwrite=overwrite,
        resumable=True, resume=resume, run_settings=run,
    ) as writer:
        summary.episodes = writer.episodes_written
        summary.frames = writer.total_frames
        summary.failed_seeds = list(writer.run_state.get("failed_seeds", []))
        remaining = num_episodes - writer.episodes_written
        if remaining < 0:
            raise ValueError(f"--resume: the partial dataset already holds {writer.episodes_written} episodes, more than "
                             f"--episodes {num_episodes}")
        bar = tqdm(total=num_episodes, initial=writer.episodes_written, desc=env_id, unit="episode", disable=not progress)
        start = writer.run_state.get("next_seed", seed)
        for record in successful_episodes(env, remaining, start, summary.failed_seeds):
            summary.episodes += 1
            summary.frames += len(record)
            bar.update()
            writer.add(record, run_state={"next_seed": record.extra["seed"] + 1, "failed_seeds": list(summary.failed_seeds)})
        bar.close()
        writer.finish()
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--env", required=True, help=f"environment id, one of {', '.join(ENV_IDS)}, or "
                        "metaworld/<task>-v3 (needs pip install 'pi0-torch[metaworld]')")
    parser.add_argument("--episodes", type=int, required=True, help="successful episodes to record")
    parser.add_argument("--output-dir", required=True, help="the dataset folder to write (absent or empty)")
    parser.add_argument("--storage", choices=["video", "image"], default="video", help="camera as mp4 video or PNG images in the parquet")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (then seed+1, ...)")
    parser.add_argument("--image-size", type=int, default=96, help="camera image side in pixels")
    parser.add_argument("--max-steps", type=int, help="episode length limit (default: the env's)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir that pi0-torch "
                        "wrote (never a folder with other files), or discard the partial dataset of an interrupted run")
    parser.add_argument("--resume", action="store_true", help="continue the partial dataset an interrupted run of "
                        "this command left (after its last flushed file of episodes)")


def run(args: argparse.Namespace) -> int:
    try:
        summary = record_demos(
            args.env, args.episodes, args.output_dir, seed=args.seed, image_size=args.image_size, storage=args.storage,
            overwrite=args.overwrite, resume=args.resume, progress=True,
            env_kwargs={"max_episode_steps": check_int("--max-steps", args.max_steps, 1, 1_000_000)} if args.max_steps else None,
        )
    except (ValueError, OSError, RuntimeError, KeyboardInterrupt) as error:  # settings, disk, expert: one line
        reason = "interrupted" if isinstance(error, KeyboardInterrupt) else first_line(error)
        kept = partial_dataset_episodes(args.output_dir)
        hint = f"; {kept} episodes are kept: run the same command with --resume to continue" if kept else ""
        raise SystemExit(f"pi0-torch demos: error: {reason}{hint}") from None
    attempts = summary.episodes + len(summary.failed_seeds)
    print(
        f"wrote {summary.episodes} episodes ({summary.frames} frames) of {args.env} to {summary.root}; "
        f"the expert succeeded in {summary.episodes}/{attempts} seeds"
    )
    return 0
