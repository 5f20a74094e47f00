"""Reproduce the shipped demo policy `pi0_torch/demo_policy/` (what `pi0-torch demo` / `make demo` evaluates).

    .venv/bin/python scripts/train_demo_policy.py [--work-dir outputs/demo_training] [--max-steps 6000]
        [--rtc-max-delay 8] [--destination pi0_torch/demo_policy] [--envs ID ...] [--objects 1 2 3]

1. records scripted-expert demonstrations of the three tabletop tasks (`pi0_torch.envs`: Reach, PickPlace, Conveyor;
   seeds from 0) into one LeRobot v3.0 dataset with the shared writer (`pi0-torch demos` does the same per task);
2. trains the tiny π0 of `DEMO_POLICY_CONFIG` from scratch on all three with the real pipeline
   (`pi0_torch.training.train_policy`, the HF Trainer), position targets relative to the effector (delta actions)
   and training-time real-time chunking (`--rtc-max-delay`);
3. evaluates it in closed loop on held-out seeds (`pi0-torch eval`'s `evaluate`, from seed 1,000,000) and copies the
   model, the processor and `demo_metrics.json` into the destination.

Seeded throughout. The instructions' words are in the tokenizer's training text, so prompts stay short.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import gymnasium
import torch

from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.envs import ENV_IDS
from pi0_torch.envs.demos import ACTION_NAMES, STATE_NAMES, expert_episode
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, evaluate
from pi0_torch.training.trainer import TrainSettings, train_policy

REPO = Path(__file__).resolve().parent.parent
POLICY_FILES = ("config.json", "model.safetensors", "processor_config.json", "norm_stats.json", "tokenizer.model")

# successful expert episodes per task (PickPlace and Conveyor are multi-stage: more of them) and number of objects:
# the benchmark's three, plus easier scenes with one and two objects (a curriculum: with one object the image alone
# says where to go, which binds the instruction's color to the image sooner)
DEMO_EPISODES = {
    ("pi0_torch/Reach-v0", 3): 200, ("pi0_torch/PickPlace-v0", 3): 600, ("pi0_torch/Conveyor-v0", 3): 600,
    ("pi0_torch/Reach-v0", 1): 100, ("pi0_torch/PickPlace-v0", 1): 150, ("pi0_torch/Conveyor-v0", 1): 150,
    ("pi0_torch/Reach-v0", 2): 100, ("pi0_torch/PickPlace-v0", 2): 150, ("pi0_torch/Conveyor-v0", 2): 150,
}

# `PI0Config.from_preset("pi0_small", **DEMO_POLICY_CONFIG)`: one 48 x 48 camera (6 x 6 patches of 8), 3 joint layers,
# the robot's 3 action dims, chunks of 16 steps (1.6 s at 10 Hz)
DEMO_POLICY_CONFIG = dict(
    image_size=48, patch_size=8,
    vision_hidden_size=48, vision_intermediate_size=96, vision_num_layers=2, vision_num_heads=2,
    vlm_hidden_size=64, vlm_intermediate_size=128, expert_hidden_size=48, expert_intermediate_size=96,
    num_hidden_layers=3, num_attention_heads=2, num_key_value_heads=1, head_dim=32, vocab_size=512,
    action_dim=3, action_horizon=16, max_token_len=16, num_inference_steps=10, camera_names=["base_0_rgb"],
)
DEMO_STEPS = 6000
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
            kept = 0
            for seed in itertools.count():
                if kept == count:
                    break
                episode, success = expert_episode(env, seed)
                if success:
                    kept += 1
                    episode.extra.update(env=env_id, num_objects=num_objects)
                    yield episode
            env.close()

    write_lerobot_dataset(root, stream(), fps=10, vector_names={"observation.state": STATE_NAMES, "action": ACTION_NAMES},
                          storage="image", episodes_per_file=200, robot_type="pi0_torch_tabletop")


def closed_loop_success(policy_dir: Path, episodes: int) -> dict[str, dict]:
    """Success of the policy on held-out seeds of every task (what `demo_metrics.json` records)."""
    policy = LocalPolicy(PI0Policy.from_pretrained(policy_dir, device="cpu"))
    success = {}
    for env_id in ENV_IDS:
        outcome = evaluate(policy, EvalSettings(env=env_id, episodes=episodes, num_envs=25, seed=HELDOUT_SEED))
        print(outcome.summary())
        success[env_id] = {"success_rate": outcome.success_rate, "success_ci95": outcome.success_ci95,
                           "episodes": outcome.episodes, "seed": HELDOUT_SEED,
                           "successes": [int(e["success"]) for e in outcome.episodes_detail]}
    return success


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work-dir", type=Path, default=REPO / "outputs" / "demo_training")
    parser.add_argument("--max-steps", type=int, default=DEMO_STEPS)
    parser.add_argument("--rtc-max-delay", type=int, default=8)
    parser.add_argument("--episodes-scale", type=float, default=1.0, help="fraction of DEMO_EPISODES to record")
    parser.add_argument("--objects", type=int, nargs="+", default=[1, 2, 3], choices=[1, 2, 3],
                        help="train on the scenes of DEMO_EPISODES with these numbers of objects")
    parser.add_argument("--envs", nargs="+", default=list(ENV_IDS), choices=ENV_IDS, help="train on the scenes of these tasks")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--destination", type=Path, default=REPO / "pi0_torch" / "demo_policy")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the tiny model gains little from more)")
    parser.add_argument("--init-from", type=Path, help="continue from this model folder (a second stage: fresh "
                        "schedule at --learning-rate) instead of training from scratch")
    parser.add_argument("--learning-rate", type=float, default=2e-3)
    parser.add_argument("--run-name", help="the training folder under --work-dir (default from the settings)")
    parser.add_argument("--image-size", type=int, default=DEMO_POLICY_CONFIG["image_size"], help="the model's camera side")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.work_dir.mkdir(parents=True, exist_ok=True)

    episodes = {key: max(1, round(count * args.episodes_scale)) for key, count in DEMO_EPISODES.items()
                if key[1] in args.objects and key[0] in args.envs}
    dataset = args.work_dir / ("demos_" + "_".join(f"{env_id.split('/')[1].split('-')[0].lower()}{objects}x{count}"
                                                    for (env_id, objects), count in episodes.items()))
    if not dataset.exists():
        record(dataset, episodes)
    tokenizer = args.work_dir / "tokenizer.model"
    build_test_tokenizer(extra_sentences=instructions() * 20, save_to=tokenizer)

    run_dir = args.work_dir / (args.run_name or f"run_rtc{args.rtc_max_delay}_px{args.image_size}{'_stage2' if args.init_from else ''}")
    if run_dir.exists():
        shutil.rmtree(run_dir)
    start = time.time()
    settings = TrainSettings(
        dataset=str(dataset), model=str(args.init_from or "pi0_small"), output_dir=str(run_dir),
        config_overrides={} if args.init_from else {**DEMO_POLICY_CONFIG, "image_size": args.image_size},
        tokenizer=None if args.init_from else str(tokenizer),
        max_steps=args.max_steps, batch_size=64, learning_rate=args.learning_rate, end_learning_rate=1e-4, warmup_steps=200,
        logging_steps=100, save_steps=2000, seed=0, rtc_max_delay=args.rtc_max_delay or None, delta_action_mask=DELTA_ACTION_MASK,
    )
    result = train_policy(settings)
    minutes = (time.time() - start) / 60

    success = closed_loop_success(run_dir, args.eval_episodes)

    args.destination.mkdir(parents=True, exist_ok=True)
    for name in POLICY_FILES:
        shutil.copy2(run_dir / name, args.destination / name)
    metrics = {
        "closed_loop": success,
        "demo_episodes": {f"{env_id} x{objects}": count for (env_id, objects), count in episodes.items()},
        "train_minutes": round(minutes, 1),
        "max_steps": args.max_steps,
        "rtc_max_delay": args.rtc_max_delay,
        "train_loss": [[e["step"], round(e["loss"], 4)] for e in result["log_history"] if "loss" in e],
        "torch": torch.__version__,
        "threads": args.threads,
    }
    (args.destination / "demo_metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    print(f"wrote {args.destination} ({minutes:.1f} min of training)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
