"""`direct_launch`: the fused kernels launched without triton's per-call binding of their arguments.

`kernel[grid](*args)` spends most of its host time in triton's `JITFunction.run` before the launch itself: it binds
the arguments, specializes each one, turns that into a cache key string and reads its knobs (about 15 of a GEMM op's
26 µs on the development CPU with the launch stubbed; 30-39 µs per op on an H200's host). Eager sampling launches
about a thousand kernels per chunk, and a π0-FAST token about 170, so that host time is what eager waits for.

A `DirectLaunch` keeps the compiled kernel that triton's `run` returned, per class of call, and launches it the way
`run` does: `compiled.run(grid, stream, function, packed metadata, launch metadata, enter hook, exit hook, *every
argument in the kernel's order, constexprs included)`. The first call of each class goes through triton (compiling,
or finding triton's compiled kernel), and so does every call whose class it cannot key.

A class is finer than triton's specialization of a call, so that a kernel compiled for one is never launched for
another: the current device; each leading tensor argument's dtype and address modulo 16 (triton: its dtype, and
whether the address is a multiple of 16); every later argument's value (triton: an integer's width, whether it is 1
or a multiple of 16; a float's type); the keyword arguments by value (the constexprs, `num_warps`, `num_stages`).
The kernels of `triton_kernels` take their tensors first.

What triton's `run` does per call and a direct launch does not: run the kernel's pre-run hooks (a kernel with any
launches through triton's `run`), check that the globals a kernel reads are unchanged, and re-read the debug and instrumentation
knobs (set while a process runs, they reach only kernels compiled after). Launch hooks (profilers such as proton) are
passed on as triton passes them, except that an empty chain of hooks (triton's default since 3.5: a `HookChain` with
nothing in it, which the launcher would call for nothing) is passed as None, and where both are, no launch metadata
is made for them (about 1.6 µs a launch on the development CPU). `PI0_TORCH_TRITON_LAUNCH=triton` in the environment
keeps triton's own launch throughout, as do triton versions outside those whose `run` launches as above (3.5 to 3.9;
`DIRECT_REASON` says why).
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Iterator
from typing import Any

import torch

from pi0_torch.utils.extras import require_extra

require_extra("kernels", "pi0_torch.kernels.launch")
import triton  # noqa: E402

TRITON_VERSIONS = ((3, 5), (3, 9))  # whose `JITFunction.run` launches as the module docstring says
MAX_CLASSES = 4_096  # classes kept per kernel (integers are keyed by value: each new batch or prompt length is one)


def _direct_reason() -> str | None:
    if os.environ.get("PI0_TORCH_TRITON_LAUNCH") == "triton":
        return "PI0_TORCH_TRITON_LAUNCH=triton"
    version = tuple(int(part) for part in triton.__version__.split(".")[:2])
    if not TRITON_VERSIONS[0] <= version <= TRITON_VERSIONS[1]:
        first, last = (".".join(map(str, each)) for each in TRITON_VERSIONS)
        return f"triton {triton.__version__}: direct launches are written for triton {first} to {last}"
    return None


DIRECT_REASON: str | None = _direct_reason()  # why kernels launch through triton's `run` (None: directly)

if DIRECT_REASON is None:
    from triton import knobs
    from triton.compiler.compiler import CompiledKernel
    from triton.knobs import HookChain
    from triton.runtime.driver import driver
    from triton.runtime.jit import JITFunction


class DirectLaunch:
    """A `@triton.jit` kernel launched as `kernel[grid](*args, **kwargs)`, directly where it can (module docstring).
    Under `TRITON_INTERPRET=1` (an interpreted kernel) or where `DIRECT_REASON` is set, triton's `kernel[grid]`."""

    def __init__(self, kernel: Any) -> None:
        self.kernel = kernel
        self.direct = DIRECT_REASON is None and isinstance(kernel, JITFunction)
        self.names = tuple(param.name for param in kernel.params) if self.direct else ()
        self.tensors = 0  # how many arguments lead as tensors: set by the first call
        self.launches: dict[tuple, tuple[Any, tuple[str, ...]]] = {}  # class -> (compiled kernel, keyword names)

    def __getitem__(self, grid: tuple[int, ...]) -> Any:
        if not self.direct or callable(grid):
            return self.kernel[grid]
        return functools.partial(self._launch, grid)

    def _key(self, device: int, args: tuple, kwargs: dict[str, Any]) -> tuple:
        return (device, *[(each.dtype, each.data_ptr() & 15) for each in args[: self.tensors]], *args[self.tensors :],
                *kwargs.items())

    def _launch(self, grid: tuple[int, ...], *args: Any, **kwargs: Any) -> Any:
        device = driver.active.get_current_device()
        try:  # (KeyError: a new class; the others: a call it cannot key, e.g. no tensor where the first call had one)
            compiled, keywords = self.launches[self._key(device, args, kwargs)]
        except (KeyError, AttributeError, TypeError, RuntimeError):
            return self._through_triton(grid, device, args, kwargs)
        if self.kernel.pre_run_hooks:  # (added since this class was keyed: triton runs them)
            return self._through_triton(grid, device, args, kwargs)
        stream = driver.active.get_current_stream(device)
        values = (*args, *[kwargs[name] for name in keywords])
        grid_x, grid_y, grid_z = (*grid, 1, 1)[:3]
        enter_hook, exit_hook = _hook(knobs.runtime.launch_enter_hook), _hook(knobs.runtime.launch_exit_hook)
        metadata = None if enter_hook is exit_hook is None else compiled.launch_metadata(grid, stream, *values)
        compiled.run(grid_x, grid_y, grid_z, stream, compiled.function, compiled.packed_metadata, metadata, enter_hook,
                     exit_hook, *values)
        return compiled

    def _through_triton(self, grid: tuple[int, ...], device: int, args: tuple, kwargs: dict[str, Any]) -> Any:
        compiled = self.kernel[grid](*args, **kwargs)
        if not self.launches:
            self.tensors = next((i for i, each in enumerate(args) if not isinstance(each, torch.Tensor)), len(args))
        keywords = self.names[len(args):]
        keyable = (
            isinstance(compiled, CompiledKernel) and len(self.launches) < MAX_CLASSES
            and all(isinstance(each, torch.Tensor) for each in args[: self.tensors])
            and all(each is None or type(each) in (bool, int, float) for each in args[self.tensors :])
            and set(keywords) <= kwargs.keys()
        )
        if keyable:
            try:
                self.launches[self._key(device, args, kwargs)] = (compiled, keywords)
            except (TypeError, RuntimeError):  # (an unhashable keyword argument: this class keeps triton's path)
                pass
        return compiled


def _hook(hook: Any) -> Any:
    """A launch hook as the launcher should get it: None for an empty `HookChain` (the launcher skips None; it would
    call an empty chain, with launch metadata made for it, for nothing)."""
    return None if isinstance(hook, HookChain) and not hook.calls else hook


LAUNCHERS: list[DirectLaunch] = []  # every kernel `direct_launch` decorated


def direct_launch(kernel: Any) -> DirectLaunch:
    """Decorator over `@triton.jit`: launch the kernel directly where it can (see the module docstring)."""
    LAUNCHERS.append(DirectLaunch(kernel))
    return LAUNCHERS[-1]


@contextlib.contextmanager
def through_triton() -> Iterator[None]:
    """Every kernel launched by triton's own `kernel[grid](...)` while inside (to compare with direct launches)."""
    saved = [(launcher, launcher.direct) for launcher in LAUNCHERS]
    for launcher, _ in saved:
        launcher.direct = False
    try:
        yield
    finally:
        for launcher, direct in saved:
            launcher.direct = direct


def launch_mode() -> str:
    """How the kernels launch, for a report line: "direct launches", or triton's and why."""
    return "direct launches" if DIRECT_REASON is None else f"triton's launches ({DIRECT_REASON})"
