"""Host time of a fused op's call, launched by triton's `kernel[grid](...)` against launched directly
(`pi0_torch.kernels.launch`), with the launch itself stubbed out: what the host spends before the GPU sees the kernel.

Eager sampling is bound by this host time (about a thousand launches per π0 chunk), so it is measured on the CPU,
where it happens: the kernels are compiled for sm_90 by triton's ptxas (`kernel_resources.TargetDriver`, no GPU
needed), and the compiled kernels' launcher does nothing. Shapes are full-size π0's suffix at batch 1 (50 rows),
bf16. Each op's row: the best of 5 rounds of 3,000 calls. The last two rows: one whole Euler step as eager sampling
runs it (as `FusedSteps.step_` calls its ops: the action tokens, 18 layers of five ops, the Euler update; 92
launches), then the same step under `sampling_kernels="persistent"` (its 18 layers in one launch: 3), each the best
of 5 rounds of 30 steps. Two passes side by side.

    python benchmarks/launch_cost.py
"""

from __future__ import annotations

import contextlib
import os
import sys
import timeit
from pathlib import Path

import torch

ROUNDS, CALLS, STEPS = 5, 3_000, 30


def main() -> int:
    if os.environ.get("TRITON_INTERPRET") == "1":
        print("unset TRITON_INTERPRET: the kernels are compiled here, not interpreted", file=sys.stderr)
        return 2
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import triton
    from kernel_resources import replace_launches

    # (every kernel module imported before TRITON_INTERPRET is set below, so that its kernels compile)
    from pi0_torch.kernels import launch, ops, persistent, triton_kernels as K  # noqa: F401

    if launch.DIRECT_REASON is not None:
        print(f"no direct launches here: {launch.DIRECT_REASON}")
        return 0
    replace_launches(90, lambda compiled, arguments: None)
    os.environ["TRITON_INTERPRET"] = "1"  # (only so that `ops.call` takes the Triton implementations for CPU tensors;
    # the kernels were made by `@triton.jit` at import, so they compile, not interpret)
    bf16 = torch.bfloat16
    x, hidden = torch.randn(50, 1024, dtype=bf16), torch.randn(50, 4096, dtype=bf16)
    gate_up, scale = torch.randn(50, 8192, dtype=bf16), torch.randn(1024, dtype=bf16)
    qkv_w, gate_up_w, down_w = (torch.randn(1024, 2560, dtype=bf16), torch.randn(1024, 8192, dtype=bf16),
                                torch.randn(4096, 1024, dtype=bf16))
    cos, cache = torch.randn(1, 50, 256, dtype=bf16), torch.zeros(1, 880, 256, dtype=bf16)
    query, first, ends = torch.randn(1, 50, 8, 256, dtype=bf16), torch.zeros(1, dtype=torch.long), torch.full((400,), 868)
    calls = {
        "norm_qkv_rope": lambda: K.norm_qkv_rope(x, scale, None, qkv_w, cos, cos, cache, cache, 818, 1e-6),
        "range_attention": lambda: K.range_attention(query, cache, cache, first, ends),
        "matmul_residual_ (down)": lambda: K.matmul_residual_(x, hidden, down_w, None),
        "norm_gate_up_geglu": lambda: K.norm_gate_up_geglu(x, scale, None, gate_up_w, 1e-6),
        "geglu (the prefix's)": lambda: K.geglu(gate_up),
    }
    layers, o_w = 18, torch.randn(2048, 1024, dtype=bf16)  # (one layer's weights for all 18: the host cost is the same)
    tables, x_t = torch.randn(1, 50, 256), torch.randn(1, 50, 32)
    in_w, mlp_w, out_w = torch.randn(32, 1024, dtype=bf16), torch.randn(1024, 1024, dtype=bf16), torch.randn(1024, 32, dtype=bf16)
    caches = [cache] * layers

    def step() -> None:  # (`FusedSteps.step_`'s ops, π0)
        tokens = ops.call(ops.embed_actions, x_t, in_w, scale, mlp_w, scale)
        ops.expert_layers_op_by_op_(tokens, [scale] * layers, [qkv_w] * layers, [o_w] * layers, [scale] * layers,
                                    [gate_up_w] * layers, [down_w] * layers, tables, tables, caches, caches, first,
                                    ends[:50], 818, 1e-6)
        ops.call(ops.norm_linear_euler_, x_t, tokens, scale, scale[:32], out_w, -0.1, 1e-6)

    stacked_scales, stacked_cache = scale.expand(layers, -1), cache.expand(layers, -1, -1, -1)

    def persistent_step() -> None:  # (the same step with `sampling_kernels="persistent"`: its layers in one launch)
        tokens = ops.call(ops.embed_actions, x_t, in_w, scale, mlp_w, scale)
        ops.call(ops.expert_layers_, tokens, stacked_scales, [qkv_w] * layers, [o_w] * layers, stacked_scales,
                 [gate_up_w] * layers, [down_w] * layers, tables, tables, stacked_cache, stacked_cache, first,
                 ends[:50], 818, 1e-6, None, None, None, None)
        ops.call(ops.norm_linear_euler_, x_t, tokens, scale, scale[:32], out_w, -0.1, 1e-6)
    print(f"host µs per call, launch stubbed, triton {triton.__version__}, torch {torch.__version__}")
    print(f"{'op':28s} {'triton run':>11s} {'direct':>8s} {'triton run':>11s} {'direct':>8s}")
    rows = [(name, call, CALLS) for name, call in calls.items()] + [("one Euler step (92 launches)", step, STEPS),
                                                                    ("the step, persistent (3)", persistent_step, STEPS)]
    for name, call, number in rows:
        times = []
        for _ in range(2):
            for direct in (False, True):
                with contextlib.nullcontext() if direct else launch.through_triton():
                    call(), call()  # (the first call of a class compiles, or goes through triton)
                    times.append(min(timeit.repeat(call, number=number, repeat=ROUNDS)) / number * 1e6)
        print(f"{name:28s} " + " ".join(f"{each:{11 if i % 2 == 0 else 8}.1f}" for i, each in enumerate(times)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
