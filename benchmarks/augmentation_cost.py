"""What openpi's image augmentation costs in a training step: the shipped demo policy's size (two 48 px cameras,
batch 32) on this machine's CPU (or `--device cuda`), side by side in one process.

    .venv/bin/python benchmarks/augmentation_cost.py [--batch 32] [--repeats 30] [--threads 2] [--device cpu]

Times, interleaved round by round: the augmentation as the trainer runs it (`draw_augmentation` for the batch's keys,
then `augment_images`), and one training step of the model (forward, loss, backward, AdamW step), and prints the
medians and the augmentation's share of the step with it.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pi0_torch.shipped_policy import demo_policy_dir
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.training.augmentation import augment_images, draw_augmentation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    synchronize = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    model = PI0ForActionGeneration.from_pretrained(demo_policy_dir()).to(device).train()
    config = model.config
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-5)
    generator = torch.Generator().manual_seed(0)
    size, cameras, batch = config.image_size, len(config.camera_names), args.batch
    inputs = {
        "pixel_values": torch.rand(batch, cameras, 3, size, size, generator=generator) * 2 - 1,
        "image_masks": torch.ones(batch, cameras, dtype=torch.bool),
        "input_ids": torch.randint(0, config.vocab_size, (batch, config.max_token_len), generator=generator),
        "attention_mask": torch.ones(batch, config.max_token_len, dtype=torch.bool),
        "state": torch.randn(batch, config.action_dim, generator=generator),
        "actions": torch.randn(batch, config.action_horizon, config.action_dim, generator=generator),
    }
    inputs = {name: tensor.to(device) for name, tensor in inputs.items()}

    def augmentation(step: int) -> None:
        draws = draw_augmentation([(0, 2, step, position) for position in range(batch)], size, size)
        augment_images(inputs["pixel_values"], config.camera_names, draws)

    def training_step(step: int) -> None:
        optimizer.zero_grad(set_to_none=True)
        model(**inputs).loss.backward()
        optimizer.step()

    times: dict[str, list[float]] = {"augmentation": [], "training step": []}
    for step in range(args.repeats + 3):
        for name, run in (("augmentation", augmentation), ("training step", training_step)):
            synchronize()
            start = time.perf_counter()
            run(step)
            synchronize()
            if step >= 3:  # (warm-up rounds)
                times[name].append(time.perf_counter() - start)
    augment_ms, step_ms = (statistics.median(times[name]) * 1e3 for name in ("augmentation", "training step"))
    print(f"demo-size batch {batch}, {cameras} cameras of {size} px, {device}, {args.threads} threads, "
          f"medians of {args.repeats} interleaved rounds")
    print("| augmentation (draws + images) | training step without it | share of the step with it |")
    print("|---|---|---|")
    print(f"| {augment_ms:.2f} ms | {step_ms:.2f} ms | {100 * augment_ms / (augment_ms + step_ms):.1f}% |")


if __name__ == "__main__":
    main()
