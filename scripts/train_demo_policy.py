"""Reproduce the committed demo policy `examples/demo_policy/` (what `make demo` loads).

    .venv/bin/python scripts/train_demo_policy.py [--work-dir outputs/demo_training] [--max-steps 6000]

1. writes the synthetic "move to the <color> object" dataset (`pi0_torch.data.synthetic_data.DEMO_DATASET`, LeRobot v3.0
   with mp4 videos) under the work dir;
2. trains the tiny π0 of `DEMO_POLICY_CONFIG` from scratch with the real pipeline (`pi0_torch.training.train_policy`,
   the HF Trainer; recipe `demo_train_settings`), evaluating the loss on the held-out split as it goes;
3. evaluates the result on the demo's held-out scenes (`DEMO_HELDOUT`, the same evaluation `examples/demo.py` runs)
   and copies the model, the processor and `demo_metrics.json` into `examples/demo_policy/`.

Seeded throughout; on the machine it was made on (2 CPU cores, torch 2.13.0, 1 thread) it took 9 minutes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import torch

from pi0_torch import PI0ForActionGeneration
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.data.synthetic_data import DEMO_DATASET, DEMO_HELDOUT, DEMO_STEPS, demo_train_settings, write_synthetic_dataset
from pi0_torch.training.trainer import evaluate_policy, train_policy

REPO = Path(__file__).resolve().parent.parent
POLICY_FILES = ("config.json", "model.safetensors", "processor_config.json", "norm_stats.json", "tokenizer.model")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work-dir", type=Path, default=REPO / "outputs" / "demo_training")
    parser.add_argument("--max-steps", type=int, default=DEMO_STEPS)
    parser.add_argument("--destination", type=Path, default=REPO / "examples" / "demo_policy")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the tiny model gains nothing from more)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    dataset = args.work_dir / "reach"
    if not dataset.exists():
        write_synthetic_dataset(dataset, **DEMO_DATASET)
    run_dir = args.work_dir / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    start = time.time()
    settings = demo_train_settings(dataset, run_dir, args.max_steps, eval_split="heldout", eval_steps=1000)
    result = train_policy(settings)
    minutes = (time.time() - start) / 60

    heldout = args.work_dir / "demo_heldout"
    if heldout.exists():
        shutil.rmtree(heldout)
    write_synthetic_dataset(heldout, **DEMO_HELDOUT)
    model = PI0ForActionGeneration.from_pretrained(run_dir)
    processor = PI0Processor.from_pretrained(run_dir)
    scenes = LeRobotEpisodeDataset(heldout, model.config.action_horizon, progress=False)
    evaluation = evaluate_policy(model, processor, scenes, seed=0, progress=False)
    print("held-out demo scenes:", evaluation.summary())

    args.destination.mkdir(parents=True, exist_ok=True)
    for name in POLICY_FILES:
        shutil.copy2(run_dir / name, args.destination / name)
    metrics = {
        "heldout_frames": len(evaluation.targets),
        "policy_mse": evaluation.mse,
        "baseline_mse": evaluation.baseline_mse,
        "error_ratio": evaluation.error_ratio,
        "train_minutes": round(minutes, 1),
        "max_steps": args.max_steps,
        "train_loss": [[e["step"], round(e["loss"], 4)] for e in result["log_history"] if "loss" in e],
        "heldout_loss": [[e["step"], round(e["eval_loss"], 4)] for e in result["log_history"] if "eval_loss" in e],
        "torch": torch.__version__,
        "threads": args.threads,
    }
    (args.destination / "demo_metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    print(f"wrote {args.destination} ({minutes:.1f} min of training)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
