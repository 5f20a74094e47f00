"""Benchmark: does an attention mask save compute? Dense-mask SDPA vs block-sparse FlexAttention on this machine.

    python benchmarks/bench_masks.py                  # 4096 tokens, 8 heads of 64, compiled FlexAttention
    python benchmarks/bench_masks.py --no-compile     # skip torch.compile (FlexAttention rows are then omitted)

For each pattern it times, forward only, after warm-up:
- SDPA with no mask (the cost of full attention),
- SDPA with the dense bool mask, and with a pre-built additive float mask,
- `masked_attention` (what the model calls: bool -> additive conversion, then SDPA),
- `torch.compile(flex_attention)` with the pattern's `BlockMask` (eager FlexAttention materialises all scores and
  is only a reference implementation, so it is not timed).
It also times RoboVLMs-style chunk-target selection (mask + masked_select) against `generate_chunk_data`.
Prints median / min / max milliseconds and the fraction of 128x128 tiles the block mask skips.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pi0_torch.masks import (  # noqa: E402
    causal_mask_mod,
    claw_mask_mod,
    claw_matrix,
    flex_attention_available,
    generate_chunk_data,
    mask_from_mod,
    masked_attention,
    prefix_lm_mask_mod,
    to_additive_mask,
    to_block_mask,
    window_chunk_mask_mod,
)


def time_interleaved(runs: dict[str, Callable[[], object]], warmup: int, repeats: int) -> dict[str, list[float]]:
    """Milliseconds per call; the methods take turns in every repeat, so load from other processes hits all alike."""
    for fn in runs.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, fn in runs.items():
            start = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - start) * 1e3)
    return times


def patterns(length: int) -> dict[str, tuple[Callable, int | None]]:
    """name -> (mask rule, batch size the rule needs or None)."""
    suffix = 64  # π0-like prefix-LM: a long bidirectional prefix, then a short action block
    valid = torch.ones(1, length, dtype=torch.bool)
    block_flags = torch.zeros(length, dtype=torch.long)
    block_flags[length - suffix] = 1
    return {
        "causal": (causal_mask_mod(), None),
        "claw band k=255": (claw_mask_mod(255), None),
        f"window+chunk {length // 2}+{length // 2}": (window_chunk_mask_mod(length // 2), None),
        f"prefix-LM {length - suffix}+{suffix}": (prefix_lm_mask_mod(valid, block_flags), 1),
    }


def bench_attention(args: argparse.Namespace) -> None:
    generator = torch.Generator().manual_seed(0)
    shape = (args.batch, args.heads, args.length, args.head_dim)
    query, key, value = (torch.randn(shape, generator=generator) for _ in range(3))
    compiled_flex = None
    if args.compile and flex_attention_available():
        from torch.nn.attention.flex_attention import flex_attention

        compiled_flex = torch.compile(flex_attention)

    print(
        f"attention forward, float32, B={args.batch}, heads={args.heads}, L=S={args.length}, head_dim="
        f"{args.head_dim}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{args.warmup} warm-up + {args.repeats} timed runs, methods interleaved, "
        f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
    )
    print("| pattern | elements masked | method | median ms | min ms | max ms | vs no-mask SDPA | tiles skipped |")
    print("|---|---|---|---|---|---|---|---|")
    notes = []
    for name, (rule, rule_batch) in patterns(args.length).items():
        dense = mask_from_mod(rule, args.length, args.length, batch_size=rule_batch)  # [L, S] or [1, L, S]
        dense = dense if dense.dim() == 3 else dense[None]  # [1, L, S]
        additive = to_additive_mask(dense[:, None], query.dtype)  # [1, 1, L, S]
        masked = f"{100 * (1 - dense.float().mean().item()):.1f}%"
        runs = {
            "SDPA, no mask": lambda: F.scaled_dot_product_attention(query, key, value),
            "SDPA, bool mask": lambda: F.scaled_dot_product_attention(query, key, value, attn_mask=dense[:, None]),
            "SDPA, additive mask": lambda: F.scaled_dot_product_attention(query, key, value, attn_mask=additive),
            "masked_attention": lambda: masked_attention(query, key, value, dense),
        }
        skipped = {}
        if compiled_flex is not None:
            start = time.perf_counter()
            block_mask = to_block_mask(rule, args.length, args.length, rule_batch, block_size=args.block_size)
            build_ms = (time.perf_counter() - start) * 1e3
            start = time.perf_counter()
            flex_out = compiled_flex(query, key, value, block_mask=block_mask)
            first_s = time.perf_counter() - start
            error = (flex_out - masked_attention(query, key, value, dense)).abs().max().item()
            notes.append(
                f"{name}: BlockMask built in {build_ms:.0f} ms; first compiled call {first_s:.1f} s; "
                f"max |flex - masked_attention| = {error:.1e}"
            )
            runs["compiled flex_attention"] = lambda: compiled_flex(query, key, value, block_mask=block_mask)
            skipped["compiled flex_attention"] = f"{block_mask.sparsity():.1f}%"

        times = time_interleaved(runs, args.warmup, args.repeats)
        baseline = statistics.median(times["SDPA, no mask"])
        for method, values in times.items():
            median = statistics.median(values)
            print(
                f"| {name} | {masked} | {method} | {median:.1f} | {min(values):.1f} | {max(values):.1f} | "
                f"{baseline / median:.2f}x | {skipped.get(method, '-')} |",
                flush=True,
            )
    for note in notes:
        print(note)


def robovlms_chunk_selection(data: torch.Tensor, window: int, chunk: int) -> torch.Tensor:
    """RoboVLMs' way: repeat the episode per window row, select with the claw mask minus its diagonal."""
    batch, length = data.shape[:2]
    flat = data.reshape(batch, length, -1)
    selection = claw_matrix(length, chunk, dtype=torch.bool)
    selection.fill_diagonal_(False)
    repeated = flat[:, None].expand(batch, window, length, flat.shape[-1]).contiguous()
    chosen = torch.masked_select(repeated, selection[None, :window, :, None].expand_as(repeated))
    return chosen.view(batch, window, chunk, *data.shape[2:])


def bench_chunk_data(args: argparse.Namespace) -> None:
    print("\nchunk targets, window 16 + chunk 10 (RoboVLMs' CALVIN setting), float32")
    print("| data | RoboVLMs mask select, median ms | generate_chunk_data, median ms | speedup |")
    print("|---|---|---|---|")
    for shape in [(128, 26, 7), (4, 26, 3, 64, 64)]:
        data = torch.randn(shape)
        assert torch.equal(robovlms_chunk_selection(data, 16, 10), generate_chunk_data(data, 16, 10))
        runs = {
            "robovlms": lambda: robovlms_chunk_selection(data, 16, 10),
            "ours": lambda: generate_chunk_data(data, 16, 10),
        }
        times = {name: statistics.median(values) for name, values in time_interleaved(runs, 1, args.repeats).items()}
        speedup = times["robovlms"] / times["ours"]
        print(f"| {list(shape)} | {times['robovlms']:.2f} | {times['ours']:.2f} | {speedup:.1f}x |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--length", type=int, default=4096)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--heads", type=int, default=8)
    parser.add_argument("--head-dim", type=int, default=64)
    parser.add_argument("--block-size", type=int, default=128)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--no-compile", dest="compile", action="store_false", help="skip compiled FlexAttention")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", category=UserWarning)
    with torch.inference_mode():
        bench_attention(args)
        bench_chunk_data(args)


if __name__ == "__main__":
    main()
