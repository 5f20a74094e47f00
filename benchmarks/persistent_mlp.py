"""An experiment for issue 37: the MLP half of an action-expert layer and Euler step as one persistent launch, against
the three fused kernels that run it today.

docs/gpu.md ("Where the next milliseconds are") finds the suffix's 54 µs per layer and step to be the kernels' fixed
latency rather than their bytes. This measures the cure it proposes on the half of a layer that has three launches
today (`matmul_residual_`: o-projection + residual; `norm_gate_up_geglu`; `matmul_residual_`: down-projection +
residual):

- one launch of as many programs as the GPU has multiprocessors; each takes tiles in ticket order from an atomic
  counter: every output tile of the o-projection (all row blocks), then gate/up's, then the down-projection's;
- a tile that reads another phase's output waits until every tile of that phase in its row block has counted itself
  in (spinning on an acquire load of the row block's counter; the producers count themselves in with a release after
  their stores), and reads that output past the L1 cache;
- a tile waits only on tiles handed out before it, whose programs are already running: no deadlock on a GPU, and
  triton's interpreter (which runs the programs one after another) runs it too, though there nothing ever waits:
  it checks the tiles' arithmetic, a GPU (`--check` there) the waiting as well;
- before it waits, a program asks its tile's weights into L2 (`prefetch.global.L2`; not in the interpreter).

The numbers are those of `pi0_torch.kernels.reference` (float32 sums, bf16 outputs), not bit for bit: no split-K here.
π0's layer (no adaRMS gate). Its tiles are those of `pi0_torch.kernels.persistent`, whose launch of a whole step's
layers sampling runs under `sampling_kernels="persistent"`; this launch of half a layer is not used by sampling.

    python benchmarks/persistent_mlp.py --check              # CPU: triton's interpreter, small float32 shapes
    python benchmarks/persistent_mlp.py --compile 90         # CPU: compile the variants for sm_90 (ptxas), print their use
    python benchmarks/persistent_mlp.py --bench              # CUDA: full size, bf16, batch 1 and 8, against today's
"""

from __future__ import annotations

import argparse
import functools
import itertools
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import torch

if "--check" in sys.argv and not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")  # (before triton is imported)

import triton
import triton.language as tl

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pi0_torch.inference.checks import FUSED_TOLERANCE, relative_deviation
from pi0_torch.kernels import reference
from pi0_torch.kernels.persistent import SPINS, _gate_up_tile, _residual_tile
from pi0_torch.kernels.triton_kernels import INTERPRETING, cdiv, dot_dtype


class Tiling(NamedTuple):
    """Output columns per tile of each phase (o-projection, gate/up, down-projection), the reduction block of each,
    rows per tile, warps, pipeline stages, and whether a waiting tile prefetches its weights (never in the
    interpreter)."""

    o: int = 16
    gate_up: int = 32
    down: int = 16
    k: int = 64
    m: int = 64
    warps: int = 4
    stages: int = 3
    prefetch: bool = True


# -- the kernel -----------------------------------------------------------------------------------------------------


@triton.jit
def _persistent_mlp_kernel(
    x_ptr, attended_ptr, o_ptr, scale_ptr, gate_up_ptr, down_ptr, hidden_ptr, state_ptr, watch_ptr,
    M, D, NH, F, stride_xm, stride_am, stride_ok, stride_on, stride_gk, stride_gn, stride_dk, stride_dn, eps,
    BLOCK_M: tl.constexpr, N_O: tl.constexpr, N_GATE_UP: tl.constexpr, N_DOWN: tl.constexpr, BLOCK_K: tl.constexpr,
    DOT: tl.constexpr, PREFETCH: tl.constexpr,
):
    # state: [0] the next ticket, [1 + r] row block r's o-projection tiles done, [1 + R + r] its gate/up tiles done
    row_blocks = tl.cdiv(M, BLOCK_M)
    o_end = row_blocks * tl.cdiv(D, N_O)
    gate_up_end = o_end + row_blocks * tl.cdiv(F, N_GATE_UP)
    total = gate_up_end + row_blocks * tl.cdiv(D, N_DOWN)
    o_counters = state_ptr + 1
    gate_up_counters = o_counters + row_blocks
    ticket = tl.atomic_add(state_ptr, 1)
    while ticket < total:
        if ticket < o_end:
            _residual_tile(ticket, x_ptr, attended_ptr, stride_am, o_ptr, stride_ok, stride_on, o_ptr, gate_up_counters,
                           0, 0, o_counters, watch_ptr, x_ptr, x_ptr, M, D, NH, stride_xm, BLOCK_M, N_O, BLOCK_K, 1,
                           DOT, False, False, True)  # (waits for nothing)
        elif ticket < gate_up_end:
            _gate_up_tile(ticket - o_end, x_ptr, scale_ptr, gate_up_ptr, gate_up_ptr, hidden_ptr, o_counters,
                          gate_up_counters, watch_ptr, x_ptr, x_ptr, M, D, F, stride_xm, stride_gk, stride_gn, eps,
                          BLOCK_M, N_O, N_GATE_UP, BLOCK_K, 1, DOT, PREFETCH, False)  # (unsplit)
        else:
            _residual_tile(ticket - gate_up_end, x_ptr, hidden_ptr, F, down_ptr, stride_dk, stride_dn, down_ptr,
                           gate_up_counters, 1, tl.cdiv(F, N_GATE_UP), gate_up_counters, watch_ptr, x_ptr, x_ptr, M, D,
                           F, stride_xm, BLOCK_M, N_DOWN, BLOCK_K, 1, DOT, PREFETCH, False, False)
        ticket = tl.atomic_add(state_ptr, 1)


def persistent_mlp_(x: torch.Tensor, attended: torch.Tensor, o: torch.Tensor, scale: torch.Tensor,
                    gate_up: torch.Tensor, down: torch.Tensor, eps: float, tiling: Tiling | None = None,
                    programs: int | None = None, launch: Callable[..., Any] | None = None) -> torch.Tensor:
    """`x += attended @ o; x += geglu(norm(x) @ gate_up) @ down` in place, in one launch (module docstring).

    x [M, D], attended [M, N H], o [N H, D], scale [D] (the norm's `1 + weight`), gate_up [D, 2 F], down [F, D]: the
    weights as `[in, out]` views of `nn.Linear` weights. `programs`: the grid (the GPU's multiprocessors by default).
    `launch`: stands in for the kernel's launch (`--compile`)."""
    tiling = tiling or Tiling()
    rows, width = x.shape
    mlp_width = down.shape[0]
    row_blocks = cdiv(rows, tiling.m)
    hidden = x.new_empty(rows, mlp_width)
    state = torch.zeros(1 + 2 * row_blocks, dtype=torch.int32, device=x.device)
    watch = torch.zeros(2, dtype=torch.int32, device=x.device)  # (its own: the experiment fills no NaN; no copy from
    watch[1] = SPINS  # the host, which a CUDA graph's capture, as `--bench` times it, would refuse)
    if programs is None:
        programs = torch.cuda.get_device_properties(x.device).multi_processor_count if x.is_cuda else 4
    arguments = (
        x, attended, o, scale, gate_up, down, hidden, state, watch, rows, width, attended.shape[1], mlp_width, x.stride(0),
        attended.stride(0), o.stride(0), o.stride(1), gate_up.stride(0), gate_up.stride(1), down.stride(0),
        down.stride(1), eps,
    )
    options = {"BLOCK_M": tiling.m, "N_O": tiling.o, "N_GATE_UP": tiling.gate_up, "N_DOWN": tiling.down,
               "BLOCK_K": tiling.k, "DOT": dot_dtype(o.dtype), "PREFETCH": tiling.prefetch and not INTERPRETING, "num_warps": tiling.warps,
               "num_stages": tiling.stages}
    if launch is not None:
        return launch(_persistent_mlp_kernel, (programs,), arguments, options)
    _persistent_mlp_kernel[(programs,)](*arguments, **options)
    return x


def fused_mlp_(x: torch.Tensor, attended: torch.Tensor, o: torch.Tensor, scale: torch.Tensor, gate_up: torch.Tensor,
               down: torch.Tensor, eps: float) -> torch.Tensor:
    """The same through today's ops (three launches on CUDA, cuBLAS from `CUBLAS_ROWS` rows; the reference elsewhere)."""
    from pi0_torch.kernels import ops

    ops.call(ops.matmul_residual_, x, attended, o, None)
    ops.call(ops.matmul_residual_, x, ops.call(ops.norm_gate_up_geglu, x, scale, None, gate_up, eps), down, None)
    return x


def reference_mlp_(x: torch.Tensor, attended: torch.Tensor, o: torch.Tensor, scale: torch.Tensor,
                   gate_up: torch.Tensor, down: torch.Tensor, eps: float) -> torch.Tensor:
    """The torch reference of the same (`pi0_torch.kernels.reference`)."""
    reference.matmul_residual_(x, attended, o, None)
    reference.matmul_residual_(x, reference.norm_gate_up_geglu(x, scale, None, gate_up, eps), down, None)
    return x


# -- check, compile, bench ------------------------------------------------------------------------------------------


def operands(rows: int, width: int, attended_width: int, mlp_width: int, dtype: torch.dtype, device: torch.device,
             seed: int = 0) -> tuple[torch.Tensor, ...]:
    """x, attended, o, scale, gate_up, down: random, the weights as transposed `[out, in]` tensors (the engine's views)."""
    generator = torch.Generator(device).manual_seed(seed)

    def randn(*shape: int) -> torch.Tensor:
        return (torch.randn(*shape, generator=generator, device=device) * shape[-1] ** -0.5).to(dtype)

    return (randn(rows, width) * width ** 0.5, randn(rows, attended_width) * attended_width ** 0.5,
            randn(width, attended_width).t(), 1 + randn(width), randn(2 * mlp_width, width).t(), randn(width, mlp_width).t())


def check(device: torch.device, dtype: torch.dtype, shapes: Iterator[tuple[int, int, int, int]], tolerance: float,
          tilings: list[Tiling]) -> int:
    """The persistent launch against the reference (and, on CUDA, against today's ops) for each shape and tiling."""
    failures = 0
    for (rows, width, attended_width, mlp_width), tiling in itertools.product(shapes, tilings):
        x, *weights = operands(rows, width, attended_width, mlp_width, dtype, device)
        want = reference_mlp_(x.clone(), *weights, 1e-6)
        got = persistent_mlp_(x.clone(), *weights, 1e-6, tiling)
        error = relative_deviation(got, want)
        line = f"rows {rows:4d} width {width:5d} mlp {mlp_width:5d} {tiling}: {error:.2e} against the reference"
        if device.type == "cuda":
            line += f", today's ops {relative_deviation(fused_mlp_(x.clone(), *weights, 1e-6), want):.2e}"
        failures += not error <= tolerance
        print(line + ("" if error <= tolerance else f"  FAILED (bound {tolerance:g})"), flush=True)
    return failures


def compile_for(arch: int, tilings: list[Tiling]) -> int:
    """Compile the full-size variants (batch 1 and 8) for `arch` with triton's ptxas, on meta tensors (no GPU)."""
    def case(batch: int, tiling: Tiling) -> tuple[str, Callable[[Callable[..., Any]], Any]]:
        meta = [tensor.to("meta") for tensor in operands(50 * batch, 1024, 2048, 4096, torch.bfloat16, torch.device("cpu"))]
        return f"batch {batch} {tiling}", lambda launch: persistent_mlp_(*meta, 1e-6, tiling, programs=132, launch=launch)

    return compile_variants(arch, (case(batch, tiling) for batch, tiling in itertools.product((1, 8), tilings)))


def compile_variants(arch: int, cases: Iterable[tuple[str, Callable[[Callable[..., Any]], Any]]]) -> int:
    """Compile each case for `arch` with triton's ptxas, without a GPU: a case is its name and a call that launches its
    kernel with the `launch` it is given, which compiles instead. Prints each one's shared memory, registers and
    spilled bytes; returns how many need more shared memory than one block may have there."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from kernel_resources import SHARED_PER_BLOCK, TargetDriver, ptxas_usage

    triton.runtime.driver.set_active(TargetDriver(arch))
    limit = SHARED_PER_BLOCK.get(arch)
    too_large = 0
    for name, launch_case in cases:
        variant = launch_case(lambda kernel, grid, arguments, options: kernel.run(*arguments, grid=grid, warmup=True,
                                                                                 **options))
        shared = variant.metadata.shared
        too_large += limit is not None and shared > limit
        print(f"sm_{arch} {name}: shared {shared:,d} B, registers / spill stores "
              f"{ptxas_usage(variant.asm['ptx'], arch).split()}", flush=True)
    return too_large


def bench(tilings: list[Tiling]) -> None:
    """Full size (π0's action expert), bf16, batch 1 and 8: today's three ops against the persistent launch, each as 50
    calls in a CUDA graph with the weights rotating through copies larger than the L2 cache."""
    device = torch.device("cuda")
    print(f"{torch.cuda.get_device_name(device)}, torch {torch.__version__}, triton {triton.__version__}; µs per call "
          "(o-projection + residual, norm + gate/up + GeGLU, down-projection + residual), 50 calls in a CUDA graph")
    for batch in (1, 8):
        bench_batch(50 * batch, tilings, device)


def bench_batch(rows: int, tilings: list[Tiling], device: torch.device) -> None:
    from pi0_torch.benchmark import graph_time

    copies = [operands(rows, 1024, 2048, 4096, torch.bfloat16, device, seed) for seed in range(10)]  # 10 x 28 MiB
    turn = itertools.cycle(copies)
    x = copies[0][0].clone()  # (the residual stream: accumulates call after call, as a layer's does)
    want = reference_mlp_(copies[0][0].clone(), *copies[0][1:], 1e-6)

    def run(tiling: Tiling | None) -> None:  # (None: today's ops)
        if tiling is None:
            fused_mlp_(x, *next(turn)[1:], 1e-6)
        else:
            persistent_mlp_(x, *next(turn)[1:], 1e-6, tiling)

    def error(tiling: Tiling | None) -> float:
        first = (copies[0][0].clone(), *copies[0][1:], 1e-6)
        return relative_deviation(fused_mlp_(*first) if tiling is None else persistent_mlp_(*first, tiling), want)

    times = [(tiling, graph_time(functools.partial(run, tiling), device), error(tiling)) for tiling in [None, *tilings]]
    print_times(f"{rows} rows", 2 * (1024 * 2048 + 1024 * 2 * 4096 + 4096 * 1024), times, "today's three launches")


def print_times(title: str, weights_bytes: int, times: list[tuple[Any, float, float]], today: str) -> None:
    """A table of (tiling, seconds, deviation), fastest first: µs, GB/s of `weights_bytes`, the speed-up over today's
    launches (the tiling None, named `today`) and the deviation from the reference."""
    base = next(seconds for tiling, seconds, _ in times if tiling is None)
    print(f"\n{title}, {weights_bytes / 2**20:.0f} MiB of weights")
    for tiling, seconds, deviation_ in sorted(times, key=lambda row: row[1]):
        name = today if tiling is None else f"persistent {tiling}"
        print(f"  {seconds * 1e6:8.1f} us {weights_bytes / seconds / 1e9:6.0f} GB/s x{base / seconds:5.2f}  deviation "
              f"{deviation_:.1e}  {name}", flush=True)


TILINGS = [Tiling(16, 32, 16, 64), Tiling(16, 32, 16, 128), Tiling(16, 32, 16, 128, prefetch=False), Tiling(32, 64, 32, 64),
           Tiling(16, 64, 16, 128, warps=8, stages=4)]


def main() -> int:
    def check_here() -> int:
        if torch.cuda.is_available():
            shapes = iter([(50, 1024, 2048, 4096), (400, 1024, 2048, 4096)])
            return check(torch.device("cuda"), torch.bfloat16, shapes, FUSED_TOLERANCE[torch.bfloat16], TILINGS)
        # (the interpreter: small, float32; rows of one and of three row blocks, the last partial)
        shapes = iter([(50, 64, 128, 96), (150, 48, 64, 80), (1, 32, 64, 32)])
        return check(torch.device("cpu"), torch.float32, shapes, 1e-5, [Tiling(16, 16, 16, 32)])

    return experiment_main(__doc__, check_here, functools.partial(compile_for, tilings=TILINGS),
                           functools.partial(bench, TILINGS))


def experiment_main(doc: str, check_here: Callable[[], int], compile_for_arch: Callable[[int], int],
                    bench_here: Callable[[], None]) -> int:
    """The command line of a persistent-launch experiment (`doc`: its module docstring): `--check` (`check_here`: the
    number of failures), `--compile ARCH`, `--bench`; exits 1 on a failure or a variant too large."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="against the reference: small float32 shapes in triton's "
                        "interpreter without a GPU; full size, bf16, on one")
    parser.add_argument("--compile", type=int, metavar="ARCH", help="compile every tiling for this compute capability")
    parser.add_argument("--bench", action="store_true", help="time it against today's ops (CUDA)")
    args = parser.parse_args()
    failures = check_here() if args.check else 0
    if args.compile:
        failures += compile_for_arch(args.compile)
    if args.bench:
        bench_here()
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
