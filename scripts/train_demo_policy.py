"""Reproduce the shipped demo policy `pi0_torch/demo_policy/` (what `pi0-torch demo` / `make demo` evaluates).

    .venv/bin/python scripts/train_demo_policy.py [--work-dir outputs/demo_training] [--rtc-max-delay 0]
        [--destination pi0_torch/demo_policy] [--threads 2] [--steps-scale 1.0] [--episodes-scale 1.0]

    # the policy fine-tuned with training-time RTC, for benchmarks/bench_closed_loop.py (shares the plain stages):
    .venv/bin/python scripts/train_demo_policy.py --rtc-max-delay 8 --destination outputs/demo_policy_rtc8
    # the policy fine-tuned with openpi's image augmentation (robust to a moved camera; docs/training.md):
    .venv/bin/python scripts/train_demo_policy.py --augment-stage --destination outputs/demo_policy_augmented

1. records scripted-expert demonstrations of the three tabletop tasks (`pi0_torch.envs`: Reach, PickPlace, Conveyor;
   seeds from 0, failed episodes skipped) into LeRobot v3.0 datasets with the shared writer (`pi0-torch demos` does
   the same per task);
2. trains the tiny π0 of `DEMO_POLICY_CONFIG` from scratch with the real pipeline (`pi0_torch.training.train_policy`,
   the HF Trainer) in the four `STAGES` of a curriculum: first finding the object the instruction names (Reach),
   then all three tasks, then a PickPlace-weighted mix, continued at a lower learning rate, each stage from the
   previous stage's model, all without image augmentation. Position targets are learned relative to the effector
   (delta actions). `--augment-stage` then fine-tunes the plain policy with openpi's image augmentation in a fifth
   stage, `AUGMENT_STAGE`, and `--rtc-max-delay D` with training-time real-time chunking in the last, `RTC_STAGE`
   (the shipped policy is plain);
3. evaluates it in closed loop on held-out seeds (`pi0-torch eval`'s `evaluate`, from seed 1,000,000, executing
   `DEMO_REPLAN_STEPS` actions of each chunk, sampled from noise of standard deviation `DEMO_NOISE_SCALE`) and copies
   the model, the processor, `demo_metrics.json` and `policy_settings.json` (the noise scale and replan steps it was
   validated with) into the destination.

A stage whose finished model has the same settings is reused, so a second invocation only evaluates.

Seeded throughout. The instructions' words are in the tokenizer's training text, so prompts stay short.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import gymnasium
import torch

from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.demo import DEMO_NOISE_SCALE, DEMO_REPLAN_STEPS
from pi0_torch.runtime.policy_settings import PolicySettings
from pi0_torch.envs import ENV_IDS
from pi0_torch.envs.demos import ACTION_NAMES, STATE_NAMES, successful_episodes
from pi0_torch.envs.tasks import CAMERA, WRIST_CAMERA
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, evaluate
from pi0_torch.training.checkpoints import FINAL_STEP_KEY, TRAIN_SETTINGS_FILE
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import scaled_warmup_steps, train_policy

REPO = Path(__file__).resolve().parent.parent
POLICY_FILES = ("config.json", "model.safetensors", "processor_config.json", "norm_stats.json", "tokenizer.model")
REACH, PICK_PLACE, CONVEYOR = ENV_IDS


@dataclass(frozen=True)
class Stage:
    """One training run of the recipe: successful expert episodes per (task, number of objects), optimizer steps,
    peak learning rate (warm-up 200 steps, cosine decay to 1e-4); every stage after the first starts from the previous
    stage's model; with openpi's image augmentation or without."""

    name: str
    episodes: dict[tuple[str, int], int]
    steps: int
    learning_rate: float = 2e-3
    augment: bool = False


# Stage 1 binds the instruction's color to the image: with three objects the policy must find the named one.
# Stage 2 adds the multi-stage tasks (grasp, carry, place; intercept on the belt), with easier one- and two-object
# scenes beside the benchmark's three. Stage 3 weights PickPlace, the slowest to learn, while keeping the other two
# (a stage on PickPlace alone forgets the conveyor); stage 4 continues it at a lower learning rate.
# docs/training.md has what each choice changed, measured.
PICK_PLACE_MIX = {(PICK_PLACE, 3): 3000, (REACH, 3): 1000, (CONVEYOR, 3): 1500}
STAGES = (
    Stage("reach", {(REACH, 3): 4000}, steps=3000),
    Stage("tasks", {(REACH, 3): 3000, (PICK_PLACE, 3): 3000, (CONVEYOR, 3): 3000,
                    (REACH, 1): 1500, (PICK_PLACE, 1): 1000, (CONVEYOR, 1): 1000,
                    (REACH, 2): 1000, (PICK_PLACE, 2): 1000, (CONVEYOR, 2): 1000}, steps=4000),
    Stage("pickplace", PICK_PLACE_MIX, steps=3000, learning_rate=1e-3),
    Stage("polish", PICK_PLACE_MIX, steps=2000, learning_rate=5e-4),
)
# With --rtc-max-delay D, the finished plain policy is fine-tuned with training-time RTC on the last stage's
# episodes, as one would fine-tune a pretrained π0 (the plain stages are shared with the plain policy). Training with
# delays from the start cost this small model most of what it learns: conditioned on committed actions, it continues
# them instead of reading the image (docs/training.md, measured).
RTC_STAGE = Stage("delays", STAGES[-1].episodes, steps=2000, learning_rate=5e-4)
# The plain stages train without image augmentation: from scratch, with openpi's augmentation in every stage, this
# small policy never learned PickPlace's precise grasp (60.7% on held-out seeds against 83.7%). With --augment-stage,
# the finished plain policy is fine-tuned with it, as openpi fine-tunes a pretrained π0: no worse than the shipped
# policy on clean frames and more robust to a shifted, recoloured camera, though the same steps without augmentation
# do better on clean frames (docs/training.md, measured).
AUGMENT_STAGE = Stage("augmented", STAGES[-1].episodes, steps=2000, learning_rate=5e-4, augment=True)

# `PI0Config.from_preset("pi0_small", **DEMO_POLICY_CONFIG)`: the table and wrist cameras at 48 x 48 (6 x 6 patches of 8
# each), 3 joint layers, the robot's 3 action dims, chunks of 16 steps (1.6 s at 10 Hz)
DEMO_POLICY_CONFIG = dict(
    image_size=48, patch_size=8,
    vision_hidden_size=48, vision_intermediate_size=96, vision_num_layers=2, vision_num_heads=2,
    vlm_hidden_size=64, vlm_intermediate_size=128, expert_hidden_size=48, expert_intermediate_size=96,
    num_hidden_layers=3, num_attention_heads=2, num_key_value_heads=1, head_dim=32, vocab_size=512,
    action_dim=3, action_horizon=16, max_token_len=16, num_inference_steps=10,
    camera_names=[CAMERA, WRIST_CAMERA],
)
DELTA_ACTION_MASK = [True, True, False]  # the position target is learned relative to the effector (openpi's DeltaActions)
HELDOUT_SEED = 1_000_000


def instructions() -> list[str]:
    """Every instruction the tasks can give (for the tokenizer's training text)."""
    prompts = set()
    for env_id in ENV_IDS:
        env = gymnasium.make(env_id)
        for seed in range(300):
            prompts.add(env.reset(seed=seed)[0]["prompt"])
        env.close()
    return sorted(prompts)


def record(root: Path, episodes: dict[tuple[str, int], int]) -> None:
    """Expert episodes of every task and object count (seeds 0, 1, ...; failed ones skipped) as one dataset."""

    def stream() -> Iterator[EpisodeRecord]:
        for (env_id, num_objects), count in episodes.items():
            env = gymnasium.make(env_id, num_objects=num_objects)
            for episode in successful_episodes(env, count):
                episode.extra.update(env=env_id, num_objects=num_objects)
                yield episode
            env.close()

    write_lerobot_dataset(root, stream(), fps=10, vector_names={"observation.state": STATE_NAMES, "action": ACTION_NAMES},
                          storage="image", episodes_per_file=200, robot_type="pi0_torch_tabletop")


def closed_loop_success(policy_dir: Path, episodes: int) -> dict[str, dict]:
    """Success of the policy on held-out seeds of every task (what `demo_metrics.json` records)."""
    policy = LocalPolicy(PI0Policy.from_pretrained(policy_dir, device="cpu", noise_scale=DEMO_NOISE_SCALE))
    success = {}
    for env_id in ENV_IDS:
        settings = EvalSettings(env=env_id, episodes=episodes, num_envs=25, seed=HELDOUT_SEED, replan_steps=DEMO_REPLAN_STEPS)
        outcome = evaluate(policy, settings)
        print(outcome.summary())
        success[env_id] = {"success_rate": outcome.success_rate, "success_ci95": outcome.success_ci95,
                           "episodes": outcome.episodes, "seed": HELDOUT_SEED, "replan_steps": DEMO_REPLAN_STEPS,
                           "noise_scale": DEMO_NOISE_SCALE,
                           "successes": [int(e["success"]) for e in outcome.episodes_detail]}
    return success


def trainer_state(settings: TrainSettings) -> Path:
    """The Trainer's log of a finished run: its last checkpoint's `trainer_state.json`."""
    return Path(settings.output_dir) / f"checkpoint-{settings.max_steps}" / "trainer_state.json"


def trained_with(settings: TrainSettings) -> bool:
    """Whether `settings.output_dir` holds the finished model of a run with exactly these settings."""
    run_dir = Path(settings.output_dir)
    saved = run_dir / TRAIN_SETTINGS_FILE
    if not ((run_dir / "model.safetensors").is_file() and trainer_state(settings).is_file() and saved.is_file()):
        return False
    recorded = {name: value for name, value in json.loads(saved.read_text()).items() if name != FINAL_STEP_KEY}
    return recorded == json.loads(json.dumps(vars(settings), default=str))


def dataset_folder(work_dir: Path, episodes: dict[tuple[str, int], int]) -> Path:
    """The dataset of these episodes under `work_dir`, named by task, number of objects and count (recorded once)."""
    name = "_".join(f"{env_id.split('/')[1].split('-')[0].lower()}{objects}x{count}" for (env_id, objects), count in episodes.items())
    root = work_dir / f"demos_{name}"
    if not root.exists():
        record(root, episodes)
    return root


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work-dir", type=Path, default=REPO / "outputs" / "demo_training")
    parser.add_argument("--rtc-max-delay", type=int, default=0,
                        help="fine-tune the plain policy with training-time real-time chunking (delays up to D) in a "
                        "fifth stage (the shipped policy: 0)")
    parser.add_argument("--augment-stage", action="store_true",
                        help="fine-tune the plain policy with openpi's image augmentation in one more stage (before "
                        "the RTC stage; the shipped policy: without)")
    parser.add_argument("--steps-scale", type=float, default=1.0, help="fraction of every stage's steps (quick checks)")
    parser.add_argument("--episodes-scale", type=float, default=1.0, help="fraction of every stage's episodes")
    parser.add_argument("--eval-episodes", type=int, default=300)
    parser.add_argument("--destination", type=Path, default=REPO / "pi0_torch" / "demo_policy")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (the shipped policy: 2)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    tokenizer = args.work_dir / "tokenizer.model"

    start, model, loss, reused = time.time(), None, [], []
    stages = [*STAGES, *([AUGMENT_STAGE] if args.augment_stage else []), *([RTC_STAGE] if args.rtc_max_delay else [])]
    steps = [max(1, round(stage.steps * args.steps_scale)) for stage in stages]
    episodes = [{key: max(1, round(count * args.episodes_scale)) for key, count in stage.episodes.items()} for stage in stages]
    datasets = [dataset_folder(args.work_dir, stage_episodes) for stage_episodes in episodes]  # all recorded first
    for stage, dataset, stage_steps in zip(stages, datasets, steps):
        rtc_max_delay = args.rtc_max_delay if stage is RTC_STAGE else 0
        run_dir = args.work_dir / f"{stage.name}_rtc{rtc_max_delay}"
        settings = TrainSettings(
            dataset=str(dataset), model=str(model or "pi0_small"), output_dir=str(run_dir),
            config_overrides={} if model else DEMO_POLICY_CONFIG, tokenizer=None if model else str(tokenizer),
            max_steps=stage_steps, batch_size=64, learning_rate=stage.learning_rate, end_learning_rate=1e-4,
            warmup_steps=200 if stage_steps > 200 else scaled_warmup_steps(stage_steps),  # (the Trainer would scale it)
            logging_steps=100, save_steps=stage_steps, seed=0, rtc_max_delay=rtc_max_delay or None, augment=stage.augment,
            delta_action_mask=DELTA_ACTION_MASK,
            norm_stats="dataset",  # (each stage's own episodes: Reach's gripper never moves, PickPlace's does)
        )
        if trained_with(settings):  # e.g. the plain stages, trained by the plain policy's run
            print(f"stage {stage.name}: reusing {run_dir}, trained with the same settings")
            log_history = json.loads(trainer_state(settings).read_text())["log_history"]
            reused.append(stage.name)
        else:
            if run_dir.exists():
                shutil.rmtree(run_dir)
            if model is None:  # the first stage builds the model, and its tokenizer, from scratch
                build_test_tokenizer(extra_sentences=instructions() * 20, save_to=tokenizer)
            log_history = train_policy(settings)["log_history"]
        loss.append({"stage": stage.name, "loss": [[e["step"], round(e["loss"], 4)] for e in log_history if "loss" in e]})
        model = run_dir
    assert model is not None
    minutes = (time.time() - start) / 60

    success = closed_loop_success(model, args.eval_episodes)

    args.destination.mkdir(parents=True, exist_ok=True)
    for name in POLICY_FILES:
        shutil.copy2(model / name, args.destination / name)
    metrics = {
        "closed_loop": success,
        "demo_episodes": {stage.name: {f"{env_id} x{objects}": count for (env_id, objects), count in stage_episodes.items()}
                          for stage, stage_episodes in zip(stages, episodes)},
        "steps": {stage.name: stage_steps for stage, stage_steps in zip(stages, steps)},
        "train_minutes": round(minutes, 1),  # recording and training in this invocation, without reused stages
        "reused_stages": reused,
        "rtc_max_delay": args.rtc_max_delay,
        "augmented_stages": [stage.name for stage in stages if stage.augment],
        "train_loss": loss,
        "torch": torch.__version__,
        "threads": args.threads,
    }
    (args.destination / "demo_metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    # how it was validated, for every runner of the folder (PI0Policy, eval, serve) to use unless told otherwise
    PolicySettings(noise_scale=DEMO_NOISE_SCALE, replan_steps=DEMO_REPLAN_STEPS).save(args.destination)
    print(f"wrote {args.destination} ({minutes:.1f} min of recording and training)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
