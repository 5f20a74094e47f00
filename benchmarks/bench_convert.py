"""Time and peak memory of converting an openpi checkpoint, on a random-weight checkpoint written in openpi's layout.

    python benchmarks/bench_convert.py                      # full-size π0 (3.24 B parameters, ~13 GB on disk)
    python benchmarks/bench_convert.py --size medium        # quick
    python benchmarks/bench_convert.py --chunk-mb 256       # arrays cut along axis 0 into chunks of <= 256 MiB

The checkpoint is generated with tensorstore in a temporary folder (zarr v2 + zstd inside OCDBT, `_METADATA` as
orbax 0.11 writes it; by default one chunk per array, which is what orbax writes for an array saved from one
device; `--chunk-mb` cuts arrays along the stacked-layer axis instead, as a sharded save does), then converted by `conversion/convert_openpi_checkpoint.py` in a child process whose own peak RSS comes from
`wait4`. Generation runs in a child of its own, so this script stays small (Linux carries the parent's RSS into a
child's peak across fork and exec). The import baseline (a child that only imports the converter) is reported too. Needs about 3x the float32 weight size of free disk (checkpoint, output and the
converter's per-layer scratch); everything is deleted at the end unless `--keep`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pi0_torch import PI0Config  # noqa: E402
from pi0_torch.conversion.openpi_weights import expected_openpi_shapes  # noqa: E402
from pi0_torch.conversion.orbax_reader import write_orbax_checkpoint  # noqa: E402

def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def generate(step_dir: Path, config: PI0Config, chunk_bytes: int | None, seed: int) -> int:
    """Write a random-weight openpi checkpoint of `config` into `step_dir`; returns its parameter count."""
    shapes = expected_openpi_shapes(config)
    rng = np.random.default_rng(seed)

    def fill(index: tuple[slice, ...]) -> np.ndarray:
        shape = tuple(s.stop - s.start for s in index)
        return (rng.random(shape, dtype=np.float32) - 0.5) * 0.04

    leaves = {path: (shape, np.float32, fill) for path, shape in shapes.items()}
    write_orbax_checkpoint(step_dir / "params", leaves, chunk_bytes=chunk_bytes)
    stats = {"mean": [0.0] * 8, "std": [1.0] * 8, "q01": [-1.0] * 8, "q99": [1.0] * 8}
    assets = step_dir / "assets" / "bench"
    assets.mkdir(parents=True)
    (assets / "norm_stats.json").write_text(json.dumps({"norm_stats": {"state": stats, "actions": stats}}))
    return sum(math.prod(shape) for shape in shapes.values())


def run_measured(command: list[str]) -> tuple[float, int, str]:
    """Run `command`; its wall time, its own peak RSS in bytes (`wait4` rusage of that child) and its stdout."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        started = time.perf_counter()
        process = subprocess.Popen(command, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(process.pid, 0)
        seconds = time.perf_counter() - started
        process.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0), err.seek(0)
        if process.returncode != 0:
            sys.exit(f"{' '.join(command)} failed:\n{err.read()}")
        return seconds, usage.ru_maxrss * 1024, out.read()  # Linux reports KiB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generate-only", metavar="STEP_DIR", help=argparse.SUPPRESS)  # internal: the generation child
    parser.add_argument("--size", choices=["full", "medium"], default="full")
    parser.add_argument("--variant", choices=["pi0", "pi05"], default="pi0")
    parser.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32", help="output dtype")
    parser.add_argument("--chunk-mb", type=int, default=0, help="chunk size of the generated arrays along axis 0 (0: one chunk per array)")
    parser.add_argument("--workdir", help="where to put the checkpoint and the output (default: a temporary folder)")
    parser.add_argument("--keep", action="store_true", help="keep the generated checkpoint and the output")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    config = PI0Config.from_preset(args.variant if args.size == "full" else f"{args.variant}_medium")
    if args.generate_only:
        print(generate(Path(args.generate_only), config, args.chunk_mb << 20 or None, args.seed))
        return
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench_convert_"))
    workdir.mkdir(parents=True, exist_ok=True)
    step_dir, output_dir = workdir / "ckpt" / "1000", workdir / "converted"
    try:
        generate_s, _, printed = run_measured(
            [sys.executable, __file__, "--generate-only", str(step_dir), "--size", args.size, "--variant", args.variant,
             "--chunk-mb", str(args.chunk_mb), "--seed", str(args.seed)]
        )
        params = int(printed.split()[-1])
        checkpoint_bytes = folder_bytes(step_dir)
        _, baseline_rss, _ = run_measured([sys.executable, "-c", "import pi0_torch.conversion.convert"])
        convert_s, peak_rss, _ = run_measured(
            [sys.executable, str(ROOT / "conversion" / "convert_openpi_checkpoint.py"), "--checkpoint-dir", str(step_dir),
             "--output-dir", str(output_dir), "--dtype", args.dtype, "--no-progress"]
        )
        output_bytes = folder_bytes(output_dir)
        weight_files = sorted(p.name for p in output_dir.glob("*.safetensors"))

        float32_bytes = params * 4
        rows = [
            ("checkpoint", f"{args.variant} {args.size}, {params / 1e9:.3f} B params, "
                           + (f"chunks <= {args.chunk_mb} MiB" if args.chunk_mb else "one chunk per array")),
            ("float32 weight bytes", f"{float32_bytes / 1e9:.2f} GB"),
            ("checkpoint on disk", f"{checkpoint_bytes / 1e9:.2f} GB (generated in {generate_s:.0f} s)"),
            ("output", f"{output_bytes / 1e9:.2f} GB {args.dtype}, {len(weight_files)} weight file(s)"),
            ("convert wall time", f"{convert_s:.1f} s ({float32_bytes / 1e9 / convert_s:.2f} GB/s of float32 weights)"),
            ("convert peak RSS", f"{peak_rss / 1e9:.2f} GB = {peak_rss / float32_bytes:.2f} x the float32 weights "
                                 f"(importing torch + pi0_torch alone: {baseline_rss / 1e9:.2f} GB)"),
        ]
        print("| quantity | value |\n|---|---|")
        for name, value in rows:
            print(f"| {name} | {value} |")
    finally:
        if not args.keep:
            shutil.rmtree(workdir if args.workdir is None else step_dir.parent, ignore_errors=True)
            if args.workdir is not None:
                shutil.rmtree(output_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
