"""`pi0-torch bench --export`: one chunk of the same model, inputs and noise run three ways side by side: the eager
engine (`generate_actions`), the exported core in onnxruntime, and the same compiled by AOTInductor. Each row's
actions are compared with the engine's; the calls alternate (`time_alternating`) so that a busy stretch of a shared
machine falls on all three alike. Prints a table; nothing is asserted.

    pi0-torch bench --export                                      # pi0_medium and pi05_medium, 2 threads, batch 1
    pi0-torch bench --export --presets pi0_small --threads 1 --cameras 1
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pi0_torch.deploy.export import write_onnx
from pi0_torch.deploy.runners import load_runner
from pi0_torch.utils.timing import time_alternating

PROGRAM_INPUTS = ("pixel_values", "image_masks", "input_ids", "attention_mask", "state", "noise")
TEXT_TOKENS = 20  # prompt tokens (as `pi0-torch bench`'s rows)


def bench_export(args: argparse.Namespace, device: torch.device) -> None:
    """The table of `--export` (see the module docstring): per preset and camera count, ms per chunk (median, min,
    max of `--repeats` alternating rounds), the ratio to the eager engine, and the deviation from its actions."""
    from pi0_torch.models.configuration_pi0 import PI0Config
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

    threads = args.threads or 2
    torch.set_num_threads(threads)
    print(f"\nexported sampling on {device} ({threads} threads, float32, batch 1): eager engine, onnxruntime, AOTInductor")
    print(f"{'preset':12s} {'cams':>4s} {'runtime':12s} {'median ms':>10s} {'min':>8s} {'max':>8s} {'x eager':>8s} "
          f"{'max |diff|':>11s} {'export s':>9s}")
    for preset in args.presets:
        config = PI0Config.from_preset(preset)
        torch.manual_seed(0)
        with device:
            model = PI0ForActionGeneration(config).eval()
        for cameras in args.cameras:
            program = model.sampling_program(batch_size=1, text_length=TEXT_TOKENS)
            arguments = program.example_inputs()
            arguments[1][:, cameras:] = False  # (the first `cameras` shown)
            noise = arguments[5]
            started = time.monotonic()
            exported = torch.export.export(program, arguments, strict=False)
            traced = time.monotonic() - started
            arrays = [value.cpu().numpy() for value in arguments]
            with tempfile.TemporaryDirectory() as folder:
                runners, setup = {}, {}
                started = time.monotonic()
                write_onnx(exported, arguments, Path(folder) / "core.onnx", input_names=PROGRAM_INPUTS)
                runners["onnxruntime"] = load_runner(Path(folder) / "core.onnx", "onnx", "cpu", threads, PROGRAM_INPUTS)
                setup["onnxruntime"] = traced + time.monotonic() - started
                started = time.monotonic()
                torch._inductor.aoti_compile_and_package(exported, package_path=str(Path(folder) / "core.pt2"))
                runners["aotinductor"] = load_runner(Path(folder) / "core.pt2", "pt2", device.type)
                setup["aotinductor"] = traced + time.monotonic() - started

                def eager() -> np.ndarray:
                    with torch.inference_mode():
                        return model.generate_actions(*arguments[:5], noise=noise).cpu().numpy()

                calls = {"eager": eager, **{name: (lambda run=run: run(arrays)) for name, run in runners.items()}}
                reference = eager()
                deviations = {name: float(np.abs(call() - reference).max()) for name, call in calls.items()}
                durations = time_alternating(list(calls.values()), device, args.repeats)
            base = statistics.median(durations[0])
            for (name, _), times in zip(calls.items(), durations):
                median = statistics.median(times)
                print(f"{preset:12s} {cameras:4d} {name:12s} {median * 1e3:10.1f} {min(times) * 1e3:8.1f} "
                      f"{max(times) * 1e3:8.1f} {median / base:8.2f} {deviations[name]:11.2e} "
                      f"{setup.get(name, 0.0):9.0f}")

