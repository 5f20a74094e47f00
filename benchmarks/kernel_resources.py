"""Compile the fused kernels for GPUs this machine does not have, and print what each variant needs of them.

Triton compiles a kernel anew for each class of its arguments (block sizes picked by row count, an integer equal to 1
or divisible by 16, a dtype), so what a GPU must hold depends on the calls. This script makes the calls: full-size
π0 and π0.5 sampling at the given batch sizes (π0's persistent launch of its layers, `sampling_kernels="persistent"`,
at batch 1) and one π0-FAST decoded token, bf16, on the meta device (no weights),
with triton's driver replaced by one that names the target GPU and every launch turned into a compile
(`JITFunction.run(..., warmup=True)`). Each variant is compiled to the target's machine code by the ptxas that comes
with triton, and gets one row: its shared memory against the most one block may have on that GPU, its registers and
spills (`ptxas -v`). A variant with more shared memory than the GPU has fails at launch ("out of resource: shared
memory"); `--check` exits 1 where one does.

    python benchmarks/kernel_resources.py                       # sm_89 (RTX 4090, L40S) and sm_90 (H100, H200)
    python benchmarks/kernel_resources.py --arch 80,86,87,89,90,120 --batches 1,3,8 --check

Needs triton (with its ptxas) and no GPU; runs on the CPU in about half a minute per target.
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

# The most shared memory one block may have (bytes, cudaDevAttrMaxSharedMemoryPerBlockOptin), per compute capability:
SHARED_PER_BLOCK = {
    80: 166_912,  # A100, A800
    86: 101_376,  # RTX 3090, A6000, A10
    87: 166_912,  # Jetson AGX Orin
    89: 101_376,  # RTX 4090, L4, L40S, RTX 6000 Ada
    90: 232_448,  # H100, H200, GH200
    100: 232_448,  # B200
    120: 101_376,  # RTX 5090, RTX PRO 6000 Blackwell
}


class TargetDriver:
    """Stands in for triton's CUDA driver: it names the target GPU, and nothing is ever launched."""

    def __init__(self, arch: int) -> None:
        from triton.backends.compiler import GPUTarget

        self.target = GPUTarget("cuda", arch, 32)

    def get_current_target(self) -> Any:
        return self.target

    def get_current_device(self) -> int:
        return self.target.arch  # (triton keeps its compiled kernels per device: one per target here)

    def get_current_stream(self, device: int | None = None) -> int:
        return 0

    def get_active_torch_device(self) -> torch.device:
        return torch.device("meta")

    def is_active(self) -> bool:
        return True


def replace_launches(arch: int, launch: Callable[[Any, tuple], None]) -> None:
    """For good: kernels compile for `arch` (`TargetDriver`), and each compiled kernel's launcher is replaced by
    `launch(compiled kernel, the launcher's arguments)`, so that nothing runs (`tests/launch_check.py` records the
    launches, `benchmarks/launch_cost.py` times what comes before them)."""
    import triton
    from triton.compiler.compiler import CompiledKernel

    triton.runtime.driver.set_active(TargetDriver(arch))

    def handles(self: CompiledKernel) -> None:
        if self._run is None:
            self._run = lambda *arguments: launch(self, arguments)
        self.module = self.function = 0

    CompiledKernel._init_handles = handles


def compile_launches(arch: int, batches: list[int]) -> dict[str, tuple[str, Any]]:
    """Every kernel variant that full-size sampling (π0, π0.5 at `batches`; π0's persistent launch at batch 1) and
    π0-FAST decoding launch, compiled for `arch`: {hash: (kernel name, compiled kernel)}."""
    import triton
    from triton.runtime.jit import JITFunction

    from pi0_torch.benchmark import TEXT_TOKENS, decode_step_on_meta, sample_on_meta
    from pi0_torch.inference.layout import InputFacts
    from pi0_torch.models.configuration_pi0 import PI0Config
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig

    compiled: dict[str, tuple[str, Any]] = {}

    def launcher(kernel: JITFunction, grid: Any) -> Any:
        def launch(*args: Any, **kwargs: Any) -> None:
            variant = kernel.run(*args, grid=grid, warmup=True, **kwargs)
            compiled.setdefault(variant.hash, (kernel.fn.__name__, variant))
        return launch

    triton.runtime.driver.set_active(TargetDriver(arch))  # (for good: without a GPU there is no driver to go back to)
    original = JITFunction.__getitem__
    JITFunction.__getitem__ = launcher
    try:
        for preset in ("pi0", "pi05"):
            config = PI0Config.from_preset(preset)
            for batch in batches:
                facts = InputFacts(((True,) * config.num_cameras,) * batch, (TEXT_TOKENS,) * batch, TEXT_TOKENS)
                sample_on_meta(config, facts, config.num_inference_steps, torch.bfloat16, fused=True, count=False)
        # the persistent launch (what "auto" runs eagerly at batch 1-2): π0 at batch 1 (its first step with the state token)
        config = PI0Config.from_preset("pi0")
        facts = InputFacts(((True,) * config.num_cameras,), (TEXT_TOKENS,), TEXT_TOKENS)
        sample_on_meta(config, facts, 1, torch.bfloat16, fused=True, count=False, persistent=True)
        decode_step_on_meta(PI0FastConfig.from_preset("pi0_fast"), fused=True, count=False)
    finally:
        JITFunction.__getitem__ = original
    return compiled


def ptxas_usage(ptx: str, arch: int) -> str:
    """Registers and spills of `ptx` for `arch`, as triton's ptxas reports them."""
    import triton

    ptxas = glob.glob(os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "ptxas*"))[0]
    with tempfile.NamedTemporaryFile("w", suffix=".ptx", delete=False) as file:
        file.write(ptx)
    name = f"sm_{arch}a" if arch >= 90 else f"sm_{arch}"
    try:
        report = subprocess.run([ptxas, "-v", "--gpu-name", name, file.name, "-o", os.devnull], capture_output=True,
                                text=True, check=True).stderr
    finally:
        os.unlink(file.name)
    lines = [line.split("info    :")[-1].strip() for line in report.splitlines()]
    registers = next((line.split("Used ")[1].split(" registers")[0] for line in lines if line.startswith("Used ")), "?")
    spills = next((line.split(", ")[1].split(" bytes")[0] for line in lines if "bytes spill stores" in line), "?")
    return f"{registers:>9s} {spills:>12s}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", default="89,90", help="comma list of compute capabilities, e.g. 80,86,89,90,120")
    parser.add_argument("--batches", default="1,8", help="comma list of sampling batch sizes")
    parser.add_argument("--check", action="store_true", help="exit 1 where a variant needs more shared memory than the GPU has")
    args = parser.parse_args(argv)
    if os.environ.get("TRITON_INTERPRET") == "1":
        parser.error("unset TRITON_INTERPRET: the kernels are compiled here, not interpreted")
    from pi0_torch.kernels import persistent, triton_kernels  # noqa: F401  (compiled kernels, before the next line)

    os.environ["TRITON_INTERPRET"] = "1"  # (only so that the ops take their Triton implementation for meta tensors)
    too_large = 0
    for arch in (int(each) for each in args.arch.split(",")):
        limit = SHARED_PER_BLOCK.get(arch)
        print(f"\nsm_{arch}: {'shared memory per block ' + format(limit, ',') + ' bytes' if limit else 'limit unknown'}")
        print(f"{'kernel':28s} {'block (M, N, K)':>16s} {'warps':>5s} {'stages':>6s} {'shared B':>9s} {'registers':>9s} {'spill stores':>12s}")
        variants = compile_launches(arch, [int(each) for each in args.batches.split(",")])
        for name, variant in sorted(variants.values(), key=lambda each: (each[0], each[1].metadata.shared)):
            names = variant.src.fn.arg_names  # (constants are keyed by their argument's index path)
            constants = {names[key[0]] if isinstance(key, tuple) else key: value for key, value in variant.src.constants.items()}
            block = ", ".join(str(constants[key]) for key in ("BLOCK_M", "BLOCK_N", "BLOCK_K") if key in constants)
            shared = variant.metadata.shared
            fits = limit is None or shared <= limit
            too_large += not fits
            print(f"{name:28s} {block:>16s} {variant.metadata.num_warps:5d} {variant.metadata.num_stages:6d} {shared:9,d} "
                  f"{ptxas_usage(variant.asm['ptx'], arch)}{'' if fits else '  TOO LARGE'}", flush=True)
    return 1 if args.check and too_large else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.exit(main())
