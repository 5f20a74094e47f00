"""Closed-loop success and smoothness under inference delay: every execution mode, every delay, with 95% intervals.

    .venv/bin/python benchmarks/bench_closed_loop.py --policy outputs/demo_policy_rtc8 --policy-plain pi0_torch/demo_policy \
        [--envs pi0_torch/Conveyor-v0 pi0_torch/PickPlace-v0] [--delays 0 1 2 4 8] [--episodes 100] \
        [--replan-steps 8] [--noise-scale 0.1] [--rtc-schedules exp ones] [--env-kwargs '{"num_objects": 1}'] \
        [--workers 2] [--output benchmarks/results/closed_loop] [--replot]

Delays are simulated in control steps (`pi0-torch eval --inference-delay`), so the numbers do not depend on this
machine's speed; every cell uses the same held-out seeds. `--policy` and `--policy-plain` (optional) are two policies,
labelled by their config: one trained with `--rtc-max-delay` (`scripts/train_demo_policy.py --rtc-max-delay 8
--destination outputs/demo_policy_rtc8`) runs every mode, `rtc-trained` included; a plain one every mode but
`rtc-trained`. Chunks are sampled from noise of standard deviation `--noise-scale` (default: the demo policy's);
`rtc` runs once per soft-mask schedule of `--rtc-schedules` (default: the paper's `exp`, then `ones`).
`--workers` evaluates cells in that many processes side by side. Prints a markdown table (success [95% CI], jerk at
chunk boundaries / inside chunks), writes `<output>.json` and a plot `<output>.png` (`--replot` redraws it from
the JSON). Also times one chunk of plain, guided and conditioned sampling.

`--served ENV` instead compares one evaluation run locally and through a `pi0-torch serve` process on loopback:
the same seeds must give the same episodes; prints both wall times.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pi0_torch.demo import DEMO_NOISE_SCALE
from pi0_torch.runtime.chunking import EXECUTION_MODES
from pi0_torch.inference.rtc import SCHEDULES
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, RemotePolicy, evaluate

DEFAULT_ENVS = ("pi0_torch/Conveyor-v0", "pi0_torch/PickPlace-v0")


def sampling_times(policy: PI0Policy, repeats: int = 20) -> dict[str, float]:
    """Milliseconds per chunk (batch 1): plain sampling, guided (inference-time RTC) and conditioned (training-time)."""
    model, config = policy.model, policy.model.config
    size = config.image_size
    inputs = policy.prepare({"images": {config.camera_names[0]: np.zeros((size, size, 3), np.uint8)},
                             "state": np.zeros(policy.processor.state_dim, np.float32), "prompt": "warm up"}).inputs
    previous = torch.zeros(1, config.action_horizon, config.action_dim)
    variants = {
        "plain": {},
        "rtc guidance": dict(previous_actions=previous, inference_delay=2, execution_horizon=8),
        "rtc conditioning": dict(previous_actions=previous, inference_delay=2, execution_horizon=8,
                                 rtc_method="conditioning"),
    }
    times = {}
    for name, options in variants.items():
        if name == "rtc conditioning" and config.rtc_max_delay < 2:
            continue
        model.generate_actions(**inputs, **options)  # warm-up
        start = time.perf_counter()
        for _ in range(repeats):
            model.generate_actions(**inputs, **options)
        times[name] = (time.perf_counter() - start) / repeats * 1000
    return times


def served_versus_local(policy_dir: Path, env_id: str, episodes: int, num_envs: int, threads: int,
                        noise_scale: float) -> None:
    """The same evaluation in this process and through `pi0-torch serve` (its own process) on loopback."""
    settings = EvalSettings(env=env_id, episodes=episodes, num_envs=num_envs)
    start = time.perf_counter()
    local = evaluate(LocalPolicy(PI0Policy.from_pretrained(policy_dir, device="cpu", noise_scale=noise_scale)), settings)
    local_s = time.perf_counter() - start
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, "-m", "pi0_torch.cli", "serve", "--model", str(policy_dir), "--port", str(port), "--device", "cpu",
         "--max-batch-size", str(num_envs), "--noise-scale", str(noise_scale), "--log-level", "WARNING"],
        env={**os.environ, "OMP_NUM_THREADS": str(threads)},
    )
    try:
        deadline = time.time() + 300
        while True:
            try:
                remote = RemotePolicy(f"ws://127.0.0.1:{port}", connections=num_envs, timeout=60)
                break
            except ConnectionError:
                if time.time() > deadline or server.poll() is not None:
                    raise
                time.sleep(1)
        start = time.perf_counter()
        served = evaluate(remote, settings)
        served_s = time.perf_counter() - start
        remote.close()
    finally:
        server.terminate()
        server.wait()
    same = [e["success"] for e in local.episodes_detail] == [e["success"] for e in served.episodes_detail]
    print(f"local : {local.summary()} [{local_s:.1f} s]")
    print(f"served: {served.summary()} [{served_s:.1f} s]")
    print(f"same episode outcomes: {same}; served / local wall time: {served_s / local_s:.2f}")


_WORKER: dict = {}


def _load_worker(policy_dirs: dict[str, Path], episodes: int, num_envs: int, replan_steps: int, threads: int,
                 env_kwargs: dict, noise_scale: float) -> None:
    """Per worker process: load every policy once (cells then only evaluate)."""
    torch.set_num_threads(threads)
    _WORKER.update(policies={label: PI0Policy.from_pretrained(path, device="cpu", noise_scale=noise_scale)
                             for label, path in policy_dirs.items()},
                   episodes=episodes, num_envs=num_envs, replan_steps=replan_steps, env_kwargs=env_kwargs)


def _run_cell(cell: tuple[str, str, str, int, str | None]) -> tuple[dict, str, float]:
    """One (policy, env, execution mode, delay, guidance schedule of `rtc`) cell over the held-out seeds: its row of
    the results, its summary line and the seconds it took."""
    label, env_id, mode, delay, schedule = cell
    start = time.time()
    policy = _WORKER["policies"][label]
    policy.rtc_schedule = schedule or "exp"
    result = evaluate(LocalPolicy(policy), EvalSettings(
        env=env_id, episodes=_WORKER["episodes"], num_envs=_WORKER["num_envs"], execution=mode, inference_delay=delay,
        replan_steps=_WORKER["replan_steps"], env_kwargs=_WORKER["env_kwargs"]))
    row = {"policy": label, "env": env_id, "env_kwargs": _WORKER["env_kwargs"], "execution": mode,
           "rtc_schedule": schedule, "inference_delay": delay, "noise_scale": policy.noise_scale,
           "success_rate": result.success_rate, "success_ci95": result.success_ci95,
           "boundary_jerk": result.boundary_jerk, "interior_jerk": result.interior_jerk,
           "mean_steps": result.mean_steps, "episodes": result.episodes}
    return row, f"{result.summary()}{f' ({schedule})' if schedule else ''}", time.time() - start


def _mode_label(row: dict) -> str:
    """`rtc` with the paper's schedule, `rtc (ones)` with another, the other modes as they are."""
    schedule = row.get("rtc_schedule")
    return row["execution"] if schedule in (None, "exp") else f"{row['execution']} ({schedule})"


def _mode_order(label: str) -> tuple[int, str]:
    """Sort key of a `_mode_label`: the execution modes in their order, `rtc` before `rtc (ones)`."""
    return EXECUTION_MODES.index(label.split(" ")[0]), label


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--policy", type=Path, default=Path("pi0_torch/demo_policy"))
    parser.add_argument("--policy-plain", type=Path, help="a second policy (the documented run: the one trained "
                        "without --rtc-max-delay)")
    parser.add_argument("--envs", nargs="+", default=list(DEFAULT_ENVS))
    parser.add_argument("--delays", nargs="+", type=int, default=[0, 1, 2, 4, 8])
    parser.add_argument("--modes", nargs="+", default=list(EXECUTION_MODES), choices=EXECUTION_MODES)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--num-envs", type=int, default=25)
    parser.add_argument("--replan-steps", type=int, default=8)
    parser.add_argument("--rtc-schedules", nargs="+", default=["exp", "ones"], choices=SCHEDULES,
                        help="soft masks of the rtc cells (one row each)")
    parser.add_argument("--noise-scale", type=float, default=DEMO_NOISE_SCALE,
                        help="standard deviation of the noise chunks are sampled from (1: openpi's sampler)")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, metavar="JSON",
                        help='passed to gymnasium.make for every env, e.g. \'{"num_objects": 1}\'')
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/closed_loop"))
    parser.add_argument("--threads", type=int, default=1, help="torch threads per worker process")
    parser.add_argument("--workers", type=int, default=1, help="processes that evaluate cells side by side")
    parser.add_argument("--served", metavar="ENV", help="compare a local and a served evaluation on ENV instead")
    parser.add_argument("--replot", action="store_true", help="only redraw <output>.png from <output>.json")
    args = parser.parse_args(argv)
    if args.replot:
        plot(json.loads(args.output.with_suffix(".json").read_text()), args.delays, args.output.with_suffix(".png"))
        return 0
    torch.set_num_threads(args.threads)
    if args.served:
        served_versus_local(args.policy, args.served, args.episodes, args.num_envs, args.threads, args.noise_scale)
        return 0

    policy_dirs: dict[str, Path] = {}
    jobs = []
    for policy_dir in filter(None, (args.policy, args.policy_plain)):
        policy = PI0Policy.from_pretrained(policy_dir, device="cpu")
        trained_delay = policy.model.config.rtc_max_delay
        label = "rtc-trained policy" if trained_delay > 0 else "plain policy"
        if label in policy_dirs:
            parser.error(f"--policy {args.policy} and --policy-plain {args.policy_plain} are both a {label}; "
                         "compare one trained with --rtc-max-delay and one without")
        policy_dirs[label] = policy_dir
        print(f"{label}: chunk ms (batch 1, CPU, {args.threads} thread):",
              {k: round(v, 1) for k, v in sampling_times(policy).items()})
        jobs += [(label, env_id, mode, delay, schedule) for env_id in args.envs for mode in args.modes
                 for schedule in (args.rtc_schedules if mode == "rtc" else [None]) for delay in args.delays
                 if mode != "rtc-trained" or 0 < trained_delay and delay <= trained_delay]
    options = (policy_dirs, args.episodes, args.num_envs, args.replan_steps, args.threads, args.env_kwargs, args.noise_scale)
    with concurrent.futures.ProcessPoolExecutor(args.workers, initializer=_load_worker, initargs=options) as pool:
        rows = []
        for row, summary, seconds in pool.map(_run_cell, jobs):
            print(f"  {summary} [{seconds:.0f} s]", flush=True)
            rows.append(row)

    print(f"\n| policy | env | execution | {' | '.join(f'd={d}' for d in args.delays)} |")
    print(f"|---|---|---|{'---|' * len(args.delays)}")
    keys = sorted({(r["policy"], r["env"], _mode_label(r)) for r in rows}, key=lambda k: (k[0], k[1], _mode_order(k[2])))
    for key in keys:
        cells = []
        for delay in args.delays:
            match = [r for r in rows if (r["policy"], r["env"], _mode_label(r)) == key and r["inference_delay"] == delay]
            if not match:
                cells.append("-")
                continue
            r = match[0]
            low, high = r["success_ci95"]
            cells.append(f"{100 * r['success_rate']:.0f}% [{100 * low:.0f}, {100 * high:.0f}] · {r['boundary_jerk']:.3f}")
        print(f"| {key[0]} | {key[1].split('/')[1]} | {key[2]} | {' | '.join(cells)} |")

    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    plot(rows, args.delays, args.output.with_suffix(".png"))
    print(f"wrote {args.output.with_suffix('.json')} and {args.output.with_suffix('.png')}")
    return 0


def plot(rows: list[dict], delays: list[int], path: Path) -> None:
    """Success (with 95% intervals) and jerk at chunk boundaries against delay, one column per env."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = sorted({r["env"] for r in rows})
    modes = sorted({_mode_label(r) for r in rows}, key=_mode_order)
    colors = {mode: plt.get_cmap("tab10")(i) for i, mode in enumerate(modes)}  # one color per mode, a line style per policy
    figure, axes = plt.subplots(2, len(envs), figsize=(6 * len(envs), 8), squeeze=False)
    for column, env_id in enumerate(envs):
        for (policy, mode) in sorted({(r["policy"], _mode_label(r)) for r in rows if r["env"] == env_id}):
            series = sorted((r for r in rows if (r["env"], r["policy"], _mode_label(r)) == (env_id, policy, mode)),
                            key=lambda r: r["inference_delay"])
            x = [r["inference_delay"] for r in series]
            label = f"{mode} ({policy})"
            style = "-o" if policy.startswith("rtc-trained") else "--s"
            success = np.array([r["success_rate"] for r in series]) * 100
            low = np.maximum(success - np.array([r["success_ci95"][0] for r in series]) * 100, 0)  # (rounding at 0%)
            high = np.maximum(np.array([r["success_ci95"][1] for r in series]) * 100 - success, 0)
            axes[0, column].errorbar(x, success, yerr=[low, high], fmt=style, capsize=3, label=label, color=colors[mode])
            axes[1, column].plot(x, [r["boundary_jerk"] for r in series], style, label=label, color=colors[mode])
        axes[0, column].set_title(env_id)
        axes[0, column].set_ylabel("success % (95% CI)")
        axes[1, column].set_ylabel("jerk at chunk boundaries")
        axes[1, column].set_xlabel("inference delay d (control steps)")
        for row in (0, 1):
            axes[row, column].set_xticks(delays)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=4, fontsize=8)
    figure.tight_layout(rect=(0, 0.1, 1, 1))
    figure.savefig(path, dpi=100)
    plt.close(figure)


if __name__ == "__main__":
    raise SystemExit(main())
