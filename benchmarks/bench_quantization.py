"""Quantized π0 / π0.5 against the same model in float32 and bf16: action error, CPU speed and memory.

    python benchmarks/bench_quantization.py --preset pi0_medium --threads 2          # error and speed per scheme
    python benchmarks/bench_quantization.py --memory /tmp/full/pi0_bfloat16           # a full-size bf16 folder: memory

Error: the actions of one chunk (same inputs, same noise) against float32's, max |difference| / max |action|, for bf16
and every scheme that runs on this machine. The weights are random, scaled so every block is contractive (random
full-size weights amplify rounding ~40x per SigLIP block, which would hide the schemes' own error). Speed: the calls
alternate (`pi0_torch.utils.timing.time_alternating`), median ms. Memory (`--memory`, a bf16 model folder): per
scheme, `pi0-torch quantize` writes the quantized folder, and a fresh process loads it and samples one chunk: the
folder's size, the weights' bytes, the process's resident set after the chunk and its peak, and the quantizing
process's peak. Prints tables; nothing is asserted.
"""

from __future__ import annotations

import argparse
import copy
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

CONTRACTION = 0.5
CPU_SCHEMES = ("int8", "int8-dynamic", "int4", "fp8-weight")


def contractive_model(preset: str):  # type: ignore[no-untyped-def]
    from pi0_torch import PI0Config, PI0ForActionGeneration

    torch.manual_seed(0)
    model = PI0ForActionGeneration(PI0Config.from_preset(preset)).eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.Linear):
                module.weight.mul_(CONTRACTION)
    return model


def accuracy_and_speed(preset: str, threads: int, repeats: int) -> None:
    from pi0_torch import PI0ForActionGeneration
    from pi0_torch.conversion.quantize import quantized_widths, torchao_config
    from pi0_torch.utils.timing import time_alternating

    torch.set_num_threads(threads)
    model = contractive_model(preset)
    inputs = model.sampling_program(1).example_inputs()
    with tempfile.TemporaryDirectory() as folder:
        model.save_pretrained(folder)
        variants = {"float32": model, "bfloat16": copy.deepcopy(model).to(torch.bfloat16)}
        for scheme in CPU_SCHEMES:
            dtype = torch.bfloat16 if scheme == "fp8-weight" else torch.float32
            config = torchao_config(scheme, "cpu", widths=quantized_widths(folder))
            variants[scheme] = PI0ForActionGeneration.from_pretrained(folder, quantization_config=config, dtype=dtype).eval()
    reference = None
    calls, errors = {}, {}
    for name, variant in variants.items():
        def call(variant=variant):  # type: ignore[no-untyped-def]
            with torch.inference_mode():
                return variant.generate_actions(*inputs[:5], noise=inputs[5])
        actions = call().float()
        reference = actions if reference is None else reference
        errors[name] = float((actions - reference).abs().max() / reference.abs().max())
        calls[name] = call
    durations = time_alternating(list(calls.values()), torch.device("cpu"), repeats)
    base = statistics.median(durations[0])
    print(f"{preset}, {threads} threads, batch 1, {model.config.num_cameras} cameras (error against float32, same noise)")
    print(f"{'weights':14s} {'error':>9s} {'ms':>9s} {'x float32':>9s}")
    for (name, _), times in zip(calls.items(), durations):
        print(f"{name:14s} {errors[name]:9.2e} {statistics.median(times) * 1e3:9.1f} {statistics.median(times) / base:9.2f}")


LOAD_AND_RUN = """
import sys, torch
from pi0_torch import PI0ForActionGeneration
model = PI0ForActionGeneration.from_pretrained(sys.argv[1], dtype="auto").eval()
inputs = model.sampling_program(1).example_inputs()
with torch.inference_mode():
    actions = model.generate_actions(*inputs[:5], noise=inputs[5])
assert torch.isfinite(actions).all()
def size(tensor):  # a quantized tensor: its inner tensors (integer data, scales)
    if type(tensor) in (torch.Tensor, torch.nn.Parameter):
        return tensor.numel() * tensor.element_size()
    names, _ = tensor.__tensor_flatten__()
    return sum(size(getattr(tensor, name)) for name in names)
resident = [int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmRSS:")][0] * 1024
print(sum(size(value) for value in model.state_dict().values()) / 1e9, resident / 1e9)
"""


def child(command: list[str]) -> tuple[int, str, str, float]:
    """Run `command`; its exit status, stdout, stderr and peak resident set in GB (its own, from wait4)."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = process.stdout.read(), process.stderr.read()  # (small outputs: no deadlock)
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return process.returncode, stdout, stderr, usage.ru_maxrss * 1024 / 1e9


def memory(folder: str, schemes: list[str]) -> None:
    """What a robot loading a quantized folder sees, per scheme: `pi0-torch quantize` writes the folder (its peak
    resident set: the machine that quantizes), then another process loads it and samples one chunk (every weight
    touched): the weights' bytes, its resident set after the chunk and its peak. "bfloat16" loads `folder` itself."""
    print(f"{'weights':12s} {'folder GB':>9s} {'weights GB':>10s} {'RSS after a chunk GB':>21s} {'peak GB':>8s} "
          f"{'quantizing peak GB':>19s}")
    with tempfile.TemporaryDirectory() as scratch:
        for scheme in schemes:
            target, quantizing_peak, failed = folder, float("nan"), ""
            if scheme != "bfloat16":
                target = str(Path(scratch) / scheme)
                code, _, stderr, quantizing_peak = child([sys.executable, "-m", "pi0_torch.cli", "quantize", folder,
                                                         "--output-dir", target, "--scheme", scheme])
                failed = "" if code == 0 else f"  quantize failed: {(stderr.strip().splitlines() or ['?'])[-1][:160]}"
            weights = resident = peak = float("nan")
            if not failed:
                code, stdout, stderr, peak = child([sys.executable, "-c", LOAD_AND_RUN, target])
                if code == 0:
                    weights, resident = (float(value) for value in stdout.split())
                else:
                    failed = f"  load failed: {(stderr.strip().splitlines() or ['?'])[-1][:160]}"
            on_disk = sum(path.stat().st_size for path in Path(target).iterdir() if path.is_file()) / 1e9
            print(f"{scheme:12s} {on_disk:9.2f} {weights:10.2f} {resident:21.2f} {peak:8.2f} {quantizing_peak:19.2f}{failed}",
                  flush=True)
            if target != folder:
                shutil.rmtree(target, ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="pi0_medium")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--memory", metavar="FOLDER", help="a model folder to measure loaded quantized (bf16 weights)")
    parser.add_argument("--memory-schemes", default="bfloat16,int8,int4,fp8-weight")
    args = parser.parse_args()
    if args.memory:
        memory(args.memory, args.memory_schemes.split(","))
    else:
        accuracy_and_speed(args.preset, args.threads, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
