"""What a device can do natively, read from its capabilities: never from a timing, which a loaded machine skews.

bfloat16 runs everywhere in torch, but a CPU without bfloat16 instructions emulates it, many times slower than
float32 (52-66x for a 512 x 512 matmul on an AVX2-only EPYC). Where that matters (the benchmark's rows, the
doctor's timing column) [`bf16_unsupported`] says why, from what torch and the CPU report:

- x86: AVX512-BF16 or AMX (`torch.cpu` reports both; `/proc/cpuinfo`'s `avx512_bf16` / `amx_bf16` flags where this
  torch does not);
- Arm: the `bf16` feature (`/proc/cpuinfo` on Linux, `hw.optional.arm.FEAT_BF16` on macOS);
- CUDA: compute capability 8.0 or later (torch's `is_bf16_supported(including_emulation=False)`).

>>> bf16_unsupported(torch.device("meta")) is None  # nothing runs there
True

[`usable_device`] turns a `--device` / `device=` value into a device this torch can run, or one line saying why not.
"""

from __future__ import annotations

import functools
import platform
import subprocess
from pathlib import Path

import torch

X86 = ("x86_64", "amd64", "i386", "i686")
ARM = ("aarch64", "arm64")


def usable_device(device: str | torch.device | None, name: str = "device") -> torch.device:
    """`device` as a `torch.device` this torch and machine can use (None: CUDA when present, else the CPU); a
    `ValueError` naming `name` otherwise: not a device string (`tpu`), CUDA with a torch built without it or no GPU
    visible, a GPU index past the last one.

    >>> usable_device("cpu")
    device(type='cpu')
    >>> usable_device("tpu", "--device")
    Traceback (most recent call last):
        ...
    ValueError: --device: 'tpu' is not a torch device (cpu, cuda, cuda:1, mps, ...)
    """
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"{name}: {str(device)!r:.40} is not a torch device (cpu, cuda, cuda:1, mps, ...)") from None
    if resolved.type == "cuda":
        if torch.version.cuda is None and not torch.cuda.is_available():
            raise ValueError(f"{name}: {resolved}: this torch ({torch.__version__}) is built without CUDA")
        if not torch.cuda.is_available():
            raise ValueError(f"{name}: {resolved}: no CUDA GPU is visible to this torch ({torch.__version__})")
        if resolved.index is not None and resolved.index >= torch.cuda.device_count():
            raise ValueError(f"{name}: {resolved}: there are {torch.cuda.device_count()} CUDA GPUs")
    elif resolved.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{name}: mps: Apple's Metal backend is not available here")
    elif resolved.type == "meta":  # (tensors with shapes and no data: a model there computes nothing)
        raise ValueError(f"{name}: meta holds tensors without data, so nothing runs there; pi0-torch runs on cpu, cuda "
                         "or mps")
    elif resolved.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"{name}: {resolved.type}: pi0-torch runs on cpu, cuda or mps")
    return resolved


def bf16_unsupported(device: torch.device) -> str | None:
    """Why `device` has no native bfloat16 arithmetic (None when it has, or when it is neither a CPU nor CUDA)."""
    if device.type == "cuda":
        if torch.cuda.is_bf16_supported(including_emulation=False):
            return None
        return f"{torch.cuda.get_device_name(device)} has no native bfloat16 (compute capability 8.0 or later has)"
    if device.type != "cpu" or cpu_has_native_bf16():
        return None
    return (f"this CPU ({platform.machine()}, torch's kernels: {torch.backends.cpu.get_cpu_capability()}) has no "
            "bfloat16 instructions, so bfloat16 is emulated; x86 needs AVX512-BF16 or AMX, Arm the BF16 extension")


@functools.lru_cache(maxsize=None)
def cpu_has_native_bf16() -> bool:
    """Whether this CPU has bfloat16 instructions (see the module docstring)."""
    machine = platform.machine().lower()
    if machine in X86:
        reported = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
        if all(check is not None for check in reported):
            return any(check() for check in reported)
        return bool(_cpu_flags() & {"avx512_bf16", "amx_bf16"})
    if machine in ARM:
        if platform.system() == "Darwin":
            return _sysctl("hw.optional.arm.FEAT_BF16") == "1"
        return "bf16" in _cpu_flags()
    return False


def _cpu_flags() -> set[str]:
    """The feature flags of the first CPU in `/proc/cpuinfo` (`flags` on x86, `Features` on Arm); empty elsewhere."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return set()
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip().lower() in ("flags", "features"):
            return set(value.split())
    return set()


def _sysctl(name: str) -> str:
    try:
        return subprocess.run(["sysctl", "-n", name], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
