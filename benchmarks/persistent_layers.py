"""Issue 37: every decoder layer of the action expert in one Euler step as one persistent launch
(`pi0_torch.kernels.persistent.expert_layers_`, which sampling runs under `sampling_kernels="persistent"`), checked
and timed against the five fused kernels per layer that run it by default (90 launches for π0's 18 layers).

The kernel's module docstring says how it works. What a CPU cannot show is its synchronization: triton's interpreter
runs one program after another, so nothing ever waits there. `--check` there therefore also counts what each counter
ends at (`expected_counts`), records what each tile waits for (`wait_graph`, from the kernel's own waits and
count-ins) and runs the tiles in other orders those waits allow (`orders`): a read or write that no wait protects is
likely to come out wrong in one (as a wait on the previous layer's gate/up instead of its down-projection does, or
an o-projection not waiting for the attention: both checked once by hand). On a GPU `--check` runs full-size layers
against the reference and today's ops, and `--bench` times the tilings (`TILINGS`) against today's launches. On
both, `--check` also launches with counters that never reach the waits: the launch must give up (`watchdog`) and
return NaN, not hang.

The numbers are those of `pi0_torch.kernels.reference` (float32 sums, bf16 outputs), not bit for bit (its sums go in
other orders). π0's layers, and π0.5's with their adaRMS biases and residual gates (`AdaRMS`); one kv head, every
action token seeing the whole cache up to the step's last slot. The weights here are stacked `[L, ...]` (each layer's
a view: their offsets from layer 0's are a whole stride apart); sampling passes the model's own, wherever they are.

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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from persistent_mlp import compile_variants, experiment_main, print_times

from pi0_torch.inference.checks import FUSED_TOLERANCE, relative_deviation
from pi0_torch.kernels import ops, persistent, reference
from pi0_torch.kernels.persistent import (
    PHASES,
    Tiling,
    default_programs,
    expert_layers_,
    phase_tiles,
    state_size,
)
from pi0_torch.kernels.triton_kernels import cdiv
from pi0_torch.kernels.reference import rope_cos_sin


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


# -- the launch and its references --------------------------------------------------------------------------------


def op_arguments(x: torch.Tensor, step: Step, eps: float) -> tuple[Any, ...]:
    """`expert_layers_`'s arguments for the action tokens `x` `[M, D]` (M = B T) and `step` (the layers' weights as
    lists of each layer's)."""
    layers, cos, sin, cache, adarms = step
    return (x, layers.attention_scale, list(layers.qkv), list(layers.o), layers.mlp_scale, list(layers.gate_up),
            list(layers.down), cos, sin, cache.key, cache.value, cache.first, cache.row_ends, cache.first_slot, eps,
            *(adarms or (None,) * 4))


def persistent_layers_(x: torch.Tensor, step: Step, eps: float, tiling: Tiling | None = None, programs: int | None = None,
                       launch: Callable[..., Any] | None = None, state: torch.Tensor | None = None,
                       order: torch.Tensor | None = None, watch: torch.Tensor | None = None,
                       timeline: torch.Tensor | None = None) -> Any:
    """Every layer of `step` on `x` in place, in one launch (`pi0_torch.kernels.persistent.expert_layers_`, whose
    keywords these are); returns `x` (with `launch`: what `launch` returns)."""
    launched = expert_layers_(*op_arguments(x, step, eps), tiling=tiling, programs=programs, launch=launch, state=state,
                              order=order, watch=watch, timeline=timeline)
    return x if launch is None else launched


def reference_layers_(x: torch.Tensor, step: Step, eps: float) -> torch.Tensor:
    """The same in `pi0_torch.kernels.reference`'s ops; returns `x`."""
    reference.expert_layers_(*op_arguments(x, step, eps))
    return x


def todays_layers_(x: torch.Tensor, step: Step, eps: float) -> torch.Tensor:
    """The same in today's five fused ops per layer (`pi0_torch.kernels.ops`: on CUDA their kernels, cuBLAS from
    `CUBLAS_ROWS` rows); returns `x`."""
    ops.expert_layers_op_by_op_(*op_arguments(x, step, eps))
    return x


def expected_counts(shape: Shape, tiling: Tiling, programs: int) -> torch.Tensor:
    """What a launch leaves in its counters without the reset: every ticket taken (and one more per program), every
    program finished, each phase's output tiles (the attention: its blocks) counted once, the key parts' and split-K
    parts' arrivals back at 0."""
    rows = shape.batch * shape.tokens
    row_blocks = cdiv(rows, tiling.m)
    attention_blocks = shape.batch * cdiv(shape.tokens * shape.heads, tiling.attention_m)
    per_row_block = [cdiv(shape.width, tiling.o), cdiv(shape.mlp_width, tiling.gate_up), cdiv(shape.width, tiling.down)]
    qkv_tiles = row_blocks * cdiv((shape.heads + 2) * shape.head_dim // 2, tiling.qkv)
    tiles = tiles_per_phase(shape, tiling)
    layer = [qkv_tiles, attention_blocks] + [each for each in per_row_block for _ in range(row_blocks)]
    layer += [0] * (attention_blocks + row_blocks * sum(per_row_block) + qkv_tiles)
    return torch.tensor([shape.depth * sum(tiles) + programs, programs] + layer * shape.depth, dtype=torch.int32)


def launch_state_size(shape: Shape, tiling: Tiling) -> int:
    """`persistent.state_size` of `shape`: the counters of a launch."""
    return state_size(shape.depth, shape.batch * shape.tokens, shape.tokens, shape.heads, shape.head_dim, shape.width,
                      shape.mlp_width, tiling)


def tiles_per_phase(shape: Shape, tiling: Tiling) -> list[int]:
    """`persistent.phase_tiles` of `shape`: the tiles of each phase of a layer, in ticket order."""
    return phase_tiles(shape.batch * shape.tokens, shape.tokens, shape.heads, shape.head_dim, shape.width,
                       shape.mlp_width, tiling)


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
    wrote, launched once on counters of its own, kept and compared with `expected_counts`, then twice in a row on the
    stream's (the second finds the counters the first put back to 0). On CUDA the first tiling also runs today's
    ops (each other launch option is another compiled variant: the check would take minutes) and launches `REPEATS`
    more times: a tile's sums go in a fixed order, so every launch must give the same bits, and one that does not
    has read something before it was written (a race the reference bound may not see); then once with a timeline
    (`--bench` prints it), which must give the same bits and stamp every tile."""
    failures = 0
    for shape, tiling in itertools.product(shapes, tilings):
        x, step = operands(shape, dtype, device)
        wanted = step.fresh()
        want = reference_layers_(x.clone(), wanted, 1e-6)
        first = tiling == tilings[0]
        for launch in (1, 2, 3):  # (1: counters kept and compared; 2 and 3 on those left at 0)
            got_step = step.fresh()
            programs = default_programs(device, tiling)
            size = launch_state_size(shape, tiling)
            state = torch.zeros(size, dtype=torch.int32, device=device) if launch == 1 else None
            got = persistent_layers_(x.clone(), got_step, 1e-6, tiling, programs, state=state)
            error = deviation(got, got_step, want, wanted)
            line = f"{shape} {tiling} launch {launch}: {error:.2e} against the reference"
            if state is not None:
                miscounted = (state.cpu() != expected_counts(shape, tiling, programs)).sum().item()
                line += f", {miscounted} of {size} counters not as expected"
                error = error if miscounted == 0 else float("inf")
                if device.type == "cuda" and first:
                    today = step.fresh()
                    todays = todays_layers_(x.clone(), today, 1e-6)
                    line += f", today's ops {deviation(todays, today, want, wanted):.2e}"
            if device.type == "cuda" and first and launch == 3:
                differing = sum(not torch.equal(persistent_layers_(x.clone(), step.fresh(), 1e-6, tiling), got)
                                for _ in range(REPEATS))
                line += f", {differing} of {REPEATS} more launches not bit for bit the same"
                timeline = new_timeline(shape, tiling, device)
                timed = persistent_layers_(x.clone(), step.fresh(), 1e-6, tiling, timeline=timeline)
                stamped = bool((timeline[:, 0] > 0).all() and (timeline[:, 1] >= timeline[:, 0]).all())
                line += f", with a timeline {'the same bits' if torch.equal(timed, got) else 'OTHER BITS'}"
                line += "" if stamped else " and tiles it did not stamp"
                error = error if differing == 0 and stamped and torch.equal(timed, got) else float("inf")
            failures += not error <= tolerance
            print(line + ("" if error <= tolerance else f"  FAILED (bound {tolerance:g})"), flush=True)
    return failures


REPEATS = 200  # launches of the same step on a GPU, compared bit for bit (`check`)


def wait_graph(run: Callable[[], Any]) -> list[set[int]]:
    """What each tile of an interpreted launch `run` waits for: the tiles (numbered in ticket order) counted in on the
    counter it waits on, where it needs more than 0. Recorded from the kernel itself: for one launch, its waits and
    count-ins (one of each per tile, in ticket order) go to a recorder instead (no waiting, no counting)."""
    waits: list[tuple[int, int]] = []  # (counter address, need) per tile
    counts: list[int] = []  # counter address per tile

    def value(each: Any) -> int:
        return int(each.handle.data.item()) if hasattr(each, "handle") else int(each)

    def wait_for(counter_ptr: Any, need: Any, watch_ptr: Any) -> None:
        waits.append((value(counter_ptr), value(need)))

    def count_in(counter_ptr: Any, count: Any) -> None:
        counts.append(value(counter_ptr))

    saved = persistent._wait_for, persistent._count_in
    persistent._wait_for, persistent._count_in = wait_for, count_in
    try:
        run()
    finally:
        persistent._wait_for, persistent._count_in = saved
    assert len(waits) == len(counts), (len(waits), len(counts))
    producers: dict[int, list[int]] = {}
    for tile, counter in enumerate(counts):
        producers.setdefault(counter, []).append(tile)
    return [set(producers.get(counter, ())) if need > 0 else set() for counter, need in waits]


def check_abandoned(device: torch.device, dtype: torch.dtype, shape: Shape, tiling: Tiling) -> int:
    """A wait that never ends is abandoned, not hung on (`persistent.watchdog`): a launch whose counters start below
    what its first waits need (-1), on a watch of its own that allows 64 spins, returns with `x` all NaN and the
    watch set; a second launch on that watch, with counters that would serve it, gives up its waits at once and
    returns NaN too."""
    x, step = operands(shape, dtype, device)
    size = launch_state_size(shape, tiling)
    watch = torch.tensor([0, 64], dtype=torch.int32, device=device)
    failures = 0
    for launch, first_counters in ((1, -1), (2, 0)):
        state = torch.zeros(size, dtype=torch.int32, device=device)
        state[2:] = first_counters
        got = persistent_layers_(x.clone(), step.fresh(), 1e-6, tiling, state=state, watch=watch)
        failed = not (bool(got.isnan().all()) and int(watch[0]) == 1)
        failures += failed
        print(f"{shape} {tiling}, launch {launch} {'with counters that never reach their waits' if launch == 1 else 'after it'}"
              f": {int(got.isnan().sum())} of {got.numel()} outputs NaN, watch {watch.tolist()}"
              + ("  FAILED (want every output NaN and the watch set)" if failed else ""), flush=True)
    return failures


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
    want = reference_layers_(x.clone(), wanted, 1e-6)
    size = launch_state_size(shape, tiling)

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
    """Compile the full-size variants (π0 at batch 1 and 8; π0.5 at batch 1 in the first tiling; π0 at batch 1 in
    the first tiling with a timeline) for `arch` with triton's ptxas, on meta tensors (no GPU)."""
    def case(shape: Shape, tiling: Tiling, timed: bool = False) -> tuple[str, Callable[[Callable[..., Any]], Any]]:
        x, step = operands(shape._replace(depth=1), torch.bfloat16, torch.device("cpu"))
        x, step = x.to("meta"), tree_map_only(torch.Tensor, lambda tensor: tensor.to("meta"), step)
        name = f"batch {shape.batch}{' π0.5' if shape.adarms else ''}{' timeline' if timed else ''} {tiling}"
        timeline = new_timeline(shape._replace(depth=1), tiling, torch.device("meta")) if timed else None
        return name, lambda launch: persistent_layers_(x, step, 1e-6, tiling, programs=132, launch=launch,
                                                       timeline=timeline)

    cases = [case(FULL._replace(batch=batch), tiling) for batch, tiling in itertools.product((1, 8), tilings)]
    return compile_variants(arch, [*cases, case(FULL._replace(adarms=True), tilings[0]), case(FULL, tilings[0], True)])


def bench(tilings: list[Tiling]) -> None:
    """π0's 18 expert layers at full size, bf16, batch 1 and 8 (π0.5's at batch 1, in the first tiling): today's 90
    launches against one persistent launch, 20 steps in a CUDA graph (the weights, 600 MB, come from memory: more
    than the L2 cache holds); then where one launch's time went in the first tiling (`print_timeline`)."""
    from pi0_torch.benchmark import graph_time

    device = torch.device("cuda")
    print(f"{torch.cuda.get_device_name(device)}, torch {torch.__version__}, triton {triton.__version__}; µs per Euler "
          "step of the 18 layers (today: 5 fused launches per layer), 20 steps in a CUDA graph")
    for shape, shape_tilings in ((FULL, tilings), (FULL._replace(batch=8), tilings), (FULL._replace(adarms=True), tilings[:1])):
        x, step = operands(shape, torch.bfloat16, device)
        want = reference_layers_(x.clone(), step.fresh(), 1e-6)
        results = []
        for tiling in [None, *shape_tilings]:  # (the action tokens accumulate step after step, as a chunk's do)
            run = (functools.partial(todays_layers_, x.clone(), step, 1e-6) if tiling is None else
                   functools.partial(persistent_layers_, x.clone(), step, 1e-6, tiling))
            seconds = graph_time(run, device, calls=20, repeats=5)
            got = (todays_layers_(x.clone(), step.fresh(), 1e-6) if tiling is None else
                   persistent_layers_(x.clone(), step.fresh(), 1e-6, tiling))
            results.append((tiling, seconds, relative_deviation(got, want)))
        title = f"{'π0.5' if shape.adarms else 'π0'} batch {shape.batch} ({shape.batch * shape.tokens} rows)"
        print_times(title, sum(weight.numel() * weight.element_size() for weight in step.layers), results,
                    "today's 90 launches")
        timeline = new_timeline(shape, tilings[0], device)  # (its variant compiled by `--check`)
        persistent_layers_(x.clone(), step.fresh(), 1e-6, tilings[0], timeline=timeline)
        print_timeline(shape, tilings[0], timeline, default_programs(device, tilings[0]))


def new_timeline(shape: Shape, tiling: Tiling, device: torch.device) -> torch.Tensor:
    """A zeroed timeline for one launch of `shape` (`expert_layers_(..., timeline=)`)."""
    return torch.zeros(shape.depth * sum(tiles_per_phase(shape, tiling)), 3, dtype=torch.int64, device=device)


def print_timeline(shape: Shape, tiling: Tiling, timeline: torch.Tensor, programs: int) -> None:
    """Where one launch's time went, from its `timeline`: per phase, its tiles per layer and the medians over them of
    a tile's time (from its ticket to its count-in), of how long it waited for what it reads (from its start to the
    last end among the tiles it waits on, where that is later) and of the rest, its work; and the median span of the
    phase in a layer (its first start to its last end). Then the launch's span, and the share of its `programs`'
    time that went to tiles and to their work (the rest: taking tickets, the gaps between tiles)."""
    stamps = timeline.cpu()
    start, end = ((stamps[:, column] - stamps[:, 0].min()).double() / 1e3 for column in (0, 1))  # µs (int64 first:
    # the clock counts ns since 1970, past float64's ns precision)
    tiles = tiles_per_phase(shape, tiling)
    per_layer, first = sum(tiles), [sum(tiles[:phase]) for phase in range(len(tiles))]
    row_blocks = cdiv(shape.batch * shape.tokens, tiling.m)
    per_block = [count // row_blocks for count in tiles]  # (the attention's tiles wait as one group)

    @functools.cache  # (every tile of a group waits on the same tiles)
    def ends(layer: int, phase: int, block: int | None) -> float:  # the last end of a phase's tiles (of a row block)
        base = layer * per_layer + first[phase]
        if block is not None:
            base, count = base + block * per_block[phase], per_block[phase]
        else:
            count = tiles[phase]
        return float(end[base : base + count].max())

    ready = torch.zeros_like(start)  # when what each tile reads was all written
    for layer in range(shape.depth):
        for phase, count in enumerate(tiles):
            for index in range(count):
                if phase == 0:
                    when = ends(layer - 1, 4, index // per_block[0]) if layer > 0 else 0.0
                else:  # (the attention waits for every q/k/v tile, the o-projection for every attention tile)
                    when = ends(layer, phase - 1, None if phase in (1, 2) else index // per_block[phase])
                ready[layer * per_layer + first[phase] + index] = when
    waited = (ready - start).clamp(min=0)
    work = (end - torch.maximum(start, ready)).clamp(min=0)  # (a producer stamps its end just after counting in)
    span = max(float(end.max()), 1e-3)
    print(f"  one launch, {tiling}: {span:.0f} µs; tiles {float((end - start).sum()) / (programs * span):.0%} of its "
          f"{programs} programs' time, their work {float(work.sum()) / (programs * span):.0%}")
    print(f"    {'phase':16s} {'tiles/layer':>11s} {'tile µs':>8s} {'waited µs':>9s} {'work µs':>8s} {'span/layer µs':>13s}")
    for phase, name in enumerate(PHASES):
        at = torch.cat([torch.arange(tiles[phase]) + layer * per_layer + first[phase] for layer in range(shape.depth)])
        spans = [float(end[at[layer * tiles[phase] : (layer + 1) * tiles[phase]]].max()
                       - start[at[layer * tiles[phase] : (layer + 1) * tiles[phase]]].min()) for layer in range(shape.depth)]
        print(f"    {name:16s} {tiles[phase]:11d} {float((end - start)[at].median()):8.2f} {float(waited[at].median()):9.2f} "
              f"{float(work[at].median()):8.2f} {float(torch.tensor(spans).median()):13.2f}", flush=True)


# The default first (the fastest of 15 on an H200: benchmarks/results/gpu_h200_2026-11-28.md), then q/k/v's and
# gate/up's reductions split too (not yet timed on a GPU), then the default's runners-up and what each lever alone
# did: µs per Euler step of π0 at batch 1 (two calls, two machines; today's 90 launches took 979 and 980 µs on them)
TILINGS = [Tiling(),  # 1091
           Tiling(qkv_splits=2, gate_up_splits=2),
           Tiling(qkv_splits=2),
           Tiling(gate_up_splits=2),
           Tiling(qkv_splits=4, gate_up_splits=2, o_splits=4, down_splits=4),
           Tiling(o=32, down=32, o_splits=4, down_splits=4),  # 1093
           Tiling(o_splits=1, down_splits=1),  # 1197 (k=128 alone)
           Tiling(k=64, o_splits=1, down_splits=1)]  # 1422 (the first default)


def main() -> int:
    def check_here() -> int:
        if torch.cuda.is_available():  # (π0.5 in the first tiling: each tiling is seconds of compiling there)
            bound, device = FUSED_TOLERANCE[torch.bfloat16], torch.device("cuda")
            return (check_abandoned(device, torch.bfloat16, FULL._replace(depth=2), TILINGS[0])  # (first: one variant)
                    + check(device, torch.bfloat16, [FULL._replace(depth=2), FULL._replace(depth=2, batch=8)], bound, TILINGS)
                    + check(device, torch.bfloat16, [FULL._replace(depth=2, adarms=True)], bound, TILINGS[:1]))
        # (the interpreter: small, float32; one and three samples, partial row and attention blocks; π0.5)
        shapes = [Shape(2, 1, 5, 7, 32, 2, 16, 48), Shape(2, 3, 6, 9, 48, 2, 16, 40, adarms=True)]
        # (the first with every projection split: q/k/v, o and gate/up in 2 parts, down in 3; the last part
        # shallower than the others)
        tilings = [Tiling(qkv=8, o=16, gate_up=16, down=16, k=16, m=16, attention_m=16, attention_n=16, key_parts=2,
                          o_splits=2, down_splits=3, qkv_splits=2, gate_up_splits=2),
                   Tiling(qkv=16, o=32, gate_up=32, down=32, k=32, m=32, attention_m=32, attention_n=16, key_parts=1)]
        return (check(torch.device("cpu"), torch.float32, shapes, 1e-5, tilings)
                + sum(check_orders(shape, tilings[0], 1e-5) for shape in shapes)
                + check_abandoned(torch.device("cpu"), torch.float32, shapes[1], tilings[0]))

    return experiment_main(__doc__, check_here, functools.partial(compile_for, tilings=TILINGS),
                           functools.partial(bench, TILINGS))


if __name__ == "__main__":
    sys.exit(main())
