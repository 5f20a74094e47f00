"""Where eager sampling's host time goes: a full-size π0 chunk timed with the fused kernels launched directly and by
triton's own `kernel[grid](...)` (`pi0_torch.kernels.launch`), side by side in one process, then one chunk under
cProfile (the functions that took the most host time themselves, and the cumulative time of the package's own).

Eager sampling on a GPU is bound by the host: the H200 run of 2026-11-27 measured 72-131 ms per π0 chunk against
18.8 ms of GPU work. This says which part of the host's work that is.

    python benchmarks/eager_host.py                      # CUDA, full-size π0, bf16, batch 1, 3 cameras
    python benchmarks/eager_host.py --kernels persistent # the same with each step's decoder layers in one launch
    python benchmarks/eager_host.py --device cpu --preset pi0_small --top 10   # a dry run (no fused kernels)
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import pstats
import statistics
import sys

import torch

from pi0_torch.benchmark import example_batch, random_model, seconds
from pi0_torch.kernels import ops
from pi0_torch.models.configuration_pi0 import PI0Config


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--preset", default="pi0")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--top", type=int, default=25, help="rows of each profile table")
    parser.add_argument("--kernels", default="auto", help="sampling_kernels: auto, or persistent (each step's decoder "
                        "layers in one launch)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    config = PI0Config.from_preset(args.preset)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    model = random_model(config, dtype, device)
    inputs = example_batch(config, 3, args.batch, device)
    if config.pi05:
        inputs.pop("state")
    noise = torch.randn(args.batch, config.action_horizon, config.action_dim, device=device)
    model.sampling_kernels = args.kernels

    def chunk() -> torch.Tensor:
        return model.generate_actions(**inputs, noise=noise)

    reason = ops.triton_reason(device)
    if reason is None:
        from pi0_torch.kernels import launch

        reason = launch.DIRECT_REASON
    direct = reason is None
    modes = {"direct launches": contextlib.nullcontext, "triton's launches": launch.through_triton} if direct else {
        "as installed": contextlib.nullcontext}
    print(f"eager generate_actions, {args.preset}, {str(dtype).removeprefix('torch.')}, batch {args.batch}, 3 cameras, "
          f"sampling_kernels={args.kernels!r}, "
          f"on {torch.cuda.get_device_name(device) if device.type == 'cuda' else 'CPU'}"
          + (f" (fused kernels: {reason})" if reason else ""))
    for _ in range(2):
        chunk()  # (the kernels' JIT, the first call's verification of the fused steps)
    times: dict[str, list[float]] = {mode: [] for mode in modes}
    for _ in range(args.repeats):  # (the modes interleaved: the host's drift hits both alike)
        for mode, launches in modes.items():
            with launches():
                times[mode].append(seconds(chunk, device))
    for mode, durations in times.items():
        print(f"{mode:20s} median {statistics.median(durations) * 1e3:8.1f} ms  min {min(durations) * 1e3:8.1f}  "
              f"max {max(durations) * 1e3:8.1f}")

    profiler = cProfile.Profile()
    profiler.enable()
    seconds(chunk, device)
    profiler.disable()
    for title, key, restriction in (("host time in the function itself", "tottime", ()),
                                    ("cumulative host time, pi0_torch's functions", "cumulative", ("pi0_torch",))):
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats(key).print_stats(*restriction, args.top)
        rows = text.getvalue().splitlines()
        start = next((i for i, line in enumerate(rows) if line.lstrip().startswith("ncalls")), 0)
        print(f"\none chunk under cProfile ({'direct launches' if direct else 'as installed'}), "
              f"{title}:")
        print("\n".join(row for row in rows[start:] if row.strip()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
