"""`pi0-torch demo` / `make demo`: the committed tiny π0 policy reaches for the object the instruction names, on
scenes it never saw.

    pi0-torch demo [--policy examples/demo_policy] [--plot outputs/demo_actions.png]

1. loads `examples/demo_policy/` with `PI0ForActionGeneration.from_pretrained` / `PI0Processor.from_pretrained`
   (a ~0.2 M-parameter π0 trained from scratch by `scripts/train_demo_policy.py`);
2. writes 24 new scenes (`pi0_torch.data.synthetic_data.DEMO_HELDOUT`: another seed than the training data, three
   colored discs each, "move to the <color> object") as a LeRobot v3.0 dataset with mp4 video;
3. runs `generate_actions` through the processor on every frame, maps the chunks back to robot units, and prints
   the error against the scripted ground truth next to the mean-action baseline (always predicting the training
   data's mean action) and the figure recorded when the checkpoint was made;
4. writes a PNG: four scenes with the true and predicted effector paths, and their dx/dy chunks.

No training happens here; it runs in a few seconds on a laptop CPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pi0_torch import PI0ForActionGeneration
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.data.synthetic_data import DEMO_HELDOUT, write_synthetic_dataset
from pi0_torch.training.trainer import PolicyEvaluation, evaluate_policy

DEFAULT_POLICY = Path(__file__).resolve().parents[1] / "examples" / "demo_policy"  # in a clone of the repository


def plot(evaluation: PolicyEvaluation, dataset: LeRobotEpisodeDataset, path: Path, scenes: int = 4) -> None:
    """Top row: a scene with the true (green) and predicted (magenta) effector paths of one chunk; below: dx, dy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(3, scenes, figsize=(3.2 * scenes, 8), gridspec_kw={"height_ratios": [1.6, 1, 1]})
    starts = np.flatnonzero(np.asarray([dataset[i]["frame_index"] for i in range(len(dataset))]) == 0)[:scenes]
    for column, index in enumerate(starts):
        sample = dataset[int(index)]
        image = sample["images"][dataset.camera_keys[0]]
        size = image.shape[0]
        to_pixels = lambda xy: (np.asarray(xy) + 1) / 2 * size - 0.5  # noqa: E731  [-1, 1] -> pixel centers
        state = sample["state"]
        axis = axes[0, column]
        axis.imshow(image)
        for actions, color, label in ((evaluation.targets[index], "lime", "true"), (evaluation.predictions[index], "magenta", "predicted")):
            path_xy = to_pixels(np.vstack([state, state + np.cumsum(actions, axis=0)]))
            axis.plot(path_xy[:, 0], path_xy[:, 1], "-o", color=color, markersize=3, linewidth=1.5, label=label)
        axis.set_title(sample["prompt"], fontsize=9)
        axis.set_xticks([]), axis.set_yticks([])
        if column == 0:
            axis.legend(fontsize=8, loc="lower left")
        steps = np.arange(evaluation.targets.shape[1])
        for row, (dim, name) in enumerate(((0, "dx"), (1, "dy")), start=1):
            axis = axes[row, column]
            axis.plot(steps, evaluation.targets[index, :, dim], "-o", color="green", markersize=3, label="true")
            axis.plot(steps, evaluation.predictions[index, :, dim], "--o", color="magenta", markersize=3, label="predicted")
            axis.plot(steps, evaluation.baseline[index, :, dim], ":", color="gray", label="mean action")
            axis.set_ylabel(name), axis.set_xlabel("step in chunk")
            if column == 0 and row == 1:
                axis.legend(fontsize=8)
    figure.suptitle("π0 demo policy on held-out scenes: predicted vs true action chunks")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", type=Path, default=DEFAULT_POLICY, help="the demo policy folder")
    parser.add_argument("--plot", type=Path, default=Path("outputs") / "demo_actions.png")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the committed demo policy on held-out synthetic scenes.")
    add_arguments(parser)
    return run(parser.parse_args(argv))


def run(args: argparse.Namespace) -> int:
    if not (args.policy / "config.json").is_file():
        print(f"error: no demo policy at {args.policy} (pass --policy, e.g. examples/demo_policy of the repository)", file=sys.stderr)
        return 1
    torch.set_num_threads(1)  # a 0.2 M-parameter model: one thread is the fastest
    start = time.time()

    model = PI0ForActionGeneration.from_pretrained(args.policy)
    processor = PI0Processor.from_pretrained(args.policy)
    parameters = sum(p.numel() for p in model.parameters())
    with tempfile.TemporaryDirectory() as scratch:
        scenes = write_synthetic_dataset(Path(scratch) / "heldout", **DEMO_HELDOUT)
        dataset = LeRobotEpisodeDataset(scenes, model.config.action_horizon, progress=False)
        evaluation = evaluate_policy(model, processor, dataset, seed=0, progress=False)
        plot(evaluation, dataset, args.plot)

    recorded = json.loads((args.policy / "demo_metrics.json").read_text()) if (args.policy / "demo_metrics.json").is_file() else None
    episodes = len(dataset.episodes)
    horizon, dims = evaluation.targets.shape[1:]
    print(f"π0 demo policy {args.policy} ({parameters / 1e6:.2f} M parameters)")
    print(f"{episodes} held-out scenes (new layouts, 3 colored discs each), {len(evaluation.targets)} frames, chunks of {horizon} x {dims}")
    print(f"  policy MSE            {evaluation.mse:.3e}")
    print(f"  mean-action baseline  {evaluation.baseline_mse:.3e}   (always the training data's mean action)")
    line = f"  error ratio           {evaluation.error_ratio:.4f}"
    if recorded:
        line += f"   (recorded when the checkpoint was made: {recorded['error_ratio']:.4f})"
    print(line)
    first_step = np.linalg.norm(evaluation.predictions[:, 0] - evaluation.targets[:, 0], axis=-1).mean()
    print(f"  first action: mean error {first_step:.4f} vs mean |action| {np.linalg.norm(evaluation.targets[:, 0], axis=-1).mean():.4f}")
    print(f"wrote {args.plot} ({time.time() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
