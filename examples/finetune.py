"""Fine-tune π0 / π0.5 on a LeRobot dataset with the Hugging Face Trainer: the Python form of `pi0-torch train`.

Your robot data (a LeRobot v3.0 or v2.1 folder) and a converted checkpoint (`pi0-torch convert ...`):

    .venv/bin/python examples/finetune.py --dataset ~/data/my_robot --model checkpoints/pi05_base --output-dir runs/my_robot

On several GPUs (or CPU processes) the same script runs under accelerate, the global batch split over processes:

    accelerate launch --multi_gpu --num_processes 4 examples/finetune.py --dataset ... --model ... --output-dir ...

Without `--dataset` it generates the synthetic reaching dataset (in a temporary folder, removed at the end) and
fine-tunes a tiny π0 for a minute, so the whole path (dataset -> Trainer -> checkpoint -> `generate_actions`) can be
tried on a laptop CPU; running it again replaces its own earlier run. The output folder gets the model, its processor
and `loss.png`. An output folder that holds a run on your data is replaced only with `--overwrite`.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from pi0_torch import PI0ForActionGeneration
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.data.synthetic_data import DEMO_POLICY_CONFIG, write_synthetic_dataset
from pi0_torch.training import TrainSettings, train_policy
from pi0_torch.utils.validation import first_line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, help="LeRobot dataset folder (default: generate a synthetic one)")
    parser.add_argument("--model", default="pi0_small", help="converted checkpoint folder (or a preset with --tokenizer)")
    parser.add_argument("--tokenizer", help="PaliGemma SentencePiece model, when --model is a preset")
    parser.add_argument("--output-dir", type=Path, default=Path("outputs") / "finetune")
    parser.add_argument("--max-steps", type=int)
    parser.add_argument("--lora", action="store_true", help="LoRA on the Gemma experts (openpi's low-memory recipe)")
    parser.add_argument("--overwrite", action="store_true", help="replace an output folder that holds an earlier run "
                        "(only one pi0-torch wrote; the synthetic example replaces its own)")
    args = parser.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory(prefix="pi0-finetune-") as scratch:  # holds the synthetic dataset, if any
            return finetune(args, Path(scratch))
    except (ValueError, OSError) as error:  # settings, the dataset, the output folder: one line, as `pi0-torch train`
        print(f"finetune.py: error: {first_line(error)}", file=sys.stderr)
        return 2


def finetune(args: argparse.Namespace, scratch: Path) -> int:
    if args.dataset is None:
        torch.set_num_threads(1)
        args.dataset = scratch / "reach"
        write_synthetic_dataset(args.dataset, num_episodes=120, num_heldout=10, episode_length=12, image_size=56)
        settings = TrainSettings(
            dataset=str(args.dataset), model="pi0_small", output_dir=str(args.output_dir),
            config_overrides=dict(DEMO_POLICY_CONFIG), tokenizer="test", train_split="train",
            max_steps=args.max_steps or 300, batch_size=32, learning_rate=2e-3, warmup_steps=50, end_learning_rate=2e-4,
            logging_steps=25, save_steps=150, ema_decay=0.99, lora=args.lora, progress=True,
            overwrite=True,  # (its own earlier run: a folder pi0-torch wrote, never one with files of others)
        )
    else:
        # openpi's fine-tuning recipe: AdamW(0.9, 0.95, wd 1e-10), clip 1.0, warmup 1k -> 2.5e-5 -> cosine 2.5e-6,
        # global batch 32, norm stats computed from the dataset, the checkpoint's tokenizer
        settings = TrainSettings(
            dataset=str(args.dataset), model=args.model, tokenizer=args.tokenizer, output_dir=str(args.output_dir),
            max_steps=args.max_steps or 30_000, batch_size=32, ema_decay=None if args.lora else 0.99, lora=args.lora,
            bf16=torch.cuda.is_available(), gradient_checkpointing=True, num_workers=4, save_steps=5_000, progress=True,
            overwrite=args.overwrite,
        )
    result = train_policy(settings)

    # the output folder is a regular checkpoint: load it and act on one frame of the data
    model = PI0ForActionGeneration.from_pretrained(result["output_dir"]).eval()
    processor = PI0Processor.from_pretrained(result["output_dir"])
    dataset = LeRobotEpisodeDataset(args.dataset, model.config.action_horizon, progress=False)
    sample = dataset[0]
    camera_map = dict(zip(dataset.camera_keys, model.config.camera_names))
    inputs = processor(images={camera_map[k]: v for k, v in sample["images"].items() if k in camera_map},
                       prompt=sample["prompt"], state=sample["state"])
    actions = model.generate_actions(**inputs, generator=torch.Generator().manual_seed(0))
    robot_actions = processor.postprocess_actions(actions[0].numpy(), state=sample["state"])
    print(f"'{sample['prompt']}'\npredicted first actions:\n{np.round(robot_actions[:3], 3)}\ntrue:\n{np.round(sample['actions'][:3], 3)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
