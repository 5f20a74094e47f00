"""Quantized π0 / π0.5 against the same model in float32 and bf16: action error, CPU speed and memory.

    python benchmarks/bench_quantization.py --preset pi0_medium --threads 2          # error and speed per scheme
    python benchmarks/bench_quantization.py --memory /tmp/full/pi0_bfloat16           # a full-size folder: RSS loaded

Error: the actions of one chunk (same inputs, same noise) against float32's, max |difference| / max |action|, for bf16
and every scheme that runs on this machine. The weights are random, scaled so every block is contractive (random
full-size weights amplify rounding ~40x per SigLIP block, which would hide the schemes' own error). Speed: the calls
alternate (`pi0_torch.utils.timing.time_alternating`), median ms. Memory (`--memory`): what the loaded weights take
per scheme (quantized while loading), what the process allocated, and its peak while loading, each in a child
process. Prints tables; nothing is asserted.
"""

from __future__ import annotations

import argparse
import copy
import json
import resource
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
            config = torchao_config(scheme, "cpu", in_features=quantized_widths(folder))
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


def memory(folder: str, schemes: list[str]) -> None:
    """Per scheme, in a child process: the bytes of the loaded model's weights (a quantized tensor's inner tensors:
    its integer data and scales), the process's anonymous resident memory after loading (what it allocated; the
    weights read from the file are page cache until touched), and its peak resident set while loading."""
    print(f"{'weights':12s} {'weights GB':>11s} {'allocated GB':>13s} {'peak RSS while loading GB':>26s}")
    for scheme in schemes:
        script = f"""
import torch
from pi0_torch import PI0ForActionGeneration
from pi0_torch.conversion.quantize import quantized_widths, torchao_config
widths = quantized_widths({folder!r})
kwargs = {{}} if {scheme!r} == "bfloat16" else {{"quantization_config": torchao_config({scheme!r}, "cpu", in_features=widths)}}
model = PI0ForActionGeneration.from_pretrained({folder!r}, dtype=torch.bfloat16, **kwargs)
def size(tensor):
    if type(tensor) in (torch.Tensor, torch.nn.Parameter):
        return tensor.numel() * tensor.element_size()
    names, _ = tensor.__tensor_flatten__()
    return sum(size(getattr(tensor, name)) for name in names)
weights = sum(size(value) for value in model.state_dict().values())
anonymous = [int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("RssAnon:")][0] * 1024
print(weights / 1e9, anonymous / 1e9)
"""
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        lines = result.stdout.strip().splitlines()
        weights, allocated = (float(value) for value in lines[-1].split()) if result.returncode == 0 and lines else (float("nan"),) * 2
        note = "" if peak > before else " (peak of an earlier child)"
        failed = "" if result.returncode == 0 else f"  failed: {(result.stderr.strip().splitlines() or ['?'])[-1][:160]}"
        print(f"{scheme:12s} {weights:11.2f} {allocated:13.2f} {peak / 2**20:26.2f}{note}{failed}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="pi0_medium")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--memory", metavar="FOLDER", help="a model folder to measure loaded quantized (bf16 weights)")
    parser.add_argument("--memory-schemes", default="bfloat16,int8,int4")
    args = parser.parse_args()
    if args.memory:
        memory(args.memory, args.memory_schemes.split(","))
    else:
        accuracy_and_speed(args.preset, args.threads, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
