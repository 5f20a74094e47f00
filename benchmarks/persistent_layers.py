"""An experiment for issue 37: every decoder layer of the action expert in one Euler step as one persistent launch,
against the five fused kernels per layer that run it today (90 launches for π0's 18 layers).

`benchmarks/persistent_mlp.py` does this for the MLP half of one layer; this takes the same scheme to the whole step
of the suffix (docs/gpu.md, "Where the next milliseconds are"):

- one launch of as many programs as the GPU has multiprocessors; each takes tiles in ticket order from an atomic
  counter, layer after layer: the q/k/v projection's tiles (RMSNorm, RoPE, k and v into the layer's cache), the
  attention's (folded query rows of a sample and one part of their keys; the last part to finish combines them),
  then the o-projection's, gate/up's and the down-projection's (`persistent_mlp`'s tiles);
- a tile waits on counters for what it reads: q/k/v of row block r for the previous layer's down-projection of r,
  the attention for every q/k/v tile of its layer, the o-projection for every attention block, gate/up for the
  o-projection of its row block, the down-projection for gate/up's. The buffers between phases (q, the attention's
  output, the MLP's hidden activations, the key parts) are one per launch, reused by every layer: each is written
  again only after every reader of the layer before has counted in (the chain of waits above);
- a tile waits only on tiles handed out before it, whose programs are already running: no deadlock, and triton's
  interpreter (programs one after another) runs it too. Nothing ever waits there, so `--check` there also records
  what each tile waits for (`wait_graph`, from the kernel's own waits and count-ins) and runs the tiles in other
  orders those waits allow (`orders`): a read or write that no wait protects is likely to come out wrong in one (as a
  wait on the previous layer's gate/up instead of its down-projection does, or an o-projection not waiting for the
  attention: both checked once by hand);
- a waiting tile first asks its weights into L2; the last program to finish puts the counters back to 0, so the
  next launch needs no memset (one launch per step, nothing else).

The numbers are those of `pi0_torch.kernels.reference` (float32 sums, bf16 outputs), not bit for bit (no split-K).
π0's layers, and π0.5's with their adaRMS biases and residual gates (`AdaRMS`); one kv head, every action token
seeing the whole cache up to the step's last slot. Not used by sampling: this measures whether it would pay.

    python benchmarks/persistent_layers.py --check              # CPU: triton's interpreter, small float32 shapes
    python benchmarks/persistent_layers.py --compile 90         # CPU: compile for sm_90 (ptxas), print its use
    python benchmarks/persistent_layers.py --bench              # CUDA: 18 full-size layers, bf16, batch 1 and 8
"""

from __future__ import annotations

import functools
import itertools
import os
import random
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch.utils._pytree import tree_map_only

if "--check" in sys.argv and not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")  # (before triton is imported)

import triton
import triton.language as tl

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from persistent_mlp import (
    _count_in,
    _down_tile,
    _gate_up_tile,
    _o_tile,
    _prefetch_weights,
    _tile_at,
    _wait_for,
    compile_variants,
    experiment_main,
    print_times,
)

from pi0_torch.inference.fused_pass import FUSED_TOLERANCE
from pi0_torch.inference.graphs import relative_deviation
from pi0_torch.kernels import reference
from pi0_torch.kernels.triton_kernels import (
    INTERPRETING,
    _attention_part,
    _combine_key_parts,
    _matmul_tiles,
    _rope_store,
    cdiv,
    dot_dtype,
)
from pi0_torch.models.layers import rope_cos_sin


class Tiling(NamedTuple):
    """Output columns per tile of each GEMM phase (q/k/v in column pairs, o-projection, gate/up, down-projection), the
    GEMMs' reduction block and rows per tile, the attention's folded query rows and keys per block and its key parts,
    warps, pipeline stages, whether a waiting tile prefetches its weights (never in the interpreter), and programs
    per multiprocessor."""

    qkv: int = 16
    o: int = 16
    gate_up: int = 32
    down: int = 16
    k: int = 64
    m: int = 64
    attention_m: int = 16
    attention_n: int = 32
    key_parts: int = 4
    warps: int = 4
    stages: int = 3
    prefetch: bool = True
    per_sm: int = 1


class Layers(NamedTuple):
    """The expert's layers stacked (`[L, ...]`): the norms' scales (`1 + weight`) and the projections' weights as
    `[in, out]` views of `nn.Linear` weights (q/k/v columns q | k | v, gate/up columns gate | up)."""

    attention_scale: torch.Tensor  # [L, D]
    qkv: torch.Tensor  # [L, D, (N + 2) H]
    o: torch.Tensor  # [L, N H, D]
    mlp_scale: torch.Tensor  # [L, D]
    gate_up: torch.Tensor  # [L, D, 2 F]
    down: torch.Tensor  # [L, F, D]


class Cache(NamedTuple):
    """The step's k/v cache of every layer and what the attention sees of it."""

    key: torch.Tensor  # [L, B, S, H]: the prefix written, the action tokens' slots written by the step
    value: torch.Tensor
    first: torch.Tensor  # long [B]: each sample's first visible slot
    row_ends: torch.Tensor  # long [T]: the slot each action token's keys end at (exclusive)
    first_slot: int  # the action tokens' first slot


class AdaRMS(NamedTuple):
    """π0.5's time conditioning of the step, per layer: the norms' shifts through the projections after them (biases),
    and the residual gates."""

    qkv_bias: torch.Tensor  # [L, (N + 2) H]
    o_gate: torch.Tensor  # [L, D]
    gate_up_bias: torch.Tensor  # [L, 2 F]
    down_gate: torch.Tensor  # [L, D]


class Step(NamedTuple):
    """What an Euler step's layers read besides the action tokens."""

    layers: Layers
    cos: torch.Tensor  # [B or 1, T, H] float32: `rope_cos_sin`'s tables of the action tokens
    sin: torch.Tensor
    cache: Cache
    adarms: AdaRMS | None  # π0.5's; None for π0

    def fresh(self) -> Step:
        """The same with a copy of the cache (a step writes its action tokens' keys and values)."""
        return self._replace(cache=self.cache._replace(key=self.cache.key.clone(), value=self.cache.value.clone()))


# -- the kernel -----------------------------------------------------------------------------------------------------


@triton.jit
def _qkv_tile(tile, x_ptr, scale_ptr, w_ptr, bias_ptr, cos_ptr, sin_ptr, q_ptr, key_ptr, value_ptr, wait_ptr, need,
              counter_ptr, M, D, tokens, first_slot, slots, stride_xm, stride_wk, stride_wn, stride_cos_b, stride_cos_t,
              eps, HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, BLOCK_M: tl.constexpr, N_QKV: tl.constexpr,
              BLOCK_K: tl.constexpr, DOT: tl.constexpr, PREFETCH: tl.constexpr, HAS_BIAS: tl.constexpr):
    """Column pairs `(c, c + H/2)` of q/k/v for row block r: RMSNorm, the projection (adaRMS: plus `bias`), RoPE; q into
    `q`, k and v into the layer's cache (`_rope_store`), once `wait[r]` reaches `need` (the previous layer's
    down-projection of r); then counted in (`counter`)."""
    half: tl.constexpr = HEAD_DIM // 2
    block, rows, pairs = _tile_at(tile, (HEADS + 2) * half, BLOCK_M, N_QKV)
    first_half = pairs // half * HEAD_DIM + pairs % half
    width = (HEADS + 2) * HEAD_DIM
    _prefetch_weights(w_ptr, stride_wk, stride_wn, first_half, D, width, BLOCK_K, PREFETCH)
    _prefetch_weights(w_ptr, stride_wk, stride_wn, first_half + half, D, width, BLOCK_K, PREFETCH)
    _wait_for(wait_ptr + block, need)
    acc1, acc2, squares = _matmul_tiles(x_ptr, stride_xm, scale_ptr, w_ptr, stride_wk, stride_wn, rows, first_half, half,
                                        M, 0, D, width, BLOCK_M, N_QKV, BLOCK_K, True, True, DOT, ".cg")
    _rope_store(acc1, acc2, squares, rows, pairs, pairs < (HEADS + 2) * half, bias_ptr, cos_ptr, sin_ptr, q_ptr,
                key_ptr, value_ptr, M, D, tokens, first_slot, slots, stride_cos_b, stride_cos_t, eps, HEADS, HEAD_DIM,
                HAS_BIAS)
    _count_in(counter_ptr, 1)


@triton.jit
def _attention_tile(tile, q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, out_ptr, partial_ptr, stats_ptr,
                    arrivals_ptr, wait_ptr, need, counter_ptr, batch, tokens, slots, scale, key_parts,
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
    _wait_for(wait_ptr, need)
    rows = block * BLOCK_M + tl.arange(0, BLOCK_M)
    acc, running_max, total = _attention_part(q_ptr, key_ptr, value_ptr, first_ptr, row_ends_ptr, sample, rows,
                                              rows_per_sample, HEADS, slots, scale, part, key_parts, HEAD_DIM, DOT,
                                              BLOCK_M, BLOCK_N, True, ".cg")
    last = _combine_key_parts(acc, running_max, total, partial_ptr, stats_ptr, arrivals_ptr,
                              out_ptr + sample * rows_per_sample * HEAD_DIM, sample, block, blocks, part, batch,
                              rows_per_sample, key_parts, HEAD_DIM, BLOCK_M, DIM_CHUNK)
    _count_in(counter_ptr, tl.where(last, 1, 0))  # (every part counts in, all but the last with 0)


@triton.jit
def _persistent_layers_kernel(
    x_ptr, attention_scale_ptr, qkv_ptr, o_ptr, mlp_scale_ptr, gate_up_ptr, down_ptr, cos_ptr, sin_ptr, key_ptr,
    value_ptr, first_ptr, row_ends_ptr, qkv_bias_ptr, o_gate_ptr, gate_up_bias_ptr, down_gate_ptr, q_ptr, attended_ptr,
    hidden_ptr, partial_ptr, stats_ptr, state_ptr, order_ptr, layers, M, D, F, tokens, first_slot, slots, eps, scale,
    key_parts, stride_xm, stride_cos_b, stride_cos_t, layer_qkv, stride_qk, stride_qn, layer_o, stride_ok, stride_on,
    layer_gate_up, stride_gk, stride_gn, layer_down, stride_dk, stride_dn, layer_cache, reset,
    HEADS: tl.constexpr, HEAD_DIM: tl.constexpr, BLOCK_M: tl.constexpr, N_QKV: tl.constexpr, N_O: tl.constexpr,
    N_GATE_UP: tl.constexpr, N_DOWN: tl.constexpr, BLOCK_K: tl.constexpr, ATTENTION_M: tl.constexpr,
    ATTENTION_N: tl.constexpr, DIM_CHUNK: tl.constexpr, DOT: tl.constexpr, PREFETCH: tl.constexpr,
    ADARMS: tl.constexpr, ORDERED: tl.constexpr,
):
    half: tl.constexpr = HEAD_DIM // 2
    batch = M // tokens
    row_blocks = tl.cdiv(M, BLOCK_M)
    attention_blocks = batch * tl.cdiv(tokens * HEADS, ATTENTION_M)
    qkv_end = row_blocks * tl.cdiv((HEADS + 2) * half, N_QKV)
    attention_end = qkv_end + attention_blocks * key_parts
    o_end = attention_end + row_blocks * tl.cdiv(D, N_O)
    gate_up_end = o_end + row_blocks * tl.cdiv(F, N_GATE_UP)
    per_layer = gate_up_end + row_blocks * tl.cdiv(D, N_DOWN)
    # state: [0] the next ticket, [1] programs finished, then per layer: [0] q/k/v tiles done, [1] attention blocks
    # done, o-projection / gate-up / down-projection tiles done per row block, key parts arrived per attention block
    layer_state = 2 + 3 * row_blocks + attention_blocks
    ticket = tl.atomic_add(state_ptr, 1)
    while ticket < layers * per_layer:
        if ORDERED:  # (`--check`: the tiles in another order its waits allow, `order[ticket]`)
            work = tl.load(order_ptr + ticket)
        else:
            work = ticket
        layer = work // per_layer
        tile = work % per_layer
        counters = state_ptr + 2 + layer * layer_state
        o_done = counters + 2
        gate_up_done = o_done + row_blocks
        down_done = gate_up_done + row_blocks
        if tile < qkv_end:  # (layer 0 waits for nothing: its own down-projection counters, need 0)
            previous = down_done - tl.where(layer > 0, layer_state, 0)
            _qkv_tile(tile, x_ptr, attention_scale_ptr + layer * D, qkv_ptr + layer * layer_qkv,
                      qkv_bias_ptr + layer * (HEADS + 2) * HEAD_DIM, cos_ptr, sin_ptr, q_ptr, key_ptr + layer * layer_cache,
                      value_ptr + layer * layer_cache, previous, tl.where(layer > 0, tl.cdiv(D, N_DOWN), 0), counters,
                      M, D, tokens, first_slot, slots, stride_xm, stride_qk, stride_qn, stride_cos_b, stride_cos_t, eps,
                      HEADS, HEAD_DIM, BLOCK_M, N_QKV, BLOCK_K, DOT, PREFETCH, ADARMS)
        elif tile < attention_end:
            _attention_tile(tile - qkv_end, q_ptr, key_ptr + layer * layer_cache, value_ptr + layer * layer_cache,
                            first_ptr, row_ends_ptr, attended_ptr, partial_ptr, stats_ptr, down_done + row_blocks,
                            counters, qkv_end, counters + 1, batch, tokens, slots, scale, key_parts, HEADS, HEAD_DIM,
                            ATTENTION_M, ATTENTION_N, DIM_CHUNK, DOT)
        elif tile < o_end:
            _o_tile(tile - attention_end, x_ptr, attended_ptr, o_ptr + layer * layer_o, o_gate_ptr + layer * D,
                    counters + 1, attention_blocks, o_done, M, D, HEADS * HEAD_DIM, stride_xm, HEADS * HEAD_DIM, stride_ok,
                    stride_on, BLOCK_M, N_O, BLOCK_K, DOT, PREFETCH, ADARMS)
        elif tile < gate_up_end:
            _gate_up_tile(tile - o_end, x_ptr, mlp_scale_ptr + layer * D, gate_up_ptr + layer * layer_gate_up,
                          gate_up_bias_ptr + layer * 2 * F, hidden_ptr, o_done, gate_up_done, M, D, F, stride_xm, stride_gk,
                          stride_gn, eps, BLOCK_M, N_O, N_GATE_UP, BLOCK_K, DOT, PREFETCH, ADARMS)
        else:
            _down_tile(tile - gate_up_end, x_ptr, hidden_ptr, down_ptr + layer * layer_down, down_gate_ptr + layer * D,
                       gate_up_done, down_done, M, D, F, stride_xm, stride_dk, stride_dn, BLOCK_M, N_GATE_UP, N_DOWN,
                       BLOCK_K, DOT, PREFETCH, ADARMS, True)
        ticket = tl.atomic_add(state_ptr, 1)
    # the last program out puts every counter back to 0 for the next launch (all others have taken their last ticket;
    # `reset` 0 keeps them, for `--check` to count)
    if (tl.atomic_add(state_ptr + 1, 1, sem="acq_rel") == tl.num_programs(0) - 1) & (reset != 0):
        size = 2 + layers * layer_state
        for start in range(0, size, 1024):
            offsets = start + tl.arange(0, 1024)
            tl.store(state_ptr + offsets, 0, mask=offsets < size)


_states: dict[tuple[torch.device, int], torch.Tensor] = {}  # zeroed once; each launch leaves them at 0


def persistent_layers_(x: torch.Tensor, step: Step, eps: float, tiling: Tiling | None = None, programs: int | None = None,
                       launch: Callable[..., Any] | None = None, state: torch.Tensor | None = None,
                       order: torch.Tensor | None = None) -> torch.Tensor:
    """Every layer of `step` on the action tokens `x` `[M, D]` (M = B T), in place and in one launch (module
    docstring): `x += attention(...) @ o; x += geglu(norm(x) @ gate_up) @ down` per layer (π0.5: with its adaRMS
    biases and gates), k and v written into the step's cache. `programs`: the grid (`default_programs`). `launch`:
    stands in for the kernel's launch (`--compile`). `state`: zeroed int32 counters of `state_size` for this launch
    alone, left as the launch counted (by default: counters kept per device and size, which each launch puts back to
    0). `order`: int32, the tiles (numbered layer after layer, in ticket order) in the order the tickets hand them
    out; one an interpreted launch can follow (`wait_graph`)."""
    layers, cos, sin, cache, adarms = step
    tiling = tiling or Tiling()
    rows, width = x.shape
    depth, batch, slots, head_dim = cache.key.shape
    tokens = rows // batch
    heads = layers.o.shape[1] // head_dim
    mlp_width = layers.down.shape[1]
    q = x.new_empty(rows, heads * head_dim)
    attended = x.new_empty(rows, heads * head_dim)
    hidden = x.new_empty(rows, mlp_width)
    partial = x.new_empty(tiling.key_parts, rows * heads, head_dim, dtype=torch.float32)
    stats = x.new_empty(2, tiling.key_parts, rows * heads, dtype=torch.float32)
    reset = state is None
    if state is None:
        size = state_size(depth, rows, tokens, heads, tiling)
        state = _states.get((x.device, size))
        if state is None:
            state = _states[(x.device, size)] = torch.zeros(size, dtype=torch.int32, device=x.device)
    programs = programs or default_programs(x.device, tiling)
    arguments = (
        x, layers.attention_scale, layers.qkv, layers.o, layers.mlp_scale, layers.gate_up, layers.down, cos, sin,
        cache.key, cache.value, cache.first, cache.row_ends, *(adarms or (x,) * 4), q, attended, hidden, partial, stats,
        state, state if order is None else order, depth, rows, width, mlp_width, tokens, cache.first_slot, slots, eps,
        head_dim**-0.5, tiling.key_parts, x.stride(0), cos.stride(0) if cos.shape[0] > 1 else 0, cos.stride(1),
        layers.qkv.stride(0), layers.qkv.stride(1), layers.qkv.stride(2), layers.o.stride(0), layers.o.stride(1),
        layers.o.stride(2), layers.gate_up.stride(0), layers.gate_up.stride(1), layers.gate_up.stride(2),
        layers.down.stride(0), layers.down.stride(1), layers.down.stride(2), cache.key.stride(0), int(reset),
    )
    options = {"HEADS": heads, "HEAD_DIM": head_dim, "BLOCK_M": tiling.m, "N_QKV": tiling.qkv, "N_O": tiling.o,
               "N_GATE_UP": tiling.gate_up, "N_DOWN": tiling.down, "BLOCK_K": tiling.k,
               "ATTENTION_M": tiling.attention_m, "ATTENTION_N": tiling.attention_n,
               "DIM_CHUNK": min(head_dim, 4096 // tiling.attention_m), "DOT": dot_dtype(layers.o.dtype),
               "PREFETCH": tiling.prefetch and not INTERPRETING, "ADARMS": adarms is not None, "ORDERED": order is not None,
               "num_warps": tiling.warps, "num_stages": tiling.stages}
    if launch is not None:
        return launch(_persistent_layers_kernel, (programs,), arguments, options)
    _persistent_layers_kernel[(programs,)](*arguments, **options)
    return x


def default_programs(device: torch.device, tiling: Tiling) -> int:
    """The grid: `tiling.per_sm` programs per multiprocessor of a GPU; 4 in the interpreter."""
    return tiling.per_sm * torch.cuda.get_device_properties(device).multi_processor_count if device.type == "cuda" else 4


def state_size(depth: int, rows: int, tokens: int, heads: int, tiling: Tiling) -> int:
    """The counters of a launch: the next ticket, the programs finished, and per layer the q/k/v tiles and attention
    blocks done, the o-projection, gate/up and down-projection tiles done per row block, and the key parts arrived
    per attention block (`_persistent_layers_kernel`'s layout)."""
    return 2 + depth * (2 + 3 * cdiv(rows, tiling.m) + rows // tokens * cdiv(tokens * heads, tiling.attention_m))


def expected_counts(shape: Shape, tiling: Tiling, programs: int) -> torch.Tensor:
    """What a launch leaves in its counters without the reset: every ticket taken (and one more per program), every
    program finished, each phase's tiles (the attention: its blocks) counted once, the key parts' arrivals back at 0."""
    rows, half = shape.batch * shape.tokens, shape.head_dim // 2
    row_blocks = cdiv(rows, tiling.m)
    attention_blocks = shape.batch * cdiv(shape.tokens * shape.heads, tiling.attention_m)
    per_row_block = [cdiv(shape.width, tiling.o), cdiv(shape.mlp_width, tiling.gate_up), cdiv(shape.width, tiling.down)]
    qkv_tiles = row_blocks * cdiv((shape.heads + 2) * half, tiling.qkv)
    tickets = qkv_tiles + attention_blocks * tiling.key_parts + row_blocks * sum(per_row_block)
    layer = [qkv_tiles, attention_blocks] + [each for each in per_row_block for _ in range(row_blocks)]
    layer += [0] * attention_blocks
    return torch.tensor([shape.depth * tickets + programs, programs] + layer * shape.depth, dtype=torch.int32)


def layer_by_layer_(x: torch.Tensor, step: Step, eps: float, ops: Any = reference) -> torch.Tensor:
    """The same, five ops per layer: `pi0_torch.kernels.reference`'s, or (`ops=fused_ops`) today's fused kernels (on
    CUDA; cuBLAS from `CUBLAS_ROWS` rows)."""
    layers, cos, sin, cache, adarms = step
    batch, heads, head_dim = cache.key.shape[1], layers.o.shape[1] // cache.key.shape[-1], cache.key.shape[-1]
    for layer in range(layers.qkv.shape[0]):
        key, value = cache.key[layer], cache.value[layer]
        qkv_bias, o_gate, gate_up_bias, down_gate = (None,) * 4 if adarms is None else (each[layer] for each in adarms)
        q = ops.norm_qkv_rope(x, layers.attention_scale[layer], qkv_bias, layers.qkv[layer], cos, sin, key, value,
                              cache.first_slot, eps)
        attended = ops.range_attention(q.view(batch, -1, heads, head_dim), key, value, cache.first, cache.row_ends)
        ops.matmul_residual_(x, attended, layers.o[layer], o_gate)
        hidden = ops.norm_gate_up_geglu(x, layers.mlp_scale[layer], gate_up_bias, layers.gate_up[layer], eps)
        ops.matmul_residual_(x, hidden, layers.down[layer], down_gate)
    return x


class _FusedOps:
    """Today's fused ops (`pi0_torch.kernels.ops`), as `layer_by_layer_` calls them."""

    def __getattr__(self, name: str) -> Callable[..., Any]:
        from pi0_torch.kernels import ops

        return lambda *args: ops.call(getattr(ops, name), *args)


fused_ops = _FusedOps()


# -- check, compile, bench ------------------------------------------------------------------------------------------


class Shape(NamedTuple):
    """The sizes of a step: layers, samples, action tokens per sample, ..., and whether π0.5's (adaRMS)."""

    depth: int
    batch: int
    tokens: int
    prefix: int  # cache slots before the action tokens (π0: the prefix and the state token)
    width: int
    heads: int
    head_dim: int
    mlp_width: int
    adarms: bool = False  # π0.5's layers


FULL = Shape(18, 1, 50, 817, 1024, 8, 256, 4096)  # π0's action expert, 3 cameras and 48 prompt tokens


def operands(shape: Shape, dtype: torch.dtype, device: torch.device, seed: int = 0) -> tuple[torch.Tensor, Step]:
    """The action tokens and the step (the cache's prefix random, samples after the first starting a few slots in):
    random, the weights as transposed `[out, in]` tensors (the engine's views)."""
    generator = torch.Generator(device).manual_seed(seed)
    depth, batch, tokens, prefix, width, heads, head_dim, mlp_width, adarms = shape

    def randn(*size: int, scale: float = 1.0) -> torch.Tensor:
        return (torch.randn(*size, generator=generator, device=device) * scale).to(dtype)

    def linear(inputs: int, outputs: int) -> torch.Tensor:  # [L, in, out] views of [L, out, in]
        return randn(depth, outputs, inputs, scale=inputs**-0.5).transpose(1, 2)

    layers = Layers(1 + randn(depth, width, scale=0.1), linear(width, (heads + 2) * head_dim),
                    linear(heads * head_dim, width), 1 + randn(depth, width, scale=0.1), linear(width, 2 * mlp_width),
                    linear(mlp_width, width))
    slots = prefix + tokens
    cos, sin = rope_cos_sin(torch.arange(prefix, slots, device=device).expand(batch, tokens), head_dim, 10_000.0)
    key, value = randn(depth, batch, slots, head_dim), randn(depth, batch, slots, head_dim)
    first = torch.arange(batch, device=device) * 3 % max(prefix, 1)
    cache = Cache(key, value, first, torch.full((tokens,), slots, device=device), prefix)
    conditioning = AdaRMS(randn(depth, (heads + 2) * head_dim), randn(depth, width), randn(depth, 2 * mlp_width),
                          randn(depth, width)) if adarms else None
    return randn(batch * tokens, width), Step(layers, cos, sin, cache, conditioning)


def deviation(got: torch.Tensor, got_step: Step, want: torch.Tensor, wanted: Step) -> float:
    """The largest relative deviation of the action tokens and the keys and values written."""
    return max(relative_deviation(got, want), relative_deviation(got_step.cache.key, wanted.cache.key),
               relative_deviation(got_step.cache.value, wanted.cache.value))


def check(device: torch.device, dtype: torch.dtype, shapes: list[Shape], tolerance: float, tilings: list[Tiling]) -> int:
    """The persistent launch against the reference for each shape and tiling: the action tokens and the caches it
    wrote, launched twice in a row (the second finds the counters the first put back to 0). The first tiling also
    launches once on counters of its own, kept and compared with `expected_counts`, and, on CUDA, runs today's ops
    (each other launch option is another compiled variant: on a GPU the check would take minutes)."""
    failures = 0
    for shape, tiling in itertools.product(shapes, tilings):
        x, step = operands(shape, dtype, device)
        wanted = step.fresh()
        want = layer_by_layer_(x.clone(), wanted, 1e-6)
        first = tiling == tilings[0]
        for launch in (1, 2, 3) if first else (2, 3):  # (1: counters kept and compared; 2 and 3 on those left at 0)
            got_step = step.fresh()
            programs = default_programs(device, tiling)
            size = state_size(shape.depth, shape.batch * shape.tokens, shape.tokens, shape.heads, tiling)
            state = torch.zeros(size, dtype=torch.int32, device=device) if launch == 1 else None
            got = persistent_layers_(x.clone(), got_step, 1e-6, tiling, programs, state=state)
            error = deviation(got, got_step, want, wanted)
            line = f"{shape} {tiling} launch {launch}: {error:.2e} against the reference"
            if state is not None:
                miscounted = (state.cpu() != expected_counts(shape, tiling, programs)).sum().item()
                line += f", {miscounted} of {size} counters not as expected"
                error = error if miscounted == 0 else float("inf")
                if device.type == "cuda":
                    today = step.fresh()
                    todays = layer_by_layer_(x.clone(), today, 1e-6, fused_ops)
                    line += f", today's ops {deviation(todays, today, want, wanted):.2e}"
            failures += not error <= tolerance
            print(line + ("" if error <= tolerance else f"  FAILED (bound {tolerance:g})"), flush=True)
    return failures


def wait_graph(run: Callable[[], Any]) -> list[set[int]]:
    """What each tile of an interpreted launch `run` waits for: the tiles (numbered in ticket order) counted in on the
    counter it waits on, where it needs more than 0. Recorded from the kernel itself: for one launch, its waits and
    count-ins (one of each per tile, in ticket order) go to a recorder instead (no waiting, no counting)."""
    import persistent_mlp

    waits: list[tuple[int, int]] = []  # (counter address, need) per tile
    counts: list[int] = []  # counter address per tile

    def value(each: Any) -> int:
        return int(each.handle.data.item()) if hasattr(each, "handle") else int(each)

    def wait_for(counter_ptr: Any, need: Any) -> None:
        waits.append((value(counter_ptr), value(need)))

    def count_in(counter_ptr: Any, count: Any) -> None:
        counts.append(value(counter_ptr))

    modules = (sys.modules[__name__], persistent_mlp)
    saved = [(module, module._wait_for, module._count_in) for module in modules]
    for module in modules:
        module._wait_for, module._count_in = wait_for, count_in
    try:
        run()
    finally:
        for module, wait, count in saved:
            module._wait_for, module._count_in = wait, count
    assert len(waits) == len(counts), (len(waits), len(counts))
    producers: dict[int, list[int]] = {}
    for tile, counter in enumerate(counts):
        producers.setdefault(counter, []).append(tile)
    return [set(producers.get(counter, ())) if need > 0 else set() for counter, need in waits]


def orders(graph: list[set[int]], seeds: int) -> Iterator[tuple[str, list[int]]]:
    """Orders of the tiles that `graph`'s waits allow: each tile as early as they let it (the later tile first where
    several could run: layers and phases running ahead of the ones before), then `seeds` random ones."""
    def order(pick: Callable[[list[int]], int]) -> list[int]:  # pick(ready tiles): the index of the next
        waiting_on = [set(each) for each in graph]
        readers: dict[int, list[int]] = {}
        for tile, needs in enumerate(graph):
            for need in needs:
                readers.setdefault(need, []).append(tile)
        ready, done = [tile for tile, needs in enumerate(waiting_on) if not needs], []
        while ready:
            tile = ready.pop(pick(ready))
            done.append(tile)
            for reader in readers.get(tile, ()):
                waiting_on[reader].discard(tile)
                if not waiting_on[reader]:
                    ready.append(reader)
        assert len(done) == len(graph), "the waits form a cycle"
        return done

    def at_random(seed: int) -> Callable[[list[int]], int]:
        chosen = random.Random(seed)
        return lambda ready: chosen.randrange(len(ready))

    yield "running ahead", order(lambda ready: ready.index(max(ready)))
    for seed in range(seeds):
        yield f"random {seed}", order(at_random(seed))


def check_orders(shape: Shape, tiling: Tiling, tolerance: float) -> int:
    """In the interpreter: the launch with its tiles in other orders its waits allow (`orders`) against the reference.
    A read or a write that no wait orders after what it must follow (a race on a GPU) is likely to come out wrong in
    one of them (a sample of the orders, not all), though the interpreter never runs two tiles at once."""
    device = torch.device("cpu")
    x, step = operands(shape, torch.float32, device)
    wanted = step.fresh()
    want = layer_by_layer_(x.clone(), wanted, 1e-6)
    size = state_size(shape.depth, shape.batch * shape.tokens, shape.tokens, shape.heads, tiling)

    def launch(order: torch.Tensor | None = None) -> float:
        got_step = step.fresh()
        state = torch.zeros(size, dtype=torch.int32, device=device)
        return deviation(persistent_layers_(x.clone(), got_step, 1e-6, tiling, state=state, order=order), got_step, want,
                         wanted)

    graph = wait_graph(launch)
    tiles = int(expected_counts(shape, tiling, programs=0)[0])  # (the tickets a launch hands out)
    assert len(graph) == tiles, f"recorded the waits of {len(graph)} tiles, not {tiles}"
    failures = 0
    for name, order in orders(graph, seeds=2):
        error = launch(torch.tensor(order, dtype=torch.int32))
        failures += not error <= tolerance
        print(f"{shape} {tiling}, {len(order)} tiles {name}: {error:.2e} against the reference"
              + ("" if error <= tolerance else f"  FAILED (bound {tolerance:g})"), flush=True)
    return failures


def compile_for(arch: int, tilings: list[Tiling]) -> int:
    """Compile the full-size variants (π0 at batch 1 and 8; π0.5 at batch 1 in the first tiling) for `arch` with
    triton's ptxas, on meta tensors (no GPU)."""
    def case(shape: Shape, tiling: Tiling) -> tuple[str, Callable[[Callable[..., Any]], Any]]:
        x, step = operands(shape._replace(depth=1), torch.bfloat16, torch.device("cpu"))
        x, step = x.to("meta"), tree_map_only(torch.Tensor, lambda tensor: tensor.to("meta"), step)
        name = f"batch {shape.batch}{' π0.5' if shape.adarms else ''} {tiling}"
        return name, lambda launch: persistent_layers_(x, step, 1e-6, tiling, programs=132, launch=launch)

    cases = [(FULL._replace(batch=batch), tiling) for batch, tiling in itertools.product((1, 8), tilings)]
    return compile_variants(arch, (case(shape, tiling) for shape, tiling in [*cases, (FULL._replace(adarms=True),
                                                                                      tilings[0])]))


def bench(tilings: list[Tiling]) -> None:
    """π0's 18 expert layers at full size, bf16, batch 1 and 8 (π0.5's at batch 1, in the first tiling): today's 90
    launches against one persistent launch, 20 steps in a CUDA graph (the weights, 600 MB, come from memory: more
    than the L2 cache holds)."""
    from pi0_torch.benchmark import graph_time

    device = torch.device("cuda")
    print(f"{torch.cuda.get_device_name(device)}, torch {torch.__version__}, triton {triton.__version__}; µs per Euler "
          "step of the 18 layers (today: 5 fused launches per layer), 20 steps in a CUDA graph")
    for shape, shape_tilings in ((FULL, tilings), (FULL._replace(batch=8), tilings), (FULL._replace(adarms=True), tilings[:1])):
        x, step = operands(shape, torch.bfloat16, device)
        want = layer_by_layer_(x.clone(), step.fresh(), 1e-6)
        results = []
        for tiling in [None, *shape_tilings]:  # (the action tokens accumulate step after step, as a chunk's do)
            run = (functools.partial(layer_by_layer_, x.clone(), step, 1e-6, fused_ops) if tiling is None else
                   functools.partial(persistent_layers_, x.clone(), step, 1e-6, tiling))
            seconds = graph_time(run, device, calls=20, repeats=5)
            got = (layer_by_layer_(x.clone(), step.fresh(), 1e-6, fused_ops) if tiling is None else
                   persistent_layers_(x.clone(), step.fresh(), 1e-6, tiling))
            results.append((tiling, seconds, relative_deviation(got, want)))
        title = f"{'π0.5' if shape.adarms else 'π0'} batch {shape.batch} ({shape.batch * shape.tokens} rows)"
        print_times(title, sum(weight.numel() * weight.element_size() for weight in step.layers), results,
                    "today's 90 launches")


TILINGS = [Tiling(), Tiling(k=128), Tiling(prefetch=False), Tiling(qkv=32, o=32, gate_up=64, down=32),
           Tiling(key_parts=2), Tiling(per_sm=2), Tiling(warps=8)]


def main() -> int:
    def check_here() -> int:
        if torch.cuda.is_available():  # (π0.5 in the first tiling: each tiling is minutes of compiling there)
            bound = FUSED_TOLERANCE[torch.bfloat16]
            return (check(torch.device("cuda"), torch.bfloat16, [FULL._replace(depth=2), FULL._replace(depth=2, batch=8)],
                          bound, TILINGS)
                    + check(torch.device("cuda"), torch.bfloat16, [FULL._replace(depth=2, adarms=True)], bound, TILINGS[:1]))
        # (the interpreter: small, float32; one and three samples, partial row and attention blocks; π0.5)
        shapes = [Shape(2, 1, 5, 7, 32, 2, 16, 48), Shape(2, 3, 6, 9, 48, 2, 16, 40, adarms=True)]
        tilings = [Tiling(qkv=8, o=16, gate_up=16, down=16, k=16, m=16, attention_m=16, attention_n=16, key_parts=2),
                   Tiling(qkv=16, o=32, gate_up=32, down=32, k=32, m=32, attention_m=32, attention_n=16, key_parts=1)]
        return (check(torch.device("cpu"), torch.float32, shapes, 1e-5, tilings)
                + sum(check_orders(shape, tilings[0], 1e-5) for shape in shapes))

    return experiment_main(__doc__, check_here, functools.partial(compile_for, tilings=TILINGS),
                           functools.partial(bench, TILINGS))


if __name__ == "__main__":
    sys.exit(main())
