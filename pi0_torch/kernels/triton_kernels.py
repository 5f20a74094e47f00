"""Triton kernels of sampling: five launches per decoder layer of a step instead of about twenty, and fewer around the
prefix pass's GEMMs.

Each kernel computes what its namesake in `pi0_torch.kernels.reference` computes:

- `norm_qkv_rope`: RMSNorm folded into the q/k/v GEMM (the row's `rsqrt(mean(x^2) + eps)` is accumulated beside the
  dot product and applied to the accumulator: it is one scalar per row), RoPE and the k/v cache write in its epilogue;
- `norm_gate_up_geglu`: RMSNorm folded into the gate/up GEMM, `gelu_tanh(gate) * up` in its epilogue;
- `matmul_residual_`: the o- or down-projection with the residual (and π0.5's gate) added in its epilogue, in place;
- `range_attention`: attention of the folded query heads over each token's key range (no mask), one kv head; where
  the samples are few the keys are cut into parts (more programs over them), combined in the same launch;
- `norm_linear_euler_`: the final norm, `action_out_proj` and the Euler update of `x_t`, in one;
- `embed_actions`: the action tokens of a step from `x_t` (π0: both GEMMs of the action/time MLP and the SiLU between
  them; the hidden row block is computed per column block, cheap where it is `x_t`'s 32 action dims deep);
- `rope_cache_write` and `geglu`: the elementwise work around the prefix pass's GEMMs (which stay cuBLAS's: at 800
  rows and more they are compute-bound, and cuBLAS is near peak there), around π0-FAST's decoding GEMMs, and around
  the step's own GEMMs from `CUBLAS_ROWS` rows on (large batches, see `blocks`);
- `add_layer_norm_`: SigLIP's residual add and the LayerNorm after it, in one pass over the rows.

A paired GEMM (RoPE, GeGLU) gives each program two column sets, `c` and `c + half`, so that both halves a rotation or
a GeGLU combines are in its accumulators. Accumulation is float32; the dot's operands are `dot_dtype`, the weights'
dtype on a GPU. Under `TRITON_INTERPRET=1` (the CPU tests) they are float32: the interpreter's bf16 `tl.dot` is wrong
(about 3e10 off on a 16 x 16 product with triton 3.9), its bf16 loads, stores and casts are right.

Only `tl.load` / `tl.store` (with a cache modifier) / `tl.dot` (with its input precision) / `tl.where` / `tl.exp` /
`tl.sqrt` / reductions / `tl.atomic_add` / `tl.debug_barrier` are used, all in the triton that torch 2.10's CUDA
wheels pin (3.6; every variant also compiles with 3.2). Tilings come from `blocks`, `narrow_blocks` and
`attention_blocks`; each kernel launches through `pi0_torch.kernels.launch.direct_launch`.
"""

from __future__ import annotations

import functools
import os
from typing import NamedTuple

import torch

from pi0_torch.kernels import reference
from pi0_torch.utils.extras import require_extra

require_extra("kernels", "pi0_torch.kernels.triton_kernels")
import triton  # noqa: E402
import triton.language as tl  # noqa: E402

from pi0_torch.kernels.launch import direct_launch  # noqa: E402

INTERPRETING = os.environ.get("TRITON_INTERPRET") == "1"

_DOT_DTYPES = {torch.bfloat16: tl.bfloat16, torch.float16: tl.float16, torch.float32: tl.float32}


def dot_dtype(dtype: torch.dtype) -> tl.dtype:
    """The operand dtype of `tl.dot` for weights of `dtype`: theirs on a GPU, float32 in the interpreter."""
    return tl.float32 if INTERPRETING else _DOT_DTYPES[dtype]


def cdiv(a: int, b: int) -> int:
    """`ceil(a / b)` of host integers. (`triton.cdiv` and `triton.next_power_of_2` are constexpr functions, about
    3.6 µs of host time per call on the development CPU: the two of a grid were a third of a launcher's host time.)"""
    return -(-a // b)


def next_power_of_2(n: int) -> int:
    """The smallest power of two >= `n` (>= 1), of a host integer (see `cdiv`)."""
    return 1 << max(n - 1, 0).bit_length()


class Blocks(NamedTuple):
    """A GEMM kernel's tiling: rows, columns and depth per block, triton's warps and pipeline stages, and into how
    many consecutive parts of the reduction (K) the programs of one output tile are cut (split-K: a skinny GEMM's
    few output tiles then still spread over every multiprocessor)."""

    m: int
    n: int
    k: int
    warps: int = 4
    stages: int = 3
    splits: int = 1


CUBLAS_ROWS = 256  # from this many rows on the GEMM ops run cuBLAS's GEMM, their epilogues in kernels of their own


def blocks(rows: int, columns: int, depth: int) -> Blocks | None:
    """The tiling of a GEMM with `rows` x `columns` outputs, `depth` deep (measured on an H200 with
    `benchmarks/kernel_sweep.py`, the weights read from memory as in a step, not from L2; see docs/gpu.md), or None
    from `CUBLAS_ROWS` rows on (π0 at batch 6 and more): there the GEMM is cuBLAS's and the norm and the epilogue
    run in kernels of their own (`rope_cache_write`, `geglu`; the residual add in cuBLAS's `addmm_`). Measured on an
    H200 at 400 rows, weights from memory: cuBLAS's q/k/v GEMM took 6.7 µs against 24.6 fused, gate/up 12.1 against
    46.7, o 6.6 against 8.6, down 11.0 against 15.8; at 50 rows the fused kernels are about as fast as cuBLAS with
    kernels around it, in fewer launches. Between 50 and 400 rows it is not measured.

    A skinny GEMM's cost is reading its weights, so what matters is how many bytes are in flight: 64-row blocks (the
    suffix's 50 rows of a sample in one), 4 pipeline stages, 128 deep where the reduction is at least twice the
    output width (o- and down-projections), and about 128 programs: where the output tiles are fewer, split-K cuts
    each tile's reduction into parts (`splits`, a power of two up to 8). Few rows (π0's state token) keep the small
    blocks. With 4 stages a tiling takes at most 96 KiB of shared memory on sm_80/86/89/120 (128 KiB on sm_90),
    within what a block may have on each (`benchmarks/kernel_resources.py`; `make test` checks sm_89)."""
    return None if rows >= CUBLAS_ROWS else _fused_blocks(rows, columns, depth)


@functools.lru_cache(maxsize=None)
def _fused_blocks(rows: int, columns: int, depth: int) -> Blocks:
    """`blocks` below `CUBLAS_ROWS` rows (kept per shape: every launch asks)."""
    if rows <= 32:
        return narrow_blocks(rows, columns)
    deep = depth >= 2 * columns
    if rows <= 64:
        block_n, block_k, warps, stages = (32, 128, 8, 4) if deep else (64, 64, 4, 3)
    else:
        block_n, block_k, warps, stages = 64, 128 if deep else 64, 4, 4
    tiles = cdiv(rows, 64) * cdiv(columns, block_n)
    splits = 1
    while splits < 8 and tiles * splits * 2 <= 128:
        splits *= 2
    return Blocks(64, block_n, block_k, warps, stages, splits)


@functools.lru_cache(maxsize=None)
def narrow_blocks(rows: int, columns: int) -> Blocks:
    """The tiling of a GEMM kernel without split-K (`embed_actions`, `norm_linear_euler_`) and of few rows: narrow
    column blocks, so that its few output tiles still make many programs (on an H200 the action embedding took
    22 µs so and 34 µs in `blocks`' 64 columns)."""
    return Blocks(16 if rows <= 16 else 32 if rows <= 32 else 64, 16 if columns <= 2048 else 32 if columns <= 8192 else 64, 64)


# -- the shared main loop and split-K -----------------------------------------------------------------------------------


@triton.jit
def _matmul_tiles(
    x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, columns, second, M, k_start, k_stop, N,
    BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr, NORM: tl.constexpr, PAIRED: tl.constexpr,
    DOT: tl.constexpr, X_CACHE: tl.constexpr,
):
    """`x[rows, k_start:k_stop] @ w[k_start:k_stop, columns]` in float32 `[BLOCK_M, BLOCK_N]`, and with PAIRED the
    same over the columns `columns + second` (read in the same pass over `x`; zeros without). With NORM, `x` is
    scaled by `scale` first and each row's sum of squares of `x` comes back too (for the RMSNorm applied
    afterwards; zeros without NORM). The dot is exact float32 ("ieee", not tf32) where its operands are float32.
    X_CACHE is the cache modifier of `x`'s loads: "" (the default), or ".cg" (past L1) where `x` was written by
    another program of the same launch."""
    acc = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
    acc_second = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
    squares = tl.zeros((BLOCK_M,), dtype=tl.float32)
    row_ok = rows < M
    column_ok = columns < N
    for k0 in range(k_start, k_stop, BLOCK_K):
        ks = k0 + tl.arange(0, BLOCK_K)
        k_ok = ks < k_stop
        x = tl.load(x_ptr + rows[:, None] * stride_xm + ks[None, :], mask=row_ok[:, None] & k_ok[None, :], other=0.0,
                    cache_modifier=X_CACHE).to(tl.float32)
        if NORM:
            squares += tl.sum(x * x, axis=1)
            x = x * tl.load(scale_ptr + ks, mask=k_ok, other=0.0).to(tl.float32)[None, :]
        x = x.to(DOT)
        w_mask = k_ok[:, None] & column_ok[None, :]
        w = tl.load(w_ptr + ks[:, None] * stride_wk + columns[None, :] * stride_wn, mask=w_mask, other=0.0)
        acc += tl.dot(x, w.to(DOT), input_precision="ieee")
        if PAIRED:
            w = tl.load(w_ptr + ks[:, None] * stride_wk + (columns + second)[None, :] * stride_wn, mask=w_mask, other=0.0)
            acc_second += tl.dot(x, w.to(DOT), input_precision="ieee")
    return acc, acc_second, squares


@triton.jit
def _split_matmul(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, columns, second, M, K, N, written,
                  workspace_ptr, counter_ptr, k_split, splits, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr,
                  BLOCK_K: tl.constexpr, NORM: tl.constexpr, PAIRED: tl.constexpr, DOT: tl.constexpr,
                  SPLIT: tl.constexpr):
    """`_matmul_tiles` of a launch's program: without SPLIT over all K; with SPLIT over part `program_id(2)` of
    `k_split` columns of the output tile of grid axes 0 and 1, the parts summed by the last to arrive (`_sum_splits`).
    Returns the sums and the bound of the columns this program writes: `written`, or 0 where another part sums."""
    if SPLIT:
        k_start = tl.program_id(2) * k_split
        k_stop = tl.minimum(k_start + k_split, K)
    else:
        k_start, k_stop = 0, K
    acc, acc_second, squares = _matmul_tiles(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, columns,
                                             second, M, k_start, k_stop, N, BLOCK_M, BLOCK_N, BLOCK_K, NORM, PAIRED,
                                             DOT, "")
    if SPLIT:
        acc, acc_second, squares, last = _sum_splits(acc, acc_second, squares, workspace_ptr, counter_ptr,
                                                     tl.program_id(0) * tl.num_programs(1) + tl.program_id(1),
                                                     tl.program_id(2), splits, BLOCK_M, BLOCK_N, PAIRED, NORM)
        written = tl.where(last, written, 0)
    return acc, acc_second, squares, written


@triton.jit
def _sum_splits(acc, acc_second, squares, workspace_ptr, counter_ptr, tile, split, splits,
                BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, PAIRED: tl.constexpr, NORM: tl.constexpr):
    """Split-K's reduction, in the same launch: part `split` of output tile `tile`. Each part stores its partial sums
    in `workspace` and counts itself in on the tile's counter (after a barrier, so that every thread's stores come
    first; acquire-release at GPU scope). The part that arrives last adds the parts up in split order (the same
    sums whichever arrives last: deterministic), reading past the L1 cache, and puts the counter back to 0 for the
    next launch. Returns the sums and whether this part is the last (only it writes the output)."""
    size: tl.constexpr = 2 * BLOCK_M * BLOCK_N + BLOCK_M  # per part: acc, acc_second, squares
    part = tl.arange(0, BLOCK_M)[:, None] * BLOCK_N + tl.arange(0, BLOCK_N)[None, :]
    rows = tl.arange(0, BLOCK_M)
    mine = workspace_ptr + (tile * splits + split) * size
    tl.store(mine + part, acc)
    if PAIRED:
        tl.store(mine + BLOCK_M * BLOCK_N + part, acc_second)
    if NORM:
        tl.store(mine + 2 * BLOCK_M * BLOCK_N + rows, squares)
    tl.debug_barrier()
    last = tl.atomic_add(counter_ptr + tile, 1, sem="acq_rel") == splits - 1
    tl.atomic_add(counter_ptr + tile, tl.where(last, -splits, 0), sem="relaxed")  # (the last: back to 0)
    read = part < tl.where(last, BLOCK_M * BLOCK_N, 0)  # [BLOCK_M, BLOCK_N]: only the last program reads the parts
    acc = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
    acc_second = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
    squares = tl.zeros((BLOCK_M,), dtype=tl.float32)
    for split in range(splits):
        parts = workspace_ptr + (tile * splits + split) * size
        acc += tl.load(parts + part, mask=read, other=0.0, cache_modifier=".cg")
        if PAIRED:
            acc_second += tl.load(parts + BLOCK_M * BLOCK_N + part, mask=read, other=0.0, cache_modifier=".cg")
        if NORM:
            squares += tl.load(parts + 2 * BLOCK_M * BLOCK_N + rows, mask=rows < tl.where(last, BLOCK_M, 0), other=0.0, cache_modifier=".cg")
    return acc, acc_second, squares, last


@triton.jit
def _gelu_tanh(x):
    """`0.5 x (1 + tanh(sqrt(2 / pi) (x + 0.044715 x^3)))`, tanh written with exp (float32)."""
    inner = 0.7978845608028654 * (x + 0.044715 * x * x * x)
    tanh = 2.0 / (1.0 + tl.exp(-2.0 * inner)) - 1.0
    return 0.5 * x * (1.0 + tanh)


# -- kernels ------------------------------------------------------------------------------------------------------------


@direct_launch
@triton.jit
def _norm_qkv_rope_kernel(
    x_ptr, scale_ptr, bias_ptr, w_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr, workspace_ptr, counter_ptr,
    M, K, tokens, first_slot, slots, stride_xm, stride_wk, stride_wn, stride_cos_b, stride_cos_t, eps, k_split, splits,
    HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, HAS_BIAS: tl.constexpr, DOT: tl.constexpr,
    BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr, SPLIT: tl.constexpr,
):
    half: tl.constexpr = HEAD_DIM // 2
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    pairs = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)  # column pairs (c, c + H/2) of every head: q..., k, v
    first_half = pairs // half * HEAD_DIM + pairs % half  # (each pair's first column)
    acc1, acc2, squares, written = _split_matmul(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows,
                                                 first_half, half, M, K, (HEADS + 2) * HEAD_DIM, (HEADS + 2) * half,
                                                 workspace_ptr, counter_ptr, k_split, splits, BLOCK_M, BLOCK_N, BLOCK_K,
                                                 True, True, DOT, SPLIT)
    _rope_store(acc1, acc2, squares, rows, pairs, pairs < written, bias_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr,
                value_ptr, M, K, tokens, first_slot, slots, stride_cos_b, stride_cos_t, eps, HEADS, HEAD_DIM, HAS_BIAS)


@triton.jit
def _rope_store(acc1, acc2, squares, rows, pairs, pair_ok, bias_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr, M, K,
                tokens, first_slot, slots, stride_cos_b, stride_cos_t, eps,
                HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, HAS_BIAS: tl.constexpr):
    """The epilogue of a q/k/v tile: the RMSNorm's `1 / rms` (from the rows' sums of squares over K), adaRMS's bias,
    RoPE on q and k, then q into `q` `[M, N H]` and k and v into the caches at slots `first_slot + t` (`pairs`: the
    tile's column pairs (c, c + H/2) of every head, as `_norm_qkv_rope_kernel` numbers them; only `pair_ok` written)."""
    half: tl.constexpr = HEAD_DIM // 2
    head = pairs // half
    lane = pairs % half
    first_half = head * HEAD_DIM + lane
    inverse = 1.0 / tl.sqrt(squares / K + eps)
    a1 = acc1 * inverse[:, None]
    a2 = acc2 * inverse[:, None]
    if HAS_BIAS:
        a1 += tl.load(bias_ptr + first_half, mask=pair_ok, other=0.0).to(tl.float32)[None, :]
        a2 += tl.load(bias_ptr + first_half + half, mask=pair_ok, other=0.0).to(tl.float32)[None, :]
    sample = rows // tokens
    token = rows % tokens
    row_ok = rows < M
    table = sample[:, None] * stride_cos_b + token[:, None] * stride_cos_t + lane[None, :]
    cos = tl.load(cos_ptr + table, mask=row_ok[:, None] & pair_ok[None, :], other=1.0)
    sin = tl.load(sin_ptr + table + half, mask=row_ok[:, None] & pair_ok[None, :], other=0.0)  # (+sin in the second half)
    rotated = (head < HEADS + 1)[None, :]  # q and k; v is not rotated
    out1 = tl.where(rotated, a1 * cos - a2 * sin, a1)
    out2 = tl.where(rotated, a2 * cos + a1 * sin, a2)
    ok = row_ok[:, None] & pair_ok[None, :]
    q_offsets = rows[:, None] * (HEADS * HEAD_DIM) + first_half[None, :]
    is_q = ok & (head < HEADS)[None, :]
    tl.store(q_ptr + q_offsets, out1.to(q_ptr.dtype.element_ty), mask=is_q)
    tl.store(q_ptr + q_offsets + half, out2.to(q_ptr.dtype.element_ty), mask=is_q)
    cache_offsets = (sample * slots + first_slot + token)[:, None] * HEAD_DIM + lane[None, :]
    is_k = ok & (head == HEADS)[None, :]
    tl.store(key_ptr + cache_offsets, out1.to(key_ptr.dtype.element_ty), mask=is_k)
    tl.store(key_ptr + cache_offsets + half, out2.to(key_ptr.dtype.element_ty), mask=is_k)
    is_v = ok & (head == HEADS + 1)[None, :]
    tl.store(value_ptr + cache_offsets, out1.to(value_ptr.dtype.element_ty), mask=is_v)
    tl.store(value_ptr + cache_offsets + half, out2.to(value_ptr.dtype.element_ty), mask=is_v)


@direct_launch
@triton.jit
def _norm_gate_up_geglu_kernel(
    x_ptr, scale_ptr, bias_ptr, w_ptr, out_ptr, workspace_ptr, counter_ptr, M, K, F, stride_xm, stride_wk, stride_wn, eps,
    k_split, splits, HAS_BIAS: tl.constexpr, DOT: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr,
    BLOCK_K: tl.constexpr, SPLIT: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)  # gate column c pairs with up column F + c
    gate, up, squares, written = _split_matmul(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, columns,
                                               F, M, K, F, F, workspace_ptr, counter_ptr, k_split, splits, BLOCK_M,
                                               BLOCK_N, BLOCK_K, True, True, DOT, SPLIT)
    _geglu_store(gate, up, squares, rows, columns, columns < written, bias_ptr, out_ptr, M, K, F, eps, HAS_BIAS)


@triton.jit
def _geglu_store(gate, up, squares, rows, columns, column_ok, bias_ptr, out_ptr, M, K, F, eps, HAS_BIAS: tl.constexpr):
    """The epilogue of a gate/up tile: the RMSNorm's `1 / rms` (from the rows' sums of squares over K), adaRMS's bias
    (`bias[c]` and `bias[F + c]`), then `gelu_tanh(gate) * up` into `out` `[M, F]` (only `column_ok` written)."""
    inverse = (1.0 / tl.sqrt(squares / K + eps))[:, None]
    gate = gate * inverse
    up = up * inverse
    if HAS_BIAS:
        gate += tl.load(bias_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
        up += tl.load(bias_ptr + F + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
    hidden = _gelu_tanh(gate) * up
    ok = (rows < M)[:, None] & column_ok[None, :]
    tl.store(out_ptr + rows[:, None] * F + columns[None, :], hidden.to(out_ptr.dtype.element_ty), mask=ok)


@direct_launch
@triton.jit
def _matmul_residual_kernel(
    residual_ptr, y_ptr, w_ptr, gate_ptr, workspace_ptr, counter_ptr, M, K, N, stride_rm, stride_ym, stride_wk, stride_wn,
    k_split, splits, HAS_GATE: tl.constexpr, DOT: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr,
    BLOCK_K: tl.constexpr, SPLIT: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)
    acc, unused, no_squares, written = _split_matmul(y_ptr, stride_ym, y_ptr, w_ptr, stride_wk, stride_wn, rows,
                                                     columns, 0, M, K, N, N, workspace_ptr, counter_ptr, k_split,
                                                     splits, BLOCK_M, BLOCK_N, BLOCK_K, False, False, DOT, SPLIT)
    column_ok = columns < written  # (split: only the last program writes)
    if HAS_GATE:
        acc = acc * tl.load(gate_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
    ok = (rows < M)[:, None] & column_ok[None, :]
    pointers = residual_ptr + rows[:, None] * stride_rm + columns[None, :]
    residual = tl.load(pointers, mask=ok, other=0.0).to(tl.float32)
    tl.store(pointers, (residual + acc).to(residual_ptr.dtype.element_ty), mask=ok)


@direct_launch
@triton.jit
def _norm_linear_euler_kernel(
    x_t_ptr, tokens_ptr, scale_ptr, bias_ptr, w_ptr, M, K, N, stride_tm, stride_wk, stride_wn, dt, eps,
    DOT: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)
    acc, _, squares = _matmul_tiles(tokens_ptr, stride_tm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, columns, 0, M, 0,
                                    K, N, BLOCK_M, BLOCK_N, BLOCK_K, True, False, DOT, "")
    column_ok = columns < N
    velocity = acc / tl.sqrt(squares / K + eps)[:, None] + tl.load(bias_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
    ok = (rows < M)[:, None] & column_ok[None, :]
    pointers = x_t_ptr + rows[:, None] * N + columns[None, :]
    tl.store(pointers, tl.load(pointers, mask=ok, other=0.0) + dt * velocity, mask=ok)


@direct_launch
@triton.jit
def _embed_actions_kernel(
    x_ptr, w_ptr, bias_ptr, out_w_ptr, out_bias_ptr, out_ptr, M, A, D, N, stride_wa, stride_wd, stride_ok, stride_on,
    TIME_MLP: tl.constexpr, DOT: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr,
    BLOCK_A: tl.constexpr,
):
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)
    dims = tl.arange(0, BLOCK_A)
    row_ok = rows < M
    column_ok = columns < N
    x = tl.load(x_ptr + rows[:, None] * A + dims[None, :], mask=row_ok[:, None] & (dims < A)[None, :], other=0.0)
    x = x.to(w_ptr.dtype.element_ty).to(DOT)  # (read in the weights' dtype, as the reference casts it)
    if TIME_MLP:  # silu(x W + b) W_out + b_out, the hidden columns in blocks of BLOCK_K
        acc = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
        for k0 in range(0, D, BLOCK_K):
            ks = k0 + tl.arange(0, BLOCK_K)
            k_ok = ks < D
            w = tl.load(w_ptr + dims[:, None] * stride_wa + ks[None, :] * stride_wd, mask=(dims < A)[:, None] & k_ok[None, :], other=0.0)
            hidden = tl.dot(x, w.to(DOT), input_precision="ieee") + tl.load(bias_ptr + ks, mask=k_ok, other=0.0).to(tl.float32)[None, :]
            hidden = hidden / (1.0 + tl.exp(-hidden))  # SiLU
            out_w = tl.load(out_w_ptr + ks[:, None] * stride_ok + columns[None, :] * stride_on, mask=k_ok[:, None] & column_ok[None, :], other=0.0)
            acc += tl.dot(hidden.to(out_w_ptr.dtype.element_ty).to(DOT), out_w.to(DOT), input_precision="ieee")
        acc += tl.load(out_bias_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
    else:  # x W + b
        w = tl.load(w_ptr + dims[:, None] * stride_wa + columns[None, :] * stride_wd, mask=(dims < A)[:, None] & column_ok[None, :], other=0.0)
        acc = tl.dot(x, w.to(DOT), input_precision="ieee") + tl.load(bias_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)[None, :]
    ok = row_ok[:, None] & column_ok[None, :]
    tl.store(out_ptr + rows[:, None] * N + columns[None, :], acc.to(out_ptr.dtype.element_ty), mask=ok)


@direct_launch
@triton.jit
def _add_layer_norm_kernel(
    residual_ptr, y_ptr, weight_ptr, bias_ptr, out_ptr, M, D, stride_rm, stride_ym, eps,
    BLOCK_M: tl.constexpr, BLOCK_D: tl.constexpr,
):
    """Rows `[i * BLOCK_M, ...)`: `residual += y` (rounded to the residual's dtype, as it is stored), then the
    LayerNorm of the stored sum, mean and variance in float32."""
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.arange(0, BLOCK_D)
    column_ok = columns < D
    ok = (rows < M)[:, None] & column_ok[None, :]
    pointers = residual_ptr + rows[:, None] * stride_rm + columns[None, :]
    total = tl.load(pointers, mask=ok, other=0.0).to(tl.float32)
    total += tl.load(y_ptr + rows[:, None] * stride_ym + columns[None, :], mask=ok, other=0.0).to(tl.float32)
    stored = total.to(residual_ptr.dtype.element_ty)
    tl.store(pointers, stored, mask=ok)
    total = stored.to(tl.float32)
    mean = tl.sum(total, axis=1) / D
    centered = tl.where(ok, total - mean[:, None], 0.0)
    inverse = 1.0 / tl.sqrt(tl.sum(centered * centered, axis=1) / D + eps)
    weight = tl.load(weight_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)
    bias = tl.load(bias_ptr + columns, mask=column_ok, other=0.0).to(tl.float32)
    normed = centered * inverse[:, None] * weight[None, :] + bias[None, :]
    tl.store(out_ptr + rows[:, None] * D + columns[None, :], normed.to(out_ptr.dtype.element_ty), mask=ok)


@direct_launch
@triton.jit
def _range_attention_kernel(
    q_ptr, key_ptr, value_ptr, out_ptr, partial_ptr, stats_ptr, counter_ptr, first_ptr, row_ends_ptr, batch,
    rows_per_sample, heads, slots, scale, splits, HEAD_DIM: tl.constexpr, DOT: tl.constexpr, BLOCK_M: tl.constexpr,
    BLOCK_N: tl.constexpr, SPLIT: tl.constexpr, DIM_CHUNK: tl.constexpr,
):
    """Program (i, b, s): folded query rows `[i * BLOCK_M, ...)` of sample b (row r is token r // heads, head r % heads)
    over the keys `[first[b], row_ends[token])`, online softmax in float32 (`_attention_part`).

    With SPLIT the block's keys are cut into `splits` consecutive parts (a runtime count: one compiled kernel serves
    every count), program s taking part s (see `key_splits`); each stores its unnormalized sum, running maximum and
    total weight, and the block's last program to arrive combines the parts and writes the output
    (`_combine_key_parts`, in this launch)."""
    sample = tl.program_id(1)
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    acc, running_max, total = _attention_part(q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, sample, rows,
                                              rows_per_sample, heads, slots, scale, tl.program_id(2), splits, HEAD_DIM,
                                              DOT, BLOCK_M, BLOCK_N, SPLIT, "")
    base = sample * rows_per_sample * HEAD_DIM
    if SPLIT:
        _combine_key_parts(acc, running_max, total, partial_ptr, stats_ptr, counter_ptr, out_ptr + base, sample,
                           tl.program_id(0), tl.num_programs(0), tl.program_id(2), batch, rows_per_sample, splits,
                           HEAD_DIM, BLOCK_M, DIM_CHUNK)
    else:
        out = acc / tl.where(total > 0.0, total, 1.0)[:, None]
        dims = tl.arange(0, HEAD_DIM)
        tl.store(out_ptr + base + rows[:, None] * HEAD_DIM + dims[None, :], out.to(out_ptr.dtype.element_ty),
                 mask=(rows < rows_per_sample)[:, None])


@triton.jit
def _attention_part(q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, sample, rows, rows_per_sample, heads, slots,
                    scale, split, splits, HEAD_DIM: tl.constexpr, DOT: tl.constexpr, BLOCK_M: tl.constexpr,
                    BLOCK_N: tl.constexpr, SPLIT: tl.constexpr, CACHE: tl.constexpr):
    """Folded query rows `rows` of sample `sample` (q `[B, rows_per_sample, H]`) over part `split` of their keys (all of
    them without SPLIT): the unnormalized weighted sum of values `[BLOCK_M, H]`, the running maximum of the logits and
    the total weight (float32). Only keys before the block's last end are read: the slots after it may not be written
    yet (π0's state token runs while the action slots are empty), and a masked-out NaN value would still poison the
    weighted sum (0 * NaN). CACHE is the cache modifier of the q, key and value loads ("", or ".cg" where this launch
    wrote them)."""
    row_ok = rows < rows_per_sample
    dims = tl.arange(0, HEAD_DIM)
    q = tl.load(q_ptr + sample * rows_per_sample * HEAD_DIM + rows[:, None] * HEAD_DIM + dims[None, :],
                mask=row_ok[:, None], other=0.0, cache_modifier=CACHE)
    start = tl.load(first_ptr + sample).to(tl.int32)
    ends = tl.load(row_ends_ptr + rows // heads, mask=row_ok, other=0).to(tl.int32)
    stop = tl.max(ends, axis=0)
    if SPLIT:  # part `split` of [start, stop), in whole key blocks
        part = tl.cdiv(tl.cdiv(tl.maximum(stop - start, 0), splits), BLOCK_N) * BLOCK_N
        start = start + split * part
        stop = tl.minimum(start + part, stop)
    running_max = tl.full((BLOCK_M,), -1.0e30, dtype=tl.float32)
    total = tl.zeros((BLOCK_M,), dtype=tl.float32)
    acc = tl.zeros((BLOCK_M, HEAD_DIM), dtype=tl.float32)
    cache = sample * slots * HEAD_DIM
    for k0 in range(start, stop, BLOCK_N):
        keys = k0 + tl.arange(0, BLOCK_N)
        key_ok = keys < stop
        k = tl.load(key_ptr + cache + keys[:, None] * HEAD_DIM + dims[None, :], mask=key_ok[:, None], other=0.0,
                    cache_modifier=CACHE)
        logits = tl.dot(q.to(DOT), tl.trans(k.to(DOT)), input_precision="ieee") * scale  # [BLOCK_M, BLOCK_N]
        visible = (keys[None, :] < ends[:, None]) & key_ok[None, :]
        logits = tl.where(visible, logits, -1.0e30)
        new_max = tl.maximum(running_max, tl.max(logits, axis=1))
        weights = tl.where(visible, tl.exp(logits - new_max[:, None]), 0.0)
        correction = tl.exp(running_max - new_max)
        v = tl.load(value_ptr + cache + keys[:, None] * HEAD_DIM + dims[None, :], mask=key_ok[:, None], other=0.0,
                    cache_modifier=CACHE)
        acc = acc * correction[:, None] + tl.dot(weights.to(DOT), v.to(DOT), input_precision="ieee")
        total = total * correction + tl.sum(weights, axis=1)
        running_max = new_max
    return acc, running_max, total


@triton.jit
def _combine_key_parts(acc, running_max, total, partial_ptr, stats_ptr, counter_ptr, out_ptr, sample, block, blocks,
                       split, batch, rows_per_sample, splits, HEAD_DIM: tl.constexpr, BLOCK_M: tl.constexpr,
                       DIM_CHUNK: tl.constexpr):
    """The key parts of row block `block` (of `blocks` per sample) of sample `sample`, combined in their launch as
    `_sum_splits` adds split-K's parts: each program stores its part `split` (`partial` `[splits, B, rows, H]`,
    `stats` `[2, splits, B, rows]`: running maximum, total weight) and counts itself in on the block's counter; the
    last to arrive merges the parts and writes the block's output rows (at `out_ptr`, the sample's first row), then
    puts the counter back to 0. The merge: the largest of the parts' maxima, each part's sum and total weight rescaled
    to it, summed in split order (deterministic), `DIM_CHUNK` columns of the head at a time (a 64-row block's whole
    head twice over would not fit the registers: 24-48 bytes spilled on sm_80/86/89/120, none in quarters). Returns
    whether this program was the last (it wrote the rows)."""
    rows = block * BLOCK_M + tl.arange(0, BLOCK_M)
    dims = tl.arange(0, HEAD_DIM)
    parts = splits * batch * rows_per_sample  # (the totals follow the maxima in `stats`)
    row_ok = rows < rows_per_sample
    mine = (split * batch + sample) * rows_per_sample + rows
    tl.store(partial_ptr + mine[:, None] * HEAD_DIM + dims[None, :], acc, mask=row_ok[:, None])
    tl.store(stats_ptr + mine, running_max, mask=row_ok)
    tl.store(stats_ptr + parts + mine, total, mask=row_ok)
    tl.debug_barrier()
    counter_ptr += sample * blocks + block
    last = tl.atomic_add(counter_ptr, 1, sem="acq_rel") == splits - 1
    tl.atomic_add(counter_ptr, tl.where(last, -splits, 0), sem="relaxed")  # (the last: back to 0)
    read = rows < tl.where(last, rows_per_sample, 0)  # only the last program reads the parts and writes
    largest = tl.full((BLOCK_M,), -1.0e30, dtype=tl.float32)
    for key_part in range(splits):
        row_index = (key_part * batch + sample) * rows_per_sample + rows
        largest = tl.maximum(largest, tl.load(stats_ptr + row_index, mask=read, other=-1.0e30, cache_modifier=".cg"))
    total = tl.zeros((BLOCK_M,), dtype=tl.float32)
    for key_part in range(splits):
        row_index = (key_part * batch + sample) * rows_per_sample + rows
        weight = tl.exp(tl.load(stats_ptr + row_index, mask=read, other=-1.0e30, cache_modifier=".cg") - largest)
        total += weight * tl.load(stats_ptr + parts + row_index, mask=read, other=0.0, cache_modifier=".cg")
    inverse = 1.0 / tl.where(total > 0.0, total, 1.0)
    for first_dim in tl.static_range(0, HEAD_DIM, DIM_CHUNK):
        chunk = first_dim + tl.arange(0, DIM_CHUNK)
        out = tl.zeros((BLOCK_M, DIM_CHUNK), dtype=tl.float32)
        for key_part in range(splits):
            row_index = (key_part * batch + sample) * rows_per_sample + rows
            weight = tl.exp(tl.load(stats_ptr + row_index, mask=read, other=-1.0e30, cache_modifier=".cg") - largest)
            part = tl.load(partial_ptr + row_index[:, None] * HEAD_DIM + chunk[None, :], mask=read[:, None], other=0.0,
                           cache_modifier=".cg")
            out += weight[:, None] * part
        out = out * inverse[:, None]
        tl.store(out_ptr + rows[:, None] * HEAD_DIM + chunk[None, :], out.to(out_ptr.dtype.element_ty), mask=read[:, None])
    return last


@direct_launch
@triton.jit
def _rope_cache_write_kernel(
    qkv_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr, slot_ptr, M, tokens, first_slot, slots, stride_qkv, stride_cos_b,
    stride_cos_t, HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, HAS_SLOT: tl.constexpr, BLOCK_M: tl.constexpr,
):
    """The epilogue of `_norm_qkv_rope_kernel` on a q/k/v projection's output (the prefix and π0-FAST's decoded tokens:
    their GEMMs stay cuBLAS's). With HAS_SLOT the first cache slot is read from `slot_ptr` (a device value: one CUDA
    graph serves every decoding step), else it is `first_slot`."""
    half: tl.constexpr = HEAD_DIM // 2
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    lane = tl.arange(0, half)
    row_ok = (rows < M)[:, None]
    sample = rows // tokens
    token = rows % tokens
    table = sample[:, None] * stride_cos_b + token[:, None] * stride_cos_t + lane[None, :]
    cos = tl.load(cos_ptr + table, mask=row_ok, other=1.0)
    sin = tl.load(sin_ptr + table + half, mask=row_ok, other=0.0)
    if HAS_SLOT:
        first_slot = tl.load(slot_ptr).to(tl.int32)
    cache_offsets = (sample * slots + first_slot + token)[:, None] * HEAD_DIM + lane[None, :]
    for head in tl.static_range(HEADS + 2):
        source = qkv_ptr + rows[:, None] * stride_qkv + head * HEAD_DIM + lane[None, :]
        a1 = tl.load(source, mask=row_ok, other=0.0).to(tl.float32)
        a2 = tl.load(source + half, mask=row_ok, other=0.0).to(tl.float32)
        if head < HEADS + 1:  # q and k rotate; v does not
            a1, a2 = a1 * cos - a2 * sin, a2 * cos + a1 * sin
        if head < HEADS:
            target = q_ptr + rows[:, None] * (HEADS * HEAD_DIM) + head * HEAD_DIM + lane[None, :]
        elif head == HEADS:
            target = key_ptr + cache_offsets
        else:
            target = value_ptr + cache_offsets
        tl.store(target, a1.to(target.dtype.element_ty), mask=row_ok)
        tl.store(target + half, a2.to(target.dtype.element_ty), mask=row_ok)


@direct_launch
@triton.jit
def _geglu_kernel(gate_up_ptr, out_ptr, M, F, stride_gm, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr):
    rows = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    columns = tl.program_id(1) * BLOCK_N + tl.arange(0, BLOCK_N)
    ok = (rows < M)[:, None] & (columns < F)[None, :]
    source = gate_up_ptr + rows[:, None] * stride_gm + columns[None, :]
    gate = tl.load(source, mask=ok, other=0.0).to(tl.float32)
    up = tl.load(source + F, mask=ok, other=0.0).to(tl.float32)
    tl.store(out_ptr + rows[:, None] * F + columns[None, :], (_gelu_tanh(gate) * up).to(out_ptr.dtype.element_ty), mask=ok)


# -- launchers (same arguments and results as `pi0_torch.kernels.reference`) ------------------------------------------


COUNTER_SLOTS = 4_096  # output tiles (attention: row blocks) one launch in parts may have
_counters: dict[tuple[torch.device, int, int], torch.Tensor] = {}  # `zeroed_counters` per (device, stream, size)


def split_k(x: torch.Tensor, tile: Blocks, tiles: int, depth: int) -> tuple[Blocks, torch.Tensor, torch.Tensor, int]:
    """Split-K's buffers for a launch of `tiles` output tiles over a reduction `depth` deep: (the tiling, with one
    part where the tiles are too many for the counters; the float32 workspace of the parts' sums; the arrival
    counters; the columns of `depth` per part, a whole number of `tile.k`).

    The counters are zeroed once and each launch leaves them at 0. Launches in one stream run one after another and
    share them; each stream has its own, so that launches of two streams at once (two policies on one GPU) never
    count into the same tile. Made during a CUDA graph's capture, they come from the graph's memory, and the graph
    zeroes them again before each replay."""
    if tile.splits == 1 or tiles > COUNTER_SLOTS:
        return tile._replace(splits=1), x, x, depth
    workspace = split_workspace(x, tiles, tile.m, tile.n, tile.splits)
    return tile, workspace, zeroed_counters(x.device, COUNTER_SLOTS), cdiv(cdiv(depth, tile.splits), tile.k) * tile.k


def split_workspace(x: torch.Tensor, tiles: int, rows: int, columns: int, splits: int) -> torch.Tensor:
    """float32 room on `x`'s device for the `splits` parts of `tiles` output tiles of `rows` x `columns` each, as
    `_sum_splits` lays them out (per part: two accumulators and the rows' sums of squares)."""
    return x.new_empty(tiles * splits * (2 * rows * columns + rows), dtype=torch.float32)


def zeroed_counters(device: torch.device, size: int) -> torch.Tensor:
    """int32 `[size]` counters of the current stream on `device`, zeroed when made (on first use) and left at 0 by
    every launch that counts in them (`split_k`'s arrivals, `persistent.expert_layers_`'s phases)."""
    stream = torch._C._cuda_getCurrentRawStream(device.index) if device.type == "cuda" else 0  # (triton's driver's call)
    key = (device, stream, size)
    counters = _counters.get(key)
    if counters is None:
        counters = _counters[key] = torch.zeros(size, dtype=torch.int32, device=device)
    return counters


def embed_actions(x_t, weight, bias, out_weight, out_bias):
    rows, action_dim = x_t.shape[0] * x_t.shape[1], x_t.shape[2]
    width = weight.shape[1]
    columns = width if out_weight is None else out_weight.shape[1]
    out = x_t.new_empty(rows, columns, dtype=weight.dtype)
    tile = narrow_blocks(rows, columns)
    x_t = x_t.contiguous()  # (the engine's is)
    _embed_actions_kernel[(cdiv(rows, tile.m), cdiv(columns, tile.n))](
        x_t, weight, bias, out_weight if out_weight is not None else weight, out_bias if out_bias is not None else bias, out,
        rows, action_dim, width, columns, weight.stride(0), weight.stride(1),
        out_weight.stride(0) if out_weight is not None else 0, out_weight.stride(1) if out_weight is not None else 0,
        TIME_MLP=out_weight is not None, DOT=dot_dtype(weight.dtype), BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k,
        BLOCK_A=max(16, next_power_of_2(action_dim)), num_warps=tile.warps, num_stages=tile.stages,
    )
    return out


def add_layer_norm_(residual, y, weight, bias, eps):
    rows, width = residual.shape
    out = torch.empty_like(residual)
    block_d = next_power_of_2(width)
    _add_layer_norm_kernel[(rows,)](  # (a row per program: SigLIP's 1,152 columns are 9 to 18 values per thread)
        residual, y, weight, bias, out, rows, width, residual.stride(0), y.stride(0), eps,
        BLOCK_M=1, BLOCK_D=block_d, num_warps=4 if block_d <= 2048 else 8,
    )
    return out


def norm_qkv_rope(x, scale, bias, weight, cos, sin, key_cache, value_cache, first_slot, eps):
    rows, width = x.shape
    batch, slots, head_dim = key_cache.shape
    heads = weight.shape[1] // head_dim - 2
    tile = blocks(rows, weight.shape[1] // 2, width)
    if tile is None:  # cuBLAS's GEMM; RoPE and the cache write after it
        qkv = reference.normed_projection(x, scale, bias, weight, eps)
        return rope_cache_write(qkv, cos, sin, key_cache, value_cache, first_slot)
    q = x.new_empty(rows, heads * head_dim)
    grid = (cdiv(rows, tile.m), cdiv((heads + 2) * head_dim // 2, tile.n))
    tile, workspace, counters, k_split = split_k(x, tile, grid[0] * grid[1], width)
    _norm_qkv_rope_kernel[(*grid, tile.splits)](
        x, scale, bias if bias is not None else scale, weight, cos, sin, q, key_cache, value_cache, workspace, counters,
        rows, width, rows // batch, first_slot, slots, x.stride(0), weight.stride(0), weight.stride(1),
        cos.stride(0) if cos.shape[0] > 1 else 0, cos.stride(1), eps, k_split, tile.splits,
        HEADS=heads, HEAD_DIM=head_dim, HAS_BIAS=bias is not None, DOT=dot_dtype(weight.dtype),
        BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k, SPLIT=tile.splits > 1, num_warps=tile.warps,
        num_stages=tile.stages,
    )
    return q


def norm_gate_up_geglu(x, scale, bias, weight, eps):
    rows, width = x.shape
    mlp_width = weight.shape[1] // 2
    tile = blocks(rows, mlp_width, width)
    if tile is None:  # cuBLAS's GEMM; the GeGLU after it
        return geglu(reference.normed_projection(x, scale, bias, weight, eps))
    out = x.new_empty(rows, mlp_width)
    grid = (cdiv(rows, tile.m), cdiv(mlp_width, tile.n))
    tile, workspace, counters, k_split = split_k(x, tile, grid[0] * grid[1], width)
    _norm_gate_up_geglu_kernel[(*grid, tile.splits)](
        x, scale, bias if bias is not None else scale, weight, out, workspace, counters, rows, width, mlp_width,
        x.stride(0), weight.stride(0), weight.stride(1), eps, k_split, tile.splits,
        HAS_BIAS=bias is not None, DOT=dot_dtype(weight.dtype), BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k,
        SPLIT=tile.splits > 1, num_warps=tile.warps, num_stages=tile.stages,
    )
    return out


def matmul_residual_(residual, y, weight, gate):
    rows, width = residual.shape
    tile = blocks(rows, width, y.shape[1])
    if tile is None:  # cuBLAS's GEMM, the residual added by it (`addmm_`; adaRMS: gated after it)
        return reference.matmul_residual_(residual, y, weight, gate)
    grid = (cdiv(rows, tile.m), cdiv(width, tile.n))
    tile, workspace, counters, k_split = split_k(y, tile, grid[0] * grid[1], y.shape[1])
    _matmul_residual_kernel[(*grid, tile.splits)](
        residual, y, weight, gate if gate is not None else weight, workspace, counters, rows, y.shape[1], width,
        residual.stride(0), y.stride(0), weight.stride(0), weight.stride(1), k_split, tile.splits,
        HAS_GATE=gate is not None, DOT=dot_dtype(weight.dtype), BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k,
        SPLIT=tile.splits > 1, num_warps=tile.warps, num_stages=tile.stages,
    )


def norm_linear_euler_(x_t, tokens, scale, bias, weight, dt, eps):
    rows, width = tokens.shape
    actions = weight.shape[1]
    tile = narrow_blocks(rows, actions)
    grid = (cdiv(rows, tile.m), cdiv(actions, tile.n))
    _norm_linear_euler_kernel[grid](
        x_t, tokens, scale, bias, weight, rows, width, actions, tokens.stride(0), weight.stride(0), weight.stride(1),
        dt, eps, DOT=dot_dtype(weight.dtype), BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k, num_warps=tile.warps,
        num_stages=tile.stages,
    )


def range_attention(query, key_cache, value_cache, first, row_ends):
    query = query.contiguous()  # (the engine's is; the kernel reads it as [B, T * N, H])
    batch, tokens, heads, head_dim = query.shape
    out = query.new_empty(batch * tokens, heads * head_dim)
    rows = tokens * heads
    tile = attention_blocks(rows, batch, key_cache.shape[1])
    row_blocks = cdiv(rows, tile.m)
    splits = tile.splits if row_blocks * batch <= COUNTER_SLOTS else 1  # (a counter per row block)
    partial = stats = counters = out  # (not read with one part)
    if splits > 1:
        partial = query.new_empty(splits, batch * rows, head_dim, dtype=torch.float32)
        stats = query.new_empty(2, splits, batch * rows, dtype=torch.float32)
        counters = zeroed_counters(query.device, COUNTER_SLOTS)
    _range_attention_kernel[(row_blocks, batch, splits)](
        query, key_cache, value_cache, out, partial, stats, counters, first, row_ends, batch, rows, heads,
        key_cache.shape[1], head_dim**-0.5, splits, HEAD_DIM=head_dim, DOT=dot_dtype(query.dtype), BLOCK_M=tile.m,
        BLOCK_N=tile.n, SPLIT=splits > 1, DIM_CHUNK=min(head_dim, 4096 // tile.m),  # (4,096 values merged at a time)
        num_stages=tile.stages, num_warps=tile.warps,
    )
    return out


class AttentionBlocks(NamedTuple):
    """`range_attention`'s tiling: folded query rows and keys per block, triton's warps and stages, key parts."""

    m: int
    n: int
    warps: int
    stages: int
    splits: int


@functools.lru_cache(maxsize=None)
def attention_blocks(rows: int, batch: int, slots: int) -> AttentionBlocks:
    """The tiling of `range_attention` for `rows` folded query rows per sample over a cache of `slots`.

    16-row blocks where the rows are few (more programs over them), else 64, and the keys cut into parts
    (`key_splits`). The 64-row blocks load keys and values in 2 stages: with triton's default 3 they take 100 KiB of
    shared memory on sm_80/86/89/120, more than a block may have on an RTX 3090/4090/5090 (99 KiB); 2 take 68 KiB
    there (96 KiB on sm_90). Warps and key blocks as measured fastest on an H200 (`benchmarks/kernel_sweep.py`)."""
    if batch * rows <= 64 * 16:
        return AttentionBlocks(16, 32, 4, 3, key_splits(cdiv(rows, 16), batch, slots))  # (64 keys: 138 KiB, sm_90's)
    return AttentionBlocks(64, 32, 4, 2, key_splits(cdiv(rows, 64), batch, slots))


def key_splits(row_blocks: int, batch: int, slots: int) -> int:
    """Into how many parts `range_attention` cuts each sample's keys (its last program to finish combines them), where
    the samples are fewer than 32: one part per 128 slots of the cache, at most 8 where a sample's query rows are one
    block (a decoded token, π0's state token), at most 4 where they are several (the action tokens). Measured on an
    H200, full-size π0 (867 slots): the action tokens' attention took 29.5 µs in one part and 11.5 µs in four at
    batch 1, 55 µs and 22 µs at batch 8; the state token 10.1 µs in six parts and 9.5 µs in eight."""
    if batch >= 32 or slots < 256:
        return 1
    return min(8 if row_blocks == 1 else 4, slots // 128)


def rope_cache_write(qkv, cos, sin, key_cache, value_cache, first_slot, slot=None):
    rows = qkv.shape[0]
    batch, slots, head_dim = key_cache.shape
    heads = qkv.shape[1] // head_dim - 2
    q = qkv.new_empty(rows, heads * head_dim)
    block_m = 16
    _rope_cache_write_kernel[(cdiv(rows, block_m),)](
        qkv, cos, sin, q, key_cache, value_cache, slot if slot is not None else cos, rows, rows // batch, first_slot,
        slots, qkv.stride(0), cos.stride(0) if cos.shape[0] > 1 else 0, cos.stride(1), HEADS=heads, HEAD_DIM=head_dim,
        HAS_SLOT=slot is not None, BLOCK_M=block_m,
    )
    return q


def geglu(gate_up):
    rows, mlp_width = gate_up.shape[0], gate_up.shape[1] // 2
    out = gate_up.new_empty(rows, mlp_width)
    block_m, block_n = 16, 128
    _geglu_kernel[(cdiv(rows, block_m), cdiv(mlp_width, block_n))](
        gate_up, out, rows, mlp_width, gate_up.stride(0), BLOCK_M=block_m, BLOCK_N=block_n,
    )
    return out
