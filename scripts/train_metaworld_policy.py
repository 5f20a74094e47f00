"""Meta-World end to end: scripted-expert demonstrations, a small π0 trained from scratch, held-out evaluation.

    .venv/bin/python scripts/train_metaworld_policy.py [--work-dir outputs/metaworld] [--episodes 100] [--steps 4000]
        [--eval-episodes 50] [--threads 2] [--no-augment] [--no-baselines]

A dataset or a finished training run of the same settings in `--work-dir` is reused (only evaluated again). Each run
has its folder (`policy_<episodes>x<steps>`, `_noaug` without augmentation) with its `metaworld_metrics.json`.

1. records `--episodes` successful expert episodes of each task of `TASKS` (`pi0_torch.envs.metaworld`, seeds from
   0, failed seeds skipped, episodes of at most `MAX_STEPS` steps) into one LeRobot v3.0 dataset, as
   `pi0-torch demos --env metaworld/<task>` does per task;
2. trains the tiny π0 of `POLICY_CONFIG` from scratch with the real pipeline (`pi0_torch.training.train_policy`, the
   HF Trainer, the recipe of the shipped demo policy: AdamW, warm-up 200 steps, cosine decay to 1e-4, batch 64;
   openpi's image augmentation unless `--no-augment`);
3. evaluates it in closed loop on held-out seeds (from 1,000,000: placements no demonstration showed) with
   `pi0-torch eval`'s `evaluate`, beside the scripted expert and uniform random actions on the same seeds (not with
   `--no-baselines`), and writes `metaworld_metrics.json` and a Markdown table (success with 95% Wilson intervals).

Why these tasks: the object each one acts on (drawer, button, window) is large and visible in the 64 x 64 camera
frame, its expert succeeds in nearly every seed, and an episode takes 60-100 steps, so recording, training and
evaluating three of them fits in about an hour on 2 CPU cores (software rendering costs about 12 ms a frame).
Tasks whose goal is a small marker (reach, push) or needs precise grasps (pick-place) would need larger images and
more training than this budget.

Seeded throughout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import torch

from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.envs.demos import successful_episodes
from pi0_torch.envs.metaworld import ACTION_NAMES, CAMERA_NAME, STATE_NAMES, make_env, task_prompt
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.policy_settings import PolicySettings
from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, ScriptedPolicy, evaluate
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import train_policy

REPO = Path(__file__).resolve().parent.parent
TASKS = ("drawer-open-v3", "button-press-topdown-v3", "window-open-v3")
IMAGE_SIZE = 64
MAX_STEPS = 200  # per episode, demonstrations and evaluation (the experts need 60-100)
HELDOUT_SEED = 1_000_000
NOISE_SCALE, REPLAN_STEPS = 0.1, 8  # how the policy samples and executes chunks (the demo policy's noise scale)
# `PI0Config.from_preset("pi0_small", **POLICY_CONFIG)`: one 64 x 64 camera (8 x 8 patches of 8), 3 joint layers,
# Meta-World's 4 action dims (effector displacement, gripper effort), chunks of 16 steps
POLICY_CONFIG = dict(
    image_size=IMAGE_SIZE, patch_size=8,
    vision_hidden_size=48, vision_intermediate_size=96, vision_num_layers=2, vision_num_heads=2,
    vlm_hidden_size=64, vlm_intermediate_size=128, expert_hidden_size=48, expert_intermediate_size=96,
    num_hidden_layers=3, num_attention_heads=2, num_key_value_heads=1, head_dim=32, vocab_size=512,
    action_dim=4, action_horizon=16, max_token_len=16, num_inference_steps=10,
    camera_names=[CAMERA_NAME],
)


def record(root: Path, episodes: int) -> None:
    """`episodes` successful expert episodes of every task (seeds 0, 1, ...) as one dataset."""

    def stream() -> Iterator[EpisodeRecord]:
        for task in TASKS:
            env = make_env(task, image_size=IMAGE_SIZE, max_episode_steps=MAX_STEPS)
            for episode in successful_episodes(env, episodes):
                episode.extra.update(env=f"metaworld/{task}")
                yield episode
            env.close()

    write_lerobot_dataset(root, stream(), fps=20, vector_names={"observation.state": STATE_NAMES, "action": ACTION_NAMES},
                          storage="image", episodes_per_file=100, robot_type="sawyer")


def closed_loop(policies: dict[str, object], episodes: int) -> dict[str, dict[str, dict]]:
    """Success of each policy on the same held-out seeds of every task."""
    results: dict[str, dict[str, dict]] = {}
    for name, policy in policies.items():
        for task in TASKS:
            settings = EvalSettings(env=f"metaworld/{task}", episodes=episodes, num_envs=10, seed=HELDOUT_SEED,
                                    replan_steps=REPLAN_STEPS if name == "pi0" else None,
                                    env_kwargs={"image_size": IMAGE_SIZE, "max_episode_steps": MAX_STEPS})
            outcome = evaluate(policy, settings)
            print(f"{name}: {outcome.summary()}", flush=True)
            results.setdefault(name, {})[task] = {
                "success_rate": outcome.success_rate, "success_ci95": outcome.success_ci95, "episodes": outcome.episodes,
                "mean_steps": outcome.mean_steps, "successes": [int(e["success"]) for e in outcome.episodes_detail]}
    return results


def table(results: dict[str, dict[str, dict]]) -> str:
    """Markdown: one row per task, one column per policy, success % [95% interval]."""
    names = list(results)
    lines = ["| task | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for task in TASKS:
        cells = [f"{100 * r['success_rate']:.0f}% [{100 * r['success_ci95'][0]:.0f}, {100 * r['success_ci95'][1]:.0f}]"
                 for r in (results[name][task] for name in names)]
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work-dir", type=Path, default=REPO / "outputs" / "metaworld")
    parser.add_argument("--episodes", type=int, default=100, help="successful expert episodes per task")
    parser.add_argument("--steps", type=int, default=4000, help="optimizer steps")
    parser.add_argument("--eval-episodes", type=int, default=50, help="held-out episodes per task and policy")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-augment", action="store_true",
                        help="train without openpi's image augmentation (as the policy of docs/benchmarks.md before it)")
    parser.add_argument("--no-baselines", action="store_true", help="evaluate only the policy, not the expert and random")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    start = time.time()

    dataset = args.work_dir / f"demos_{args.episodes}"
    reused = []  # stages found finished (their minutes are not in this invocation's)
    if dataset.exists():
        reused.append("recording")
    else:
        record(dataset, args.episodes)
    recorded = time.time()
    tokenizer = args.work_dir / "tokenizer.model"
    build_test_tokenizer(extra_sentences=[task_prompt(task) for task in TASKS] * 50, save_to=tokenizer)
    run_dir = args.work_dir / f"policy_{args.episodes}x{args.steps}{'_noaug' if args.no_augment else ''}"
    settings = TrainSettings(
        dataset=str(dataset), model="pi0_small", output_dir=str(run_dir), config_overrides=POLICY_CONFIG,
        tokenizer=str(tokenizer), max_steps=args.steps, batch_size=64, learning_rate=2e-3, end_learning_rate=1e-4,
        warmup_steps=min(200, args.steps // 10), logging_steps=100, save_steps=args.steps, seed=0, overwrite=True, threads=args.threads,
        augment=not args.no_augment,
    )
    state = run_dir / f"checkpoint-{args.steps}" / "trainer_state.json"
    if (run_dir / "model.safetensors").is_file() and state.is_file():  # a finished run of these settings: evaluate it
        print(f"reusing the finished run {run_dir}")
        reused.append("training")
        log_history = json.loads(state.read_text())["log_history"]
    else:
        log_history = train_policy(settings)["log_history"]
        PolicySettings(noise_scale=NOISE_SCALE, replan_steps=REPLAN_STEPS).save(run_dir)
    trained = time.time()

    policy = LocalPolicy(PI0Policy.from_pretrained(run_dir, device="cpu"), source=run_dir)
    baselines = {} if args.no_baselines else {"expert": ScriptedPolicy("expert"), "random": ScriptedPolicy("random")}
    results = closed_loop({"pi0": policy, **baselines}, args.eval_episodes)
    metrics = {
        "tasks": list(TASKS), "episodes_per_task": args.episodes, "steps": args.steps, "max_episode_steps": MAX_STEPS,
        "augment": not args.no_augment, "heldout_seed": HELDOUT_SEED, "noise_scale": NOISE_SCALE, "replan_steps": REPLAN_STEPS,
        "closed_loop": results,
        "minutes": {"recording": round((recorded - start) / 60, 1), "training": round((trained - recorded) / 60, 1),
                    "evaluation": round((time.time() - trained) / 60, 1)}, "reused": reused,
        "train_loss": [[e["step"], round(e["loss"], 4)] for e in log_history if "loss" in e],
        "torch": torch.__version__, "threads": args.threads,
    }
    (run_dir / "metaworld_metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    print(table(results))
    print(f"minutes: {metrics['minutes']}; the policy: {run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
