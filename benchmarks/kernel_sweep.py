"""Tilings of the fused sampling kernels, timed on a CUDA GPU: which block sizes, warps, pipeline stages and key parts
make each full-size kernel of a sampling step fastest (the choice in `pi0_torch.kernels.triton_kernels.blocks` and
`attention_blocks` comes from this script's run on an H200).

Per kernel and shape (π0's action expert, bf16, batch 1 and 8; π0.5's shapes are the same): the tiling in use, then
every candidate (a GEMM's include None: cuBLAS's GEMM with the epilogue kernels around it, what `blocks` chooses from
`CUBLAS_ROWS` rows on, so that each run shows where that pays), each timed as 50 calls in one CUDA graph (median of
10 replays; the GEMMs' weights rotate through copies larger than the L2 cache), with GB/s of weights (GEMMs) or of
keys and values read (attention) and the deviation from the torch reference, fastest first. A tiling that does not
compile or fit is counted with an error.

    python benchmarks/kernel_sweep.py                         # everything, about 2 minutes after the compiles
    python benchmarks/kernel_sweep.py --compile-only --shard 0/4 &   # compile in 4 processes first (triton's disk
    ...                                                       #  cache), e.g. while something else uses the GPU
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import traceback
from collections.abc import Callable, Iterator

import torch

from pi0_torch.benchmark import TEXT_TOKENS, graph_time, step_gemms
from pi0_torch.inference.checks import FUSED_TOLERANCE, relative_deviation
from pi0_torch.kernels import reference, triton_kernels
from pi0_torch.kernels.triton_kernels import AttentionBlocks, Blocks
from pi0_torch.models.configuration_pi0 import PI0Config

DEVICE = torch.device("cuda")


def gemm_tilings(block_m: int) -> Iterator[Blocks]:
    """The fused GEMMs' candidate tilings."""
    for n, k, (warps, stages), splits in itertools.product((16, 32, 64), (64, 128), ((4, 3), (4, 4), (8, 4)), (1, 2, 4, 8)):
        yield Blocks(block_m, n, k, warps, stages, splits)


def attention_tilings(rows: int) -> Iterator[AttentionBlocks]:
    for m, n, (warps, stages), splits in itertools.product((16, 32, 64), (32, 64), ((4, 2), (4, 3), (8, 2)), (1, 2, 4, 8)):
        if m <= max(16, rows):
            yield AttentionBlocks(m, n, warps, stages, splits)


def attention_case(batch: int, tokens: int, slots: int, end: int) -> tuple[Callable[[], object], int, Callable[[], float]]:
    """`range_attention` of `tokens` query tokens (8 heads folded, head dim 256) over keys [0, end) of each sample:
    the call, the bytes of keys and values it reads, and its deviation from the torch reference."""
    generator = torch.Generator(DEVICE).manual_seed(0)
    query = torch.randn(batch, tokens, 8, 256, generator=generator, device=DEVICE).to(torch.bfloat16)
    key, value = (torch.randn(batch, slots, 256, generator=generator, device=DEVICE).to(torch.bfloat16) for _ in range(2))
    first = torch.zeros(batch, dtype=torch.int32, device=DEVICE)
    row_ends = torch.full((tokens,), end, dtype=torch.int32, device=DEVICE)
    arguments = (query, key, value, first, row_ends)

    def deviation() -> float:
        return relative_deviation(triton_kernels.range_attention(*arguments), reference.range_attention(*arguments))

    return (lambda: triton_kernels.range_attention(*arguments)), 2 * batch * end * 256 * 2, deviation


def cases(batches: list[int]) -> Iterator[tuple[str, str, Callable[[], object], int, Callable[[], float], object, list,
                                                tuple[int, ...]]]:
    """(kernel, shape, call, bytes read, deviation, tiling in use, candidate tilings, the arguments its tiling is
    chosen by) of every kernel of a step."""
    config = PI0Config.from_preset("pi0")
    prefix = config.num_cameras * config.tokens_per_image + TEXT_TOKENS
    width, mlp, heads, head_dim = (config.expert_hidden_size, config.expert_intermediate_size, config.num_attention_heads,
                                   config.head_dim)
    shapes = {"qkv": (width, (heads + 2) * head_dim // 2), "o": (heads * head_dim, width), "gate_up": (width, mlp),
              "down": (mlp, width)}  # (K, output columns a tiling spans: pairs for qkv and gate_up)
    for batch in batches:
        rows = batch * config.action_horizon
        for name, gemm in step_gemms(config, batch, DEVICE).items():
            depth, columns = shapes[name]
            current = triton_kernels.blocks(rows, columns, depth)  # (None: cuBLAS's GEMM, epilogue kernels around it)
            yield (name, f"M={rows} K={depth} columns={columns}", gemm.fused, gemm.weight_bytes, gemm.deviation, current,
                   [None, *gemm_tilings(64 if current is None else current.m)], (rows, columns, depth))
        slots = prefix + 1 + config.action_horizon
        for name, tokens, end in (("attn actions", config.action_horizon, slots), ("attn state", 1, prefix + 1)):
            call, size, deviation = attention_case(batch, tokens, slots, end)
            yield (name, f"B={batch} rows={tokens * heads} keys={end}", call, size, deviation,
                   triton_kernels.attention_blocks(tokens * heads, batch, slots), list(attention_tilings(tokens * heads)),
                   (tokens * heads, batch, slots))


def describe(tiling: object) -> str:
    """A tiling in a line; None (from `CUBLAS_ROWS` rows on) is cuBLAS's GEMM with the epilogue kernels around it."""
    return "cuBLAS GEMM + epilogue kernels" if tiling is None else str(tiling)


def with_tiling(kernel: str, tiling: object) -> tuple[str, object]:
    """Which function of triton_kernels chooses this kernel's tiling, and a replacement that returns `tiling`."""
    if kernel.startswith("attn"):
        return "attention_blocks", lambda rows, batch, slots: tiling
    return "blocks", lambda rows, columns, depth: tiling


def measure(kernel: str, call: Callable[[], object], deviation: Callable[[], float], tiling: object,
            compile_only: bool) -> tuple[float, float] | str:
    """(seconds per call, deviation from the reference) of `call` with `tiling`, or why it did not run."""
    name, replacement = with_tiling(kernel, tiling)
    original = getattr(triton_kernels, name)
    setattr(triton_kernels, name, replacement)
    try:
        call()
        torch.cuda.synchronize()
        return (0.0, 0.0) if compile_only else (graph_time(call, DEVICE), deviation())
    except Exception as error:  # (a tiling that does not compile or fit: listed with its error)
        torch.cuda.synchronize()
        return f"{type(error).__name__}: {str(error).splitlines()[0][:60] if str(error) else ''}"
    finally:
        setattr(triton_kernels, name, original)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", default="1,8")
    parser.add_argument("--compile-only", action="store_true", help="only compile every tiling (triton's disk cache)")
    parser.add_argument("--shard", default="0/1", help="i/n: this process takes every n-th tiling from the i-th")
    parser.add_argument("--top", type=int, default=6, help="fastest tilings printed per kernel and shape")
    parser.add_argument("--write", default=None, help="write the fastest tiling of each kernel and shape (within the "
                        "bf16 bound of its reference) to this JSON file")
    parser.add_argument("--bench", action="store_true", help="then time π0 and π0.5 sampling (pi0-torch bench, batch 1 "
                        "and 8, fused) with those tilings in place of the ones in use")
    args = parser.parse_args()
    shard, shards = (int(part) for part in args.shard.split("/"))
    sys.stdout.reconfigure(line_buffering=True)
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}; us per call, 50 calls in a CUDA graph")
    index = 0
    fastest: dict[tuple[str, tuple[int, ...]], object] = {}  # (chooser, its arguments) -> the fastest tiling
    for kernel, shape, call, size, deviation, current, tilings, key in cases([int(b) for b in args.batches.split(",")]):
        results = []
        for tiling in [current, *[t for t in tilings if t != current]]:
            index += 1
            if index % shards != shard and tiling != current:
                continue
            try:
                results.append((tiling, measure(kernel, call, deviation, tiling, args.compile_only)))
            except Exception:  # (a lost CUDA context: nothing after it can run)
                traceback.print_exc()
                return 1
        failed = [result for result in results if isinstance(result[1], str)]
        if args.compile_only:
            print(f"{kernel:13s} {shape:30s} compiled {len(results) - len(failed)}, failed {len(failed)}")
            continue
        timed = sorted((result for result in results if not isinstance(result[1], str)), key=lambda result: result[1][0])
        now = results[0][1]
        print(f"\n{kernel} {shape} ({size / 2**20:.1f} MiB): in use {describe(current)} "
              + (f"{now[0] * 1e6:.1f} us {size / now[0] / 1e9:.0f} GB/s, deviation {now[1]:.1e}" if not isinstance(now, str) else now))
        for tiling, (seconds, off) in timed[: args.top]:
            speedup = f"x{now[0] / seconds:5.2f}" if not isinstance(now, str) else ""
            print(f"    {seconds * 1e6:8.1f} us {size / seconds / 1e9:6.0f} GB/s {speedup}  deviation {off:.1e}  {describe(tiling)}")
        good = [tiling for tiling, (_, off) in timed if off <= FUSED_TOLERANCE[torch.bfloat16]]  # (else wrong, however fast)
        if good:
            fastest[(with_tiling(kernel, None)[0], key)] = good[0]
        worst = max((off for _, (_, off) in timed), default=0.0)
        print(f"    {len(timed)} ran (largest deviation {worst:.1e})"
              + (f", {len(failed)} did not, e.g. {failed[0][0]}: {failed[0][1]}" if failed else ""))
    if args.write and not args.compile_only:
        with open(args.write, "w") as file:
            json.dump([{"chooser": chooser, "arguments": list(key), "tiling": None if tiling is None else tiling._asdict()}
                       for (chooser, key), tiling in fastest.items()], file, indent=1)
    if args.bench and not args.compile_only:
        bench_with(fastest)
    return 0


def bench_with(fastest: dict[tuple[str, tuple[int, ...]], object]) -> None:
    """`pi0-torch bench` of full-size π0 and π0.5 (bf16, 3 cameras, batch 1 and 8, fused steps), the tilings chosen
    by `fastest` where it has the call's arguments, the ones in use elsewhere."""
    from pi0_torch import benchmark

    for chooser in ("blocks", "attention_blocks"):
        original = getattr(triton_kernels, chooser)
        setattr(triton_kernels, chooser, lambda *key, original=original, chooser=chooser:
                fastest[(chooser, key)] if (chooser, key) in fastest else original(*key))
    print("\npi0-torch bench with the fastest tilings above")
    parser = argparse.ArgumentParser()
    benchmark.add_arguments(parser)
    benchmark.run(parser.parse_args(["--device", "cuda", "--presets", "pi0,pi05", "--dtypes", "bfloat16", "--cameras", "3",
                                     "--batches", "1,8", "--kernels", "auto", "--repeats", "10", "--kernel-table", "12"]))


if __name__ == "__main__":
    sys.exit(main())
