"""What exporting a full-size π0 / π0.5 costs on this machine: time, peak resident memory and file sizes, per format.

    python benchmarks/bench_export_full_size.py --preset pi0 --formats onnx,pt2 --dtype bfloat16 --work /tmp/full

A model folder of the preset with random weights is written first (bf16 unless `--dtype float32`; a test tokenizer
and unit statistics for its processor). Its weights are scaled down so that every block is contractive: full-size
random weights amplify rounding differences about 40x per SigLIP block, which would make any reordering of float sums
(an exporter's) look like a wrong graph. Each export then runs as `pi0-torch export` in a child process, which
verifies the artifact against `generate_actions` as every export does; its peak resident set size is the child's
`ru_maxrss`. Prints one row per format; nothing is asserted.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

CONTRACTION = 0.5  # every Linear's weights times this: each block's gain below one


def write_model(preset: str, dtype: str, folder: Path) -> None:
    from pi0_torch import PI0Config, PI0ForActionGeneration, PI0Processor
    from pi0_torch.processing.normalization import NormStats
    from pi0_torch.processing.tokenization import build_test_tokenizer

    config = PI0Config.from_preset(preset)
    torch.manual_seed(0)
    model = PI0ForActionGeneration(config).eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.Linear):
                module.weight.mul_(CONTRACTION)
    model = model.to(getattr(torch, dtype))
    model.save_pretrained(folder)
    dims = 8
    stats = {key: NormStats(mean=np.zeros(dims), std=np.ones(dims), q01=-np.ones(dims), q99=np.ones(dims)) for key in ("state", "actions")}
    PI0Processor.from_config(config, build_test_tokenizer(), norm_stats=stats).save_pretrained(folder)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="pi0", help="pi0 or pi05 (the released sizes)")
    parser.add_argument("--formats", default="onnx,pt2")
    parser.add_argument("--dtype", default="bfloat16", choices=("bfloat16", "float32"))
    parser.add_argument("--work", default="/tmp/pi0_export_full_size", help="where the model and the exports go")
    args = parser.parse_args()
    work = Path(args.work)
    model_dir = work / f"{args.preset}_{args.dtype}"
    if not (model_dir / "config.json").is_file():
        started = time.monotonic()
        write_model(args.preset, args.dtype, model_dir)
        print(f"wrote {model_dir} in {time.monotonic() - started:.0f} s", flush=True)
    print(f"{'format':6s} {'dtype':9s} {'seconds':>8s} {'peak RSS GB':>12s} {'files GB':>9s}  result")
    for fmt in args.formats.split(","):
        output = work / f"{args.preset}_{args.dtype}_{fmt}"
        command = [sys.executable, "-m", "pi0_torch.cli", "export", str(model_dir), "--output-dir", str(output),
                   "--format", fmt, "--dtype", args.dtype, "--overwrite"]
        started = time.monotonic()
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        result = subprocess.run(command, capture_output=True, text=True)
        seconds = time.monotonic() - started
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # (KiB; the largest child so far)
        size = sum(path.stat().st_size for path in output.iterdir()) / 1e9 if output.is_dir() else 0.0
        last = (result.stderr.strip().splitlines() or ["(no output)"])[-1]
        note = "" if peak > before else " (peak of an earlier child)"
        print(f"{fmt:6s} {args.dtype:9s} {seconds:8.0f} {peak / 2**20:12.1f} {size:9.2f}  exit {result.returncode}: {last}{note}",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
