"""Checks that a direct launch (`pi0_torch.kernels.launch`) makes the same launch as triton's own `kernel[grid](...)`,
on a CPU: run by `tests/test_kernels.py` in a process of its own, without `TRITON_INTERPRET`.

The kernels are compiled for sm_89 by triton's ptxas (`benchmarks/kernel_resources.py`'s stand-in driver), and the
compiled kernels' launcher is replaced by one that records its arguments. Each case is called through triton's path,
then through the direct one (twice: the first call of a class goes through triton); each pair of recorded launches
must be equal: the same compiled kernel (so the same specialization: aligned and unaligned tensors, an integer 1, 16
or 17 are each their own), the same grid, stream, handles, launch metadata, hooks and arguments in the same order.
The cases cover each of the nine kernels, in every variant sampling runs. Last, a kernel given a pre-run hook after
its classes were keyed must launch through triton's `run` again (which runs the hook).
The second direct pass must not enter triton's `JITFunction.run` at all. Prints the number of launches compared.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Any, Callable

import torch


def unaligned(tensor: torch.Tensor) -> torch.Tensor:
    """A copy of `tensor` 2 bytes past a 16-byte boundary (triton compiles such a pointer apart)."""
    flat = torch.empty(tensor.numel() + 1, dtype=tensor.dtype)[1:]
    return flat.view(tensor.shape).copy_(tensor)


def cases(K: Any) -> dict[str, Callable[[], Any]]:
    """Calls of the fused ops (`triton_kernels` as `K`) whose launches are compared, one launch each: the classes
    below, and every variant of the other kernels that sampling runs (the first-call check's cases at full width)."""
    from pi0_torch.inference.checks import op_name, sampling_cases

    generator = torch.Generator().manual_seed(0)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=generator).to(torch.bfloat16)

    rows = 50
    gate_up, qkv, cos, sin = randn(rows, 2 * 4096), randn(rows, 12 * 256), randn(1, rows, 256), randn(1, rows, 256)
    key_cache, value_cache = randn(1, 880, 256), randn(1, 880, 256)
    residual, y, weight, gate = randn(rows, 1024), randn(rows, 4096), randn(4096, 1024), randn(rows, 1024)
    query, first, ends = randn(1, rows, 8, 256), torch.zeros(1, dtype=torch.long), torch.full((rows * 8,), 868)
    return {
        "geglu": lambda: K.geglu(gate_up),
        "geglu, unaligned": lambda: K.geglu(unaligned(gate_up)),
        "rope_cache_write, slot 1": lambda: K.rope_cache_write(qkv, cos, sin, key_cache, value_cache, 1),
        "rope_cache_write, slot 16": lambda: K.rope_cache_write(qkv, cos, sin, key_cache, value_cache, 16),
        "rope_cache_write, slot 17": lambda: K.rope_cache_write(qkv, cos, sin, key_cache, value_cache, 17),
        "matmul_residual_, split-K": lambda: K.matmul_residual_(residual, y, weight, None),
        "matmul_residual_, gated": lambda: K.matmul_residual_(residual, y, weight, gate),
        "range_attention, key parts": lambda: K.range_attention(query, key_cache, value_cache, first, ends),
        **{f"{op_name(op)}, variant {index}": (lambda name=op_name(op), arguments=make(): getattr(K, name)(*arguments))
           for index, (op, make) in enumerate(sampling_cases(torch.device("cpu"), torch.bfloat16, 1024, 8, 256, 4096, 32, 1152))
           if op_name(op) in ("norm_qkv_rope", "norm_gate_up_geglu", "norm_linear_euler_", "embed_actions", "add_layer_norm_")},
    }


def normalized(record: tuple) -> tuple:
    """A recorded launch with tensors as (dtype, shape, strides, address modulo 16), the launch metadata as a dict,
    and an empty chain of launch hooks as None, its launch metadata None (the launcher calls no hook then; a chain
    with nothing in it calls nothing either)."""
    from triton.knobs import HookChain

    compiled, arguments = record
    metadata, *hooks = arguments[6:9]
    enter_hook, exit_hook = (None if isinstance(hook, HookChain) and not hook.calls else hook for hook in hooks)
    plain = tuple(("tensor", each.dtype, tuple(each.shape), each.stride(), each.data_ptr() & 15)
                  if isinstance(each, torch.Tensor) else each for each in arguments)
    return (id(compiled), *plain[:6], None if metadata is None or enter_hook is None else dict(metadata.get()), enter_hook,
            exit_hook, *plain[9:])


def main() -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from kernel_resources import replace_launches

    from pi0_torch.kernels import launch

    if launch.DIRECT_REASON is not None:
        print(f"triton's launch throughout: {launch.DIRECT_REASON}")
        return 0
    from triton import knobs
    from triton.runtime.jit import JITFunction

    recorded: list[tuple] = []
    replace_launches(89, lambda compiled, arguments: recorded.append((compiled, arguments)))
    entered = []
    triton_run = JITFunction.run
    JITFunction.run = lambda self, *args, **kwargs: entered.append(self) or triton_run(self, *args, **kwargs)

    from pi0_torch.kernels import triton_kernels

    calls = cases(triton_kernels)

    def launches(direct: bool) -> list[tuple]:
        recorded.clear()
        entered.clear()
        with contextlib.nullcontext() if direct else launch.through_triton():
            for call in calls.values():
                call()
        assert direct or len(entered) == len(calls), "a launch inside through_triton() did not go through triton's run"
        return [normalized(each) for each in recorded]

    compared = 0
    default_enter = knobs.runtime.launch_enter_hook  # (3.5 to 3.9: an empty `HookChain`)
    for enter in ("triton's default", None, lambda metadata: None):
        knobs.runtime.launch_enter_hook = default_enter if enter == "triton's default" else enter
        through_triton = launches(direct=False)
        first_direct = launches(direct=True)
        second_direct = launches(direct=True)
        assert not entered, f"the second direct pass entered triton's run for {[each.fn.__name__ for each in entered]}"
        assert len(through_triton) == len(calls)
        for name, expected, first_got, got in zip(calls, through_triton, first_direct, second_direct):
            assert first_got == expected, (name, "first direct call", first_got, expected)
            assert got == expected, (name, "direct launch", got, expected)
            compared += 1
        kernels = [each[0] for each in through_triton]
        assert kernels[0] != kernels[1] and len(set(kernels[2:5])) == 3, "triton compiled no variant apart"
        if not callable(enter):  # (the second direct pass's own launches: no hook passed, no metadata made for one)
            assert all(each is None for _, arguments in recorded for each in arguments[6:9]), "a hook for nothing"
    knobs.runtime.launch_enter_hook = default_enter
    geglu = triton_kernels._geglu_kernel  # a kernel with a pre-run hook takes triton's path, which runs the hook
    geglu.kernel.add_pre_run_hook(lambda *args, **kwargs: None)
    entered.clear()
    calls["geglu"]()
    assert entered == [geglu.kernel], "a kernel with a pre-run hook was launched directly"
    print(f"direct launches equal triton's: {compared} launches compared")
    return 0


if __name__ == "__main__":
    sys.exit(main())
