"""What openpi's image augmentation costs in a training step of the shipped demo policy's size (two 48 px cameras,
batch 32): `pi0-torch train`'s own trainer on a small recorded PickPlace dataset, on this machine's CPU.

    .venv/bin/python benchmarks/augmentation_cost.py [--steps 150] [--rounds 3] [--threads 2]

Each round trains `--steps` steps with the augmentation, timing its two calls inside the trainer
(`draw_augmentation` for the batch's keys, then `augment_images`), and the same steps without it (`--no-augment`).
Prints per round the augmentation's time per step, the step times with and without it (wall time of the training
loop over the steps, `train_runtime`), and the augmentation's share of the augmented step.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from pi0_torch.envs.demos import record_demos
from pi0_torch.shipped_policy import demo_policy_dir
from pi0_torch.training import pi0_trainer
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import train_policy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()

    spent: list[float] = []  # seconds in the augmentation's calls, this round
    for name in ("draw_augmentation", "augment_images"):  # (the trainer calls them by these module names)
        def timed(*arguments, _function=getattr(pi0_trainer, name), **options):
            start = time.perf_counter()
            result = _function(*arguments, **options)
            spent.append(time.perf_counter() - start)
            return result
        setattr(pi0_trainer, name, timed)

    with tempfile.TemporaryDirectory() as scratch:
        dataset = Path(scratch) / "pick_place"
        record_demos("pi0_torch/PickPlace-v0", 20, dataset, image_size=48)
        print(f"demo policy, batch 32, two 48 px cameras, CPU, {args.threads} threads, {args.steps} steps a run")
        print("| round | augmentation a step | step with it | step without it | share of the step with it |")
        print("|---|---|---|---|---|")
        for round_index in range(1, args.rounds + 1):
            step_ms, augment_ms = {}, 0.0
            for augment in (True, False):
                spent.clear()
                settings = TrainSettings(dataset=str(dataset), model=str(demo_policy_dir()),
                                         output_dir=str(Path(scratch) / f"run_{round_index}_{augment}"),
                                         max_steps=args.steps, batch_size=32, threads=args.threads, cpu=True,
                                         save_steps=10 * args.steps, logging_steps=10 * args.steps, augment=augment)
                runtime = train_policy(settings)["log_history"][-1]["train_runtime"]  # (the loop's, not the set-up's)
                step_ms[augment] = 1e3 * runtime / args.steps
                augment_ms += 1e3 * sum(spent) / args.steps
            print(f"| {round_index} | {augment_ms:.2f} ms | {step_ms[True]:.1f} ms | {step_ms[False]:.1f} ms | "
                  f"{100 * augment_ms / step_ms[True]:.1f}% |")


if __name__ == "__main__":
    main()
