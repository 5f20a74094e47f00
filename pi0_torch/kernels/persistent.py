"""Every decoder layer of the action expert in one Euler step, as one persistent launch (`expert_layers_`) instead
of five launches per layer (90 for π0's 18 layers): `sampling_kernels="persistent"`.

- One launch of as many programs as the GPU has multiprocessors (`Tiling.per_sm` per multiprocessor). Each takes
  tiles in ticket order from an atomic counter, layer after layer: the q/k/v projection's tiles (RMSNorm, RoPE, k and
  v into the layer's cache: `norm_qkv_rope`'s epilogue, `_rope_store`), the attention's (folded query rows of a sample
  and one part of their keys; the last part to finish combines them: `range_attention`'s `_attention_part` and
  `_combine_key_parts`), the o-projection's (+ residual), gate/up's (norm, GeGLU: `_geglu_store`) and the
  down-projection's (+ residual; with the o-projection one tile function, `_residual_tile`, whose reduction may be
  split into parts that the last to arrive sums: `Tiling.o_splits`, `down_splits`, `_sum_splits`). π0.5's adaRMS
  biases and residual gates ride in the same epilogues.
- A tile waits on counters for what it reads: q/k/v of row block r for the previous layer's down-projection of r,
  the attention for every q/k/v tile of its layer, the o-projection for every attention block, gate/up for the
  o-projection of its row block, the down-projection for gate/up's. The buffers between phases (q, the attention's
  output, the MLP's hidden activations, the key parts) are one per launch and reused by every layer: each is written
  again only after every reader of the layer before has counted in (the chain of waits above).
- A tile waits only on tiles handed out before it, whose programs are already running: no deadlock however many
  programs the GPU runs at once, and triton's interpreter (programs one after another) runs it too. Nothing ever
  waits there, so `benchmarks/persistent_layers.py --check` also records what each tile waits for and runs the tiles
  in other orders those waits allow.
- A wait that has not ended after a few seconds (`SPINS`) is abandoned rather than hung on: the launch then returns
  NaN actions, the device's `watchdog` says so (`abandoned`), and every later launch there does the same at once. A
  correct launch never gets there; what would is a synchronization fault on a GPU, and a robot is better served by
  a refusal (the first call's verification) or a withheld chunk than by a process that never returns.
- A waiting tile first asks its weights into L2. The last program to finish puts the counters back to 0, so the next
  launch needs no memset: a step's layers are one launch and nothing else. The counters are kept per stream
  (`zeroed_counters`), so launches of two streams at once never count into each other's (a model's CUDA graphs share
  their capture stream's, and replay one after another).

The layers' weights stay where the model keeps them: the kernel reads layer 0's and, per layer, its offset from them
(`weight_offsets`, a table made once per set of weights), so every layer's weights must have the same shape, strides
and dtype and start 16-byte aligned. The caches, norm scales and adaRMS tensors are stacked `[L, ...]`.

The numbers are those of `pi0_torch.kernels.reference.expert_layers_` (float32 sums, bf16 outputs), not bit for bit
(its sums go in other orders). Inside a CUDA graph a step of π0's 18 layers takes about 1.09 ms so against 0.98 ms in
five launches per layer (an H200, docs/gpu.md); eagerly it is faster: `ActionSampling.runs_persistent` says where.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from pi0_torch.utils.extras import require_extra

require_extra("kernels", "pi0_torch.kernels.persistent")
import triton  # noqa: E402
import triton.language as tl  # noqa: E402
from triton.language.extra.cuda import globaltimer, smid  # noqa: E402

from pi0_torch.kernels.triton_kernels import (  # noqa: E402
    INTERPRETING,
    _attention_part,
    _combine_key_parts,
    _geglu_store,
    _matmul_tiles,
    _rope_store,
    _sum_splits,
    cdiv,
    dot_dtype,
    split_workspace,
    zeroed_counters,
)


class Tiling(NamedTuple):
    """Output columns per tile of each GEMM phase (q/k/v in column pairs, o-projection, gate/up, down-projection), the
    GEMMs' reduction block and rows per tile, the attention's folded query rows and keys per block and its key parts,
    warps, pipeline stages, whether a waiting tile prefetches its weights (never in the interpreter), programs per
    multiprocessor, and the parts the o- and down-projections' reductions (2,048 and 4,096 deep in π0's expert) and
    q/k/v's and gate/up's (1,024 deep, the norm's sums of squares with them) are split into (split-K: more tiles,
    each a part as deep, summed by the last part to arrive).

    The defaults were the fastest of 15 tilings timed on an H200 (`benchmarks/persistent_layers.py --bench`, π0,
    batch 1: 1.09 ms a step, against 1.42 ms with 64-deep blocks and no split; 8 warps, 4 stages or wider tiles were
    slower). A tile's GEMM is bound by its loads' latency, so a deeper reduction block (fewer, larger loads) and
    splitting the two deep reductions (each tile reads a part of the activations as well as of the weights) pay.
    Splitting q/k/v's and gate/up's is not timed on a GPU yet (`benchmarks/persistent_layers.py --bench` does), so
    they stay whole by default."""

    qkv: int = 16
    o: int = 16
    gate_up: int = 32
    down: int = 16
    k: int = 128
    m: int = 64
    attention_m: int = 16
    attention_n: int = 32
    key_parts: int = 4
    warps: int = 4
    stages: int = 3
    prefetch: bool = True
    per_sm: int = 1
    o_splits: int = 2
    down_splits: int = 2
    qkv_splits: int = 1
    gate_up_splits: int = 1


# -- tiles ----------------------------------------------------------------------------------------------------------


@triton.jit
def _wait_for(counter_ptr, need, watch_ptr):
    """Spin until the int32 counter reaches `need` (acquire: what its producers stored before counting is visible),
    or abandon the wait after `watch[1]` spins (about a second per million): then `watch[0]` is set, every later wait
    gives up at once (this launch's and the next ones'), and the launch's last program fills `x` with NaN."""
    count = tl.atomic_add(counter_ptr, 0, sem="acquire")
    if count < need:
        spins = tl.where(tl.atomic_add(watch_ptr, 0) == 0, tl.load(watch_ptr + 1), 0)
        while (count < need) & (spins > 0):
            count = tl.atomic_add(counter_ptr, 0, sem="acquire")
            spins -= 1
        if count < need:
            tl.atomic_xchg(watch_ptr, 1)


@triton.jit
def _count_in(counter_ptr, count):
    """`count` more of this phase done (a tile: 1): after every thread's stores (the barrier), a release add."""
    tl.debug_barrier()
    tl.atomic_add(counter_ptr, count, sem="release")


@triton.jit
def _prefetch_weights(w_ptr, stride_wk, stride_wn, columns, k_start, k_stop, N, BLOCK_K: tl.constexpr,
                      PREFETCH: tl.constexpr):
    """Ask `w[k_start:k_stop, columns]` into the L2 cache (a hint: nothing comes into registers): one address per 32
    bytes of a column of a bf16 `[in, out]` view of an `nn.Linear` weight (`in` has unit stride)."""
    if PREFETCH:
        for k0 in range(k_start, k_stop, BLOCK_K):
            ks = k0 + tl.arange(0, BLOCK_K // 16) * 16
            ok = (ks < k_stop)[:, None] & (columns < N)[None, :]
            offsets = tl.where(ok, ks[:, None] * stride_wk + columns[None, :] * stride_wn, 0)
            tl.inline_asm_elementwise("prefetch.global.L2 [$1]; mov.u32 $0, 0;", "=r,l", [w_ptr + offsets],
                                      dtype=tl.int32, is_pure=False, pack=1)


@triton.jit
def _add_to_residual(x_ptr, stride_xm, rows, columns, M, N, acc, gate_ptr, HAS_GATE: tl.constexpr):
    """`x[rows, columns] += acc` (adaRMS: `acc * gate[columns]`; float32 sum, rounded once), read past L1."""
    ok = (rows < M)[:, None] & (columns < N)[None, :]
    if HAS_GATE:
        acc = acc * tl.load(gate_ptr + columns, mask=columns < N, other=0.0).to(tl.float32)[None, :]
    pointers = x_ptr + rows[:, None] * stride_xm + columns[None, :]
    residual = tl.load(pointers, mask=ok, other=0.0, cache_modifier=".cg").to(tl.float32)
    tl.store(pointers, (residual + acc).to(x_ptr.dtype.element_ty), mask=ok)


@triton.jit
def _part_range(part, K, SPLITS: tl.constexpr, BLOCK_K: tl.constexpr):
    """The reduction range `[start, stop)` of part `part` of `SPLITS` (a whole number of BLOCK_K each; the last may be
    shallower, or empty)."""
    depth = tl.cdiv(tl.cdiv(K, SPLITS), BLOCK_K) * BLOCK_K
    start = part * depth
    return start, tl.minimum(start + depth, K)


@triton.jit
def _tile_at(tile, N, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr):
    """Output tile `tile` of a phase whose tiles go row block by row block, `cdiv(N, BLOCK_N)` column blocks each:
    its row block, rows and columns."""
    column_blocks = tl.cdiv(N, BLOCK_N)
    block = tile // column_blocks
    return block, block * BLOCK_M + tl.arange(0, BLOCK_M), (tile % column_blocks) * BLOCK_N + tl.arange(0, BLOCK_N)


@triton.jit
def _residual_tile(tile, x_ptr, a_ptr, stride_am, w_ptr, stride_wk, stride_wn, gate_ptr, wait_ptr, wait_stride, need,
                   counters_ptr, watch_ptr, workspace_ptr, arrivals_ptr, M, D, K, stride_xm, BLOCK_M: tl.constexpr,
                   BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr, SPLITS: tl.constexpr, DOT: tl.constexpr,
                   PREFETCH: tl.constexpr, HAS_GATE: tl.constexpr, COUNT: tl.constexpr):
    """`x[r, n] += a[r] @ w[:, n]` (adaRMS: times `gate[n]`) for output tile `tile // SPLITS` (row block r, columns
    n): the o-projection (`a`: the attention's output) and the down-projection (`a`: the MLP's hidden activations).
    It starts once `wait[r * wait_stride]` reaches `need`, and with COUNT it is then counted in for r
    (`counters[r]`). With SPLITS > 1 this is part `tile % SPLITS` of the reduction (a whole number of BLOCK_K): the
    part to arrive last adds the parts up in part order (`_sum_splits`: float32 sums in `workspace`, the tile's
    `arrivals` back at 0) and updates `x`; every part counts in, all but the last with 0. (COUNT is optional for
    `benchmarks/persistent_mlp.py`, whose down-projection nothing waits for: with 4 stages of 128-deep blocks its
    barrier took 80 KiB more shared memory than sm_90 has.)"""
    output = tile // SPLITS
    block, rows, columns = _tile_at(output, D, BLOCK_M, BLOCK_N)
    k_start, k_stop = _part_range(tile % SPLITS, K, SPLITS, BLOCK_K)
    _prefetch_weights(w_ptr, stride_wk, stride_wn, columns, k_start, k_stop, D, BLOCK_K, PREFETCH)
    _wait_for(wait_ptr + block * wait_stride, need, watch_ptr)
    acc, unused, no_squares = _matmul_tiles(a_ptr, stride_am, a_ptr, w_ptr, stride_wk, stride_wn, rows, columns, 0, M,
                                            k_start, k_stop, D, BLOCK_M, BLOCK_N, BLOCK_K, False, False, DOT, ".cg")
    written, count = D, 1
    if SPLITS > 1:  # (only the last part to arrive writes, and counts in)
        acc, unused, no_squares, last = _sum_splits(acc, unused, no_squares, workspace_ptr, arrivals_ptr, output,
                                                    tile % SPLITS, SPLITS, BLOCK_M, BLOCK_N, False, False)
        written, count = tl.where(last, D, 0), tl.where(last, 1, 0)
    _add_to_residual(x_ptr, stride_xm, rows, columns, M, written, acc, gate_ptr, HAS_GATE)
    if COUNT:
        _count_in(counters_ptr + block, count)


@triton.jit
def _gate_up_tile(tile, x_ptr, scale_ptr, gate_up_ptr, bias_ptr, hidden_ptr, o_counters_ptr, counters_ptr, watch_ptr,
                  workspace_ptr, arrivals_ptr, M, D, F, stride_xm, stride_gk, stride_gn, eps, BLOCK_M: tl.constexpr,
                  N_O: tl.constexpr, N_GATE_UP: tl.constexpr, BLOCK_K: tl.constexpr, SPLITS: tl.constexpr,
                  DOT: tl.constexpr, PREFETCH: tl.constexpr, HAS_BIAS: tl.constexpr):
    """`hidden[r, f] = gelu_tanh(norm(x[r]) @ gate[:, f]) * (norm(x[r]) @ up[:, f])` (adaRMS: plus `bias[f]` and
    `bias[F + f]` before the GeGLU) for output tile `tile // SPLITS`, once every o-projection tile of row block r is
    in (`o_counters[r]`); then counted in for r (`counters[r]`). With SPLITS > 1 this is part `tile % SPLITS` of the
    reduction, as `_residual_tile`'s: the last part to arrive sums the parts (and their sums of squares) and stores."""
    output = tile // SPLITS
    block, rows, columns = _tile_at(output, F, BLOCK_M, N_GATE_UP)
    k_start, k_stop = _part_range(tile % SPLITS, D, SPLITS, BLOCK_K)
    _prefetch_weights(gate_up_ptr, stride_gk, stride_gn, columns, k_start, k_stop, F, BLOCK_K, PREFETCH)
    _prefetch_weights(gate_up_ptr + F * stride_gn, stride_gk, stride_gn, columns, k_start, k_stop, F, BLOCK_K, PREFETCH)
    _wait_for(o_counters_ptr + block, tl.cdiv(D, N_O), watch_ptr)
    gate, up, squares = _matmul_tiles(x_ptr, stride_xm, scale_ptr, gate_up_ptr, stride_gk, stride_gn, rows, columns, F,
                                      M, k_start, k_stop, F, BLOCK_M, N_GATE_UP, BLOCK_K, True, True, DOT, ".cg")
    written, count = F, 1
    if SPLITS > 1:  # (only the last part to arrive writes, and counts in)
        gate, up, squares, last = _sum_splits(gate, up, squares, workspace_ptr, arrivals_ptr, output, tile % SPLITS,
                                              SPLITS, BLOCK_M, N_GATE_UP, True, True)
        written, count = tl.where(last, F, 0), tl.where(last, 1, 0)
    _geglu_store(gate, up, squares, rows, columns, columns < written, bias_ptr, hidden_ptr, M, D, F, eps, HAS_BIAS)
    _count_in(counters_ptr + block, count)


@triton.jit
def _qkv_tile(tile, x_ptr, scale_ptr, w_ptr, bias_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr, wait_ptr, need,
              counter_ptr, watch_ptr, workspace_ptr, arrivals_ptr, M, D, tokens, first_slot, slots, stride_xm, stride_wk,
              stride_wn, stride_cos_b, stride_cos_t, eps, HEADS: tl.constexpr, HEAD_DIM: tl.constexpr,
              BLOCK_M: tl.constexpr, N_QKV: tl.constexpr, BLOCK_K: tl.constexpr, SPLITS: tl.constexpr,
              DOT: tl.constexpr, PREFETCH: tl.constexpr, HAS_BIAS: tl.constexpr):
    """Column pairs `(c, c + H/2)` of q/k/v for row block r (output tile `tile // SPLITS`): RMSNorm, the projection
    (adaRMS: plus `bias`), RoPE; q into `q`, k and v into the layer's cache (`_rope_store`), once `wait[r]` reaches
    `need` (the previous layer's down-projection of r); then counted in (`counter`). With SPLITS > 1 this is part
    `tile % SPLITS` of the reduction, as `_gate_up_tile`'s."""
    half: tl.constexpr = HEAD_DIM // 2
    output = tile // SPLITS
    block, rows, pairs = _tile_at(output, (HEADS + 2) * half, BLOCK_M, N_QKV)
    first_half = pairs // half * HEAD_DIM + pairs % half
    width = (HEADS + 2) * HEAD_DIM
    k_start, k_stop = _part_range(tile % SPLITS, D, SPLITS, BLOCK_K)
    _prefetch_weights(w_ptr, stride_wk, stride_wn, first_half, k_start, k_stop, width, BLOCK_K, PREFETCH)
    _prefetch_weights(w_ptr, stride_wk, stride_wn, first_half + half, k_start, k_stop, width, BLOCK_K, PREFETCH)
    _wait_for(wait_ptr + block, need, watch_ptr)
    acc1, acc2, squares = _matmul_tiles(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, first_half, half,
                                        M, k_start, k_stop, width, BLOCK_M, N_QKV, BLOCK_K, True, True, DOT, ".cg")
    written, count = (HEADS + 2) * half, 1
    if SPLITS > 1:  # (only the last part to arrive writes, and counts in)
        acc1, acc2, squares, last = _sum_splits(acc1, acc2, squares, workspace_ptr, arrivals_ptr, output, tile % SPLITS,
                                                SPLITS, BLOCK_M, N_QKV, True, True)
        written, count = tl.where(last, written, 0), tl.where(last, 1, 0)
    _rope_store(acc1, acc2, squares, rows, pairs, pairs < written, bias_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr,
                M, D, tokens, first_slot, slots, stride_cos_b, stride_cos_t, eps, HEADS, HEAD_DIM, HAS_BIAS)
    _count_in(counter_ptr, count)


@triton.jit
def _attention_tile(tile, q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, out_ptr, partial_ptr, stats_ptr,
                    arrivals_ptr, wait_ptr, need, counter_ptr, watch_ptr, batch, tokens, slots, scale, key_parts,
                    HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr,
                    DIM_CHUNK: tl.constexpr, DOT: tl.constexpr):
    """Part s of the keys of folded query rows block i of sample b (`range_attention`'s program (i, b, s)), once
    `wait` reaches `need` (every q/k/v tile of the layer); the block's last part to finish combines the parts into
    `out` and counts the block in (`counter`)."""
    rows_per_sample = tokens * HEADS
    blocks = tl.cdiv(rows_per_sample, BLOCK_M)
    sample = tile // (blocks * key_parts)
    block = tile // key_parts % blocks
    part = tile % key_parts
    _wait_for(wait_ptr, need, watch_ptr)
    rows = block * BLOCK_M + tl.arange(0, BLOCK_M)
    acc, running_max, total = _attention_part(q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, sample, rows,
                                              rows_per_sample, HEADS, slots, scale, part, key_parts, HEAD_DIM, DOT,
                                              BLOCK_M, BLOCK_N, True, ".cg")
    last = _combine_key_parts(acc, running_max, total, partial_ptr, stats_ptr, arrivals_ptr,
                              out_ptr + sample * rows_per_sample * HEAD_DIM, sample, block, blocks, part, batch,
                              rows_per_sample, key_parts, HEAD_DIM, BLOCK_M, DIM_CHUNK)
    _count_in(counter_ptr, tl.where(last, 1, 0))  # (every part counts in, all but the last with 0)


@triton.jit(do_not_specialize=["reset"])  # (0 for `--check`'s counted launches, 1 otherwise: one variant)
def _expert_layers_kernel(
    x_ptr, attention_scale_ptr, qkv_ptr, o_ptr, mlp_scale_ptr, gate_up_ptr, down_ptr, offsets_ptr, cos_ptr, sin_ptr, key_ptr,
    value_ptr, first_ptr, row_ends_ptr, qkv_bias_ptr, o_gate_ptr, gate_up_bias_ptr, down_gate_ptr, q_ptr, attended_ptr,
    hidden_ptr, partial_ptr, stats_ptr, qkv_parts_ptr, o_parts_ptr, gate_up_parts_ptr, down_parts_ptr, state_ptr,
    watch_ptr, order_ptr, timeline_ptr,
    layers, M, D, F, tokens, first_slot, slots, eps, scale, key_parts, stride_xm, stride_cos_b, stride_cos_t, stride_qk,
    stride_qn, stride_ok, stride_on, stride_gk, stride_gn, stride_dk, stride_dn, layer_cache, reset,
    HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, BLOCK_M: tl.constexpr, N_QKV: tl.constexpr, N_O: tl.constexpr,
    N_GATE_UP: tl.constexpr, N_DOWN: tl.constexpr, BLOCK_K: tl.constexpr, ATTENTION_M: tl.constexpr,
    ATTENTION_N: tl.constexpr, DIM_CHUNK: tl.constexpr, DOT: tl.constexpr, PREFETCH: tl.constexpr,
    QKV_SPLITS: tl.constexpr, O_SPLITS: tl.constexpr, GATE_UP_SPLITS: tl.constexpr, DOWN_SPLITS: tl.constexpr,
    ADARMS: tl.constexpr, ORDERED: tl.constexpr,
    ALIGN: tl.constexpr, TIMELINE: tl.constexpr,
):
    half: tl.constexpr = HEAD_DIM // 2
    batch = M // tokens
    row_blocks = tl.cdiv(M, BLOCK_M)
    attention_blocks = batch * tl.cdiv(tokens * HEADS, ATTENTION_M)
    qkv_tiles = row_blocks * tl.cdiv((HEADS + 2) * half, N_QKV)  # (output tiles; with QKV_SPLITS parts each, ...)
    o_tiles = row_blocks * tl.cdiv(D, N_O)
    gate_up_tiles = row_blocks * tl.cdiv(F, N_GATE_UP)
    down_tiles = row_blocks * tl.cdiv(D, N_DOWN)
    qkv_end = qkv_tiles * QKV_SPLITS
    attention_end = qkv_end + attention_blocks * key_parts
    o_end = attention_end + o_tiles * O_SPLITS
    gate_up_end = o_end + gate_up_tiles * GATE_UP_SPLITS
    per_layer = gate_up_end + down_tiles * DOWN_SPLITS
    # state: [0] the next ticket, [1] programs finished, then per layer: [0] q/k/v tiles done, [1] attention blocks
    # done, o-projection / gate-up / down-projection tiles done per row block, key parts arrived per attention block,
    # split-K parts arrived per o-projection, down-projection, q/k/v and gate/up tile
    layer_state = 2 + 3 * row_blocks + attention_blocks + o_tiles + down_tiles + qkv_tiles + gate_up_tiles
    ticket = tl.atomic_add(state_ptr, 1)
    while ticket < layers * per_layer:
        if ORDERED:  # (`--check`: the tiles in another order its waits allow, `order[ticket]`)
            work = tl.load(order_ptr + ticket)
        else:
            work = ticket
        if TIMELINE:
            started = globaltimer()
        layer = work // per_layer
        tile = work % per_layer
        counters = state_ptr + 2 + layer * layer_state
        o_done = counters + 2
        gate_up_done = o_done + row_blocks
        down_done = gate_up_done + row_blocks
        o_arrivals = down_done + row_blocks + attention_blocks
        qkv_arrivals = o_arrivals + o_tiles + down_tiles
        offsets_at = offsets_ptr + layer * 4  # (its q/k/v, o, gate/up and down weights' from layer 0's)
        if tile < qkv_end:  # (layer 0 waits for nothing: its own down-projection counters, need 0)
            previous = down_done - tl.where(layer > 0, layer_state, 0)
            _qkv_tile(tile, x_ptr, attention_scale_ptr + layer * D,
                      qkv_ptr + tl.multiple_of(tl.load(offsets_at), ALIGN),
                      qkv_bias_ptr + layer * (HEADS + 2) * HEAD_DIM, cos_ptr, sin_ptr, q_ptr,
                      key_ptr + layer * layer_cache, value_ptr + layer * layer_cache, previous,
                      tl.where(layer > 0, tl.cdiv(D, N_DOWN), 0), counters, watch_ptr, qkv_parts_ptr, qkv_arrivals, M,
                      D, tokens, first_slot, slots, stride_xm, stride_qk, stride_qn, stride_cos_b, stride_cos_t, eps,
                      HEADS, HEAD_DIM, BLOCK_M, N_QKV, BLOCK_K, QKV_SPLITS, DOT, PREFETCH, ADARMS)
        elif tile < attention_end:
            _attention_tile(tile - qkv_end, q_ptr, key_ptr + layer * layer_cache, value_ptr + layer * layer_cache,
                            first_ptr, row_ends_ptr, attended_ptr, partial_ptr, stats_ptr, down_done + row_blocks,
                            counters, qkv_tiles, counters + 1, watch_ptr, batch, tokens, slots, scale, key_parts, HEADS,
                            HEAD_DIM, ATTENTION_M, ATTENTION_N, DIM_CHUNK, DOT)
        elif tile < o_end:
            _residual_tile(tile - attention_end, x_ptr, attended_ptr, HEADS * HEAD_DIM,
                           o_ptr + tl.multiple_of(tl.load(offsets_at + 1), ALIGN), stride_ok, stride_on,
                           o_gate_ptr + layer * D, counters + 1, 0, attention_blocks, o_done, watch_ptr, o_parts_ptr,
                           o_arrivals, M, D, HEADS * HEAD_DIM, stride_xm, BLOCK_M, N_O, BLOCK_K, O_SPLITS, DOT,
                           PREFETCH, ADARMS, True)
        elif tile < gate_up_end:
            _gate_up_tile(tile - o_end, x_ptr, mlp_scale_ptr + layer * D,
                          gate_up_ptr + tl.multiple_of(tl.load(offsets_at + 2), ALIGN),
                          gate_up_bias_ptr + layer * 2 * F, hidden_ptr, o_done, gate_up_done, watch_ptr,
                          gate_up_parts_ptr, qkv_arrivals + qkv_tiles, M, D, F, stride_xm, stride_gk, stride_gn, eps,
                          BLOCK_M, N_O, N_GATE_UP, BLOCK_K, GATE_UP_SPLITS, DOT, PREFETCH, ADARMS)
        else:
            _residual_tile(tile - gate_up_end, x_ptr, hidden_ptr, F,
                           down_ptr + tl.multiple_of(tl.load(offsets_at + 3), ALIGN), stride_dk, stride_dn,
                           down_gate_ptr + layer * D, gate_up_done, 1, tl.cdiv(F, N_GATE_UP), down_done, watch_ptr,
                           down_parts_ptr, o_arrivals + o_tiles, M, D, F, stride_xm, BLOCK_M, N_DOWN, BLOCK_K,
                           DOWN_SPLITS, DOT, PREFETCH, ADARMS, True)
        if TIMELINE:  # (when each tile started and ended, ns, and on which multiprocessor)
            tl.store(timeline_ptr + work * 3, started)
            tl.store(timeline_ptr + work * 3 + 1, globaltimer())
            tl.store(timeline_ptr + work * 3 + 2, smid().to(tl.int64))
        ticket = tl.atomic_add(state_ptr, 1)
    # the last program out (all others have taken their last ticket): where a wait was abandoned, nothing of the
    # launch may pass for actions, so `x` becomes NaN; every counter goes back to 0 for the next launch (`reset` 0
    # keeps them, for `--check` to count)
    if tl.atomic_add(state_ptr + 1, 1, sem="acq_rel") == tl.num_programs(0) - 1:
        if tl.atomic_add(watch_ptr, 0) != 0:
            for start in range(0, M * D, 1024):
                offsets = start + tl.arange(0, 1024)
                tl.store(x_ptr + offsets // D * stride_xm + offsets % D, float("nan"), mask=offsets < M * D)
        if reset != 0:
            size = 2 + layers * layer_state
            for start in range(0, size, 1024):
                offsets = start + tl.arange(0, 1024)
                tl.store(state_ptr + offsets, 0, mask=offsets < size)


# -- the op ---------------------------------------------------------------------------------------------------------


def expert_layers_(
    x: torch.Tensor,  # [M, D] (M = B T), updated in place
    attention_scales: torch.Tensor,  # [L, D]: each layer's attention norm scale (`1 + weight`, adaRMS: this step's)
    qkv: Sequence[torch.Tensor],  # L x [D, (N + 2) H]: `[in, out]` views of the layers' weights (q | k | v columns)
    o: Sequence[torch.Tensor],  # L x [N H, D]
    mlp_scales: torch.Tensor,  # [L, D]
    gate_up: Sequence[torch.Tensor],  # L x [D, 2 F] (gate | up columns)
    down: Sequence[torch.Tensor],  # L x [F, D]
    cos: torch.Tensor,  # [B or 1, T, H] float32: the action tokens' RoPE tables
    sin: torch.Tensor,
    key_cache: torch.Tensor,  # [L, B, S, H], the action tokens' slots written here
    value_cache: torch.Tensor,
    first: torch.Tensor,  # long [B]: each sample's first visible slot
    row_ends: torch.Tensor,  # long [T]: where each action token's keys end (exclusive)
    first_slot: int,  # the action tokens' first slot
    eps: float,
    qkv_bias: torch.Tensor | None = None,  # π0.5: [L, (N + 2) H], the attention norms' shifts through q/k/v
    o_gate: torch.Tensor | None = None,  # π0.5: [L, D]
    gate_up_bias: torch.Tensor | None = None,  # π0.5: [L, 2 F]
    down_gate: torch.Tensor | None = None,  # π0.5: [L, D]
    *,
    tiling: Tiling | None = None,
    programs: int | None = None,
    launch: Callable[..., Any] | None = None,
    state: torch.Tensor | None = None,
    order: torch.Tensor | None = None,
    watch: torch.Tensor | None = None,
    timeline: torch.Tensor | None = None,
) -> Any:
    """Every layer of an Euler step on the action tokens `x`, in place and in one launch (module docstring): what
    `reference.expert_layers_` computes. `tiling`: `Tiling()` by default. `programs`: the grid (`default_programs`).
    `launch`: stands in for the kernel's launch (compiling without a GPU; what it returns is returned, else None).
    `state`: zeroed int32 counters of `state_size` for this launch alone, left as the launch counted (by default: the
    stream's, which each launch puts back to 0). `order`: int32, the tiles (numbered layer after layer, in ticket
    order) in the order the tickets hand them out; one an interpreted launch can follow
    (`benchmarks/persistent_layers.py`). `watch`: int32 `[2]`, whether a wait was abandoned and after how many spins
    (by default the device's, `watchdog`). `timeline`: int64 `[L * tiles per layer, 3]` (`phase_tiles`), where the
    launch writes when each tile (numbered layer after layer, in ticket order) started and ended (`%globaltimer`,
    ns) and on which multiprocessor it ran (not in triton's interpreter)."""
    tiling = tiling or Tiling()
    rows, width = x.shape
    depth, batch, slots, head_dim = key_cache.shape
    tokens = rows // batch
    heads = o[0].shape[0] // head_dim
    mlp_width = down[0].shape[0]
    if value_cache.stride() != key_cache.stride() or key_cache[0].stride() != (slots * head_dim, head_dim, 1):
        raise ValueError(f"expert_layers_: the caches must be [L, B, S, H] buffers, each layer's contiguous; got strides "
                         f"{tuple(key_cache.stride())} and {tuple(value_cache.stride())} for shape {tuple(key_cache.shape)}")
    q = x.new_empty(rows, heads * head_dim)
    attended = x.new_empty(rows, heads * head_dim)
    hidden = x.new_empty(rows, mlp_width)
    partial = x.new_empty(tiling.key_parts, rows * heads, head_dim, dtype=torch.float32)
    stats = x.new_empty(2, tiling.key_parts, rows * heads, dtype=torch.float32)
    row_blocks = cdiv(rows, tiling.m)
    qkv_parts, o_parts, gate_up_parts, down_parts = (  # each phase's split-K workspace (its tiles' parts; the layers
        # take turns in it), or `x` where the phase is not split (never read); q/k/v's outputs are column pairs
        x if splits == 1 else split_workspace(x, row_blocks * cdiv(outputs, columns), tiling.m, columns, splits)
        for outputs, columns, splits in (((heads + 2) * head_dim // 2, tiling.qkv, tiling.qkv_splits),
                                         (width, tiling.o, tiling.o_splits),
                                         (mlp_width, tiling.gate_up, tiling.gate_up_splits),
                                         (width, tiling.down, tiling.down_splits)))
    if watch is not None and (watch.shape != (2,) or watch.dtype != torch.int32 or watch.device != x.device):
        raise ValueError(f"expert_layers_: a watch is int32 [2] on {x.device}; got {watch.dtype} {tuple(watch.shape)} on "
                         f"{watch.device}")
    if timeline is not None:
        tickets = depth * sum(phase_tiles(rows, tokens, heads, head_dim, width, mlp_width, tiling))
        if INTERPRETING or timeline.shape != (tickets, 3) or timeline.dtype != torch.int64:
            raise ValueError(f"expert_layers_: a timeline is int64 [{tickets}, 3], read from a GPU's clock (not in "
                             f"triton's interpreter); got {timeline.dtype} {tuple(timeline.shape)} on {timeline.device}")
    reset = state is None
    if state is None:
        state = zeroed_counters(x.device, state_size(depth, rows, tokens, heads, head_dim, width, mlp_width, tiling))
    programs = programs or default_programs(x.device, tiling)
    attention_scales, mlp_scales = attention_scales.contiguous(), mlp_scales.contiguous()  # (layer l's at l * D)
    adarms = [x] * 4 if qkv_bias is None else [t.contiguous() for t in (qkv_bias, o_gate, gate_up_bias, down_gate)]
    arguments = (
        x, attention_scales, qkv[0], o[0], mlp_scales, gate_up[0], down[0], weight_offsets((qkv, o, gate_up, down), x.device),
        cos, sin, key_cache, value_cache, first, row_ends, *adarms, q, attended, hidden, partial, stats, qkv_parts,
        o_parts, gate_up_parts, down_parts, state, watchdog(x.device) if watch is None else watch,
        state if order is None else order, state if timeline is None else timeline, depth, rows, width, mlp_width, tokens, first_slot, slots, eps,
        head_dim**-0.5, tiling.key_parts, x.stride(0), cos.stride(0) if cos.shape[0] > 1 else 0, cos.stride(1),
        *qkv[0].stride(), *o[0].stride(), *gate_up[0].stride(), *down[0].stride(), key_cache.stride(0), int(reset),
    )
    options = {"HEADS": heads, "HEAD_DIM": head_dim, "BLOCK_M": tiling.m, "N_QKV": tiling.qkv, "N_O": tiling.o,
               "N_GATE_UP": tiling.gate_up, "N_DOWN": tiling.down, "BLOCK_K": tiling.k,
               "ATTENTION_M": tiling.attention_m, "ATTENTION_N": tiling.attention_n,
               "DIM_CHUNK": min(head_dim, 4096 // tiling.attention_m), "DOT": dot_dtype(o[0].dtype),
               "PREFETCH": tiling.prefetch and not INTERPRETING, "ADARMS": qkv_bias is not None,
               "QKV_SPLITS": tiling.qkv_splits, "O_SPLITS": tiling.o_splits,
               "GATE_UP_SPLITS": tiling.gate_up_splits, "DOWN_SPLITS": tiling.down_splits, "ORDERED": order is not None,
               "TIMELINE": timeline is not None, "ALIGN": WEIGHT_ALIGNMENT // o[0].element_size(),
               "num_warps": tiling.warps, "num_stages": tiling.stages}
    if launch is not None:
        return launch(_expert_layers_kernel, (programs,), arguments, options)
    _expert_layers_kernel[(programs,)](*arguments, **options)
    return None


SPINS = 1 << 22  # a wait's spins before it is abandoned: a few seconds (one atomic read of L2 per spin), where a
# wait the kernel's order allows ends within microseconds
_watches: dict[torch.device, torch.Tensor] = {}


def watchdog(device: torch.device) -> torch.Tensor:
    """int32 `[2]` on `device`, read and written by every persistent launch there: `[0]` whether a launch abandoned
    a wait that did not end (0: none did; never reset: once set, every later launch gives up its waits at once and
    returns NaN, so a process never samples with the launch again), `[1]` the spins before a wait is abandoned
    (`SPINS`). Made on first use, by an eager launch: one made while a CUDA graph is captured would be zeroed again
    at each replay, so a capture that finds none raises (sampling's graphs capture after an eager call)."""
    device = _indexed(device)
    watch = _watches.get(device)
    if watch is None:
        if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
            raise RuntimeError("the persistent launch's watchdog is made by an eager launch on its GPU before a CUDA "
                               "graph captures one")
        with torch.inference_mode(False):  # (a plain tensor, whichever mode the first launch ran in)
            watch = _watches[device] = torch.zeros(2, dtype=torch.int32, device=device)
            watch[1] = SPINS
    return watch


def abandoned(device: torch.device) -> bool:
    """Whether a persistent launch on `device` abandoned a wait (`watchdog`): a synchronization fault of the kernel
    on this GPU, whose launches then return NaN. Reads the GPU (synchronizes)."""
    watch = _watches.get(_indexed(device))
    return watch is not None and bool(watch[0] != 0)


def _indexed(device: torch.device) -> torch.device:
    """`device` with its index (a CUDA device without one: the current GPU), as tensors name theirs."""
    return torch.device("cuda", torch.cuda.current_device()) if device.type == "cuda" and device.index is None else device


WEIGHT_ALIGNMENT = 16  # bytes: every layer's weights start at a multiple of this (the kernel's loads assume it)
# `weight_offsets` by (device, dtype, layer 0's shapes and strides, every weight's address): a few hundred bytes each,
# never dropped (a captured CUDA graph reads its table's address at every replay)
_offset_tables: dict[tuple[Any, ...], torch.Tensor] = {}


def weight_offsets(weights: Sequence[Sequence[torch.Tensor]], device: torch.device) -> torch.Tensor:
    """int64 `[L, 4]` on `device`: where each layer's q/k/v, o, gate/up and down weights (`weights`: the four lists)
    start, in elements from layer 0's. Made on first use per set of weights (checked then) and kept: a CUDA graph's
    capture finds it made by the eager runs before it. Raises `ValueError` where the layers' weights differ in shape,
    strides or dtype, or one does not start `WEIGHT_ALIGNMENT`-aligned."""
    key = (device, weights[0][0].dtype, *((each[0].shape, each[0].stride()) for each in weights),
           *(t.data_ptr() for each in weights for t in each))
    table = _offset_tables.get(key)
    if table is not None:
        return table
    rows = []
    for name, each in zip(("qkv", "o", "gate_up", "down"), weights):
        first = each[0]
        for layer, t in enumerate(each):
            if (t.shape, t.stride(), t.dtype) != (first.shape, first.stride(), first.dtype):
                raise ValueError(f"expert_layers_: layer {layer}'s {name} weight is {tuple(t.shape)} with strides "
                                 f"{t.stride()} in {t.dtype}, layer 0's {tuple(first.shape)} with {first.stride()} in "
                                 f"{first.dtype}: one launch reads every layer's weights alike")
            if t.data_ptr() % WEIGHT_ALIGNMENT:
                raise ValueError(f"expert_layers_: layer {layer}'s {name} weight starts at an address that is not a "
                                 f"multiple of {WEIGHT_ALIGNMENT} bytes")
        rows.append([(t.data_ptr() - first.data_ptr()) // first.element_size() for t in each])
    table = _offset_tables[key] = torch.tensor(rows, dtype=torch.int64).t().contiguous().to(device)
    return table


def default_programs(device: torch.device, tiling: Tiling) -> int:
    """The grid: `tiling.per_sm` programs per multiprocessor of a GPU; 4 in the interpreter."""
    return tiling.per_sm * torch.cuda.get_device_properties(device).multi_processor_count if device.type == "cuda" else 4


def state_size(depth: int, rows: int, tokens: int, heads: int, head_dim: int, width: int, mlp_width: int,
               tiling: Tiling) -> int:
    """The counters of a launch: the next ticket, the programs finished, and per layer the q/k/v tiles and attention
    blocks done, the o-projection, gate/up and down-projection tiles done per row block, the key parts arrived per
    attention block, and the split-K parts arrived per o-projection, down-projection, q/k/v and gate/up tile
    (`_expert_layers_kernel`'s layout): per phase its tickets over their parts (`phase_tiles`)."""
    parts = (tiling.qkv_splits, tiling.key_parts, tiling.o_splits, tiling.gate_up_splits, tiling.down_splits)
    tiles = phase_tiles(rows, tokens, heads, head_dim, width, mlp_width, tiling)
    return 2 + depth * (2 + 3 * cdiv(rows, tiling.m) + sum(each // split for each, split in zip(tiles, parts)))


PHASES = ("q/k/v", "attention", "o-projection", "gate/up", "down-projection")


def phase_tiles(rows: int, tokens: int, heads: int, head_dim: int, width: int, mlp_width: int, tiling: Tiling) -> list[int]:
    """The tiles of each phase of a layer (`PHASES`), in the order a launch hands them out (`_expert_layers_kernel`'s
    tickets; the attention's: its blocks' key parts, split projections': their parts)."""
    row_blocks = cdiv(rows, tiling.m)
    return [row_blocks * cdiv((heads + 2) * head_dim // 2, tiling.qkv) * tiling.qkv_splits,
            rows // tokens * cdiv(tokens * heads, tiling.attention_m) * tiling.key_parts,
            row_blocks * cdiv(width, tiling.o) * tiling.o_splits,
            row_blocks * cdiv(mlp_width, tiling.gate_up) * tiling.gate_up_splits,
            row_blocks * cdiv(width, tiling.down) * tiling.down_splits]
