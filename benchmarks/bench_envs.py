"""Benchmark the tabletop environments: speed, scripted-expert success, and Conveyor's sensitivity to delays.

    python benchmarks/bench_envs.py                         # 500 seeds per task, all three tables
    python benchmarks/bench_envs.py --seeds 100 --skip-delays

Tables (printed as markdown):
1. env steps per second on one core: `env.step` at `--image-size` (dynamics + both cameras + task checks), without
   rendering (the world's dynamics and the task checks only), and with the scripted expert choosing every action;
2. scripted-expert success over seeds 0 .. N-1 with 95% Wilson intervals, mean / max episode length and slips;
3. delay sensitivity: the expert acts for 8 steps, then the robot waits k steps (holding its last action, what a
   synchronous robot does while the next chunk is inferred), for k in `--pauses`; success with the default slip
   threshold and with slipping turned off (so lateness alone shows).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pi0_torch.envs import ENV_IDS, make_expert  # noqa: E402


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95% for z = 1.96)."""
    p = successes / trials
    denominator = 1 + z * z / trials
    center = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    return max(center - half, 0.0), min(center + half, 1.0)


def percent(successes: int, trials: int) -> str:
    low, high = wilson_interval(successes, trials)
    return f"{100 * successes / trials:.1f} [{100 * low:.1f}, {100 * high:.1f}]"


def run_episode(env: gymnasium.Env, expert, seed: int, act_steps: int = 0, pause: int = 0) -> dict:
    """One expert episode; with `pause`, the robot holds its last action for `pause` steps after every `act_steps`."""
    env.reset(seed=seed)
    expert.reset(seed)
    done, step, action = False, 0, None
    while not done:
        if pause == 0 or step % (act_steps + pause) < act_steps:
            action = expert.act(env)
        _, _, terminated, truncated, info = env.step(action)
        done, step = terminated or truncated, step + 1
    return {"success": bool(info["is_success"]), "length": step, "slipped": info["slipped"]}


def steps_per_second(env_id: str, image_size: int, steps: int) -> tuple[float, float, float]:
    env = gymnasium.make(env_id, image_size=image_size)
    task = env.unwrapped
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(steps, 3)).astype(np.float32)
    actions[:, :2] = np.cumsum(rng.normal(0, 0.02, size=(steps, 2)), axis=0).clip(-0.9, 0.9)  # a wandering target

    def timed(step_fn) -> float:
        env.reset(seed=0)
        start = time.perf_counter()
        for action in actions:
            step_fn(action)
        return steps / (time.perf_counter() - start)

    rendered = timed(task.step)

    def dynamics_only(action: np.ndarray) -> None:
        task.world.step(action[:2].astype(np.float64), float(action[2]))
        task.is_success() or task.is_failure()

    unrendered = timed(dynamics_only)
    expert = make_expert(env)
    start, count, seed = time.perf_counter(), 0, 0
    while count < steps:
        count += run_episode(env, expert, seed)["length"]
        seed += 1
    with_expert = count / (time.perf_counter() - start)
    return rendered, unrendered, with_expert


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=500, help="episodes per task for the success tables")
    parser.add_argument("--image-size", type=int, default=96)
    parser.add_argument("--speed-steps", type=int, default=3000)
    parser.add_argument("--pauses", default="0,2,4,6,8", help="k values of the delay table")
    parser.add_argument("--act-steps", type=int, default=8, help="steps the expert acts between pauses")
    parser.add_argument("--delay-envs", default="pi0_torch/Conveyor-v0,pi0_torch/PickPlace-v0")
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--skip-delays", action="store_true")
    args = parser.parse_args()

    if not args.skip_speed:
        print(f"\n### Steps per second (one process, table and wrist cameras of {args.image_size}x{args.image_size})\n")
        print("| env | env.step (rendered) | dynamics only | expert + env.step |")
        print("|---|---:|---:|---:|")
        for env_id in ENV_IDS:
            rendered, unrendered, with_expert = steps_per_second(env_id, args.image_size, args.speed_steps)
            print(f"| {env_id} | {rendered:,.0f} | {unrendered:,.0f} | {with_expert:,.0f} |", flush=True)

    print(f"\n### Scripted expert, seeds 0..{args.seeds - 1} (success %, 95% Wilson interval)\n")
    print("| env | success | mean length | max length | step limit | slips |")
    print("|---|---:|---:|---:|---:|---:|")
    for env_id in ENV_IDS:
        env = gymnasium.make(env_id, image_size=args.image_size)
        expert = make_expert(env)
        results = [run_episode(env, expert, seed) for seed in range(args.seeds)]
        successes = sum(r["success"] for r in results)
        lengths = [r["length"] for r in results]
        print(
            f"| {env_id} | {percent(successes, len(results))} | {np.mean(lengths):.1f} | {max(lengths)} | "
            f"{env.spec.max_episode_steps} | {sum(r['slipped'] for r in results)} |", flush=True,
        )

    if args.skip_delays:
        return
    pauses = [int(k) for k in args.pauses.split(",")]
    print(f"\n### Delay sensitivity: act {args.act_steps} steps, wait k (success %, 95% Wilson, {args.seeds} seeds)\n")
    print("| env | k | slip on (default 0.06) | slips per episode | slip off |")
    print("|---|---:|---:|---:|---:|")
    for env_id in args.delay_envs.split(","):
        for pause in pauses:
            row = []
            for slip in (None, math.inf):
                env = gymnasium.make(env_id, image_size=args.image_size, **({} if slip is None else {"slip_acceleration": slip}))
                expert = make_expert(env)
                results = [run_episode(env, expert, seed, args.act_steps, pause) for seed in range(args.seeds)]
                row.append((sum(r["success"] for r in results), np.mean([r["slipped"] for r in results])))
            (on, slips), (off, _) = row
            print(f"| {env_id} | {pause} | {percent(on, args.seeds)} | {slips:.2f} | {percent(off, args.seeds)} |", flush=True)


if __name__ == "__main__":
    main()
