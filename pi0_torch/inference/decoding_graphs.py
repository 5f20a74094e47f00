"""π0-FAST's decoded tokens as CUDA graphs, captured by hand (no compiler): `PI0FastForActionGeneration.capture_decoding`.

A decoded token runs the whole decoder on one row per sample: at full size about two hundred small launches, whose
host time, not the GPU's, sets the pace of eager decoding. `decode_step` never reads the device from the host and its
shapes do not change from token to token (the token's step and slot are device values), so one graph per cache
signature (batch size, cache slots, dtype, fused kernels or modules) serves every token of every call. Unlike
`compile_decoding(mode="reduce-overhead")` it needs no compiler: it runs on torch 2.10 and 2.11 too, where inductor's
graphs of the decoding step crashed the process, and it replays the fused kernels (`fast_decoding`) where eager
decoding runs them.

Each call's prefill runs eagerly (`prepare_decoding`: it runs once per call, over a prompt whose length may change) and
its cache is copied into the graph's static cache; each token is then copied into the graph's static token and step,
and the graph replays `decode_step` into its static logits. The first call of a signature captures its graph (two
warm-up steps on a side stream, then the capture, on the graphs' own capture stream, into their shared memory pool)
and verifies it: its first replay must give the logits of the last warm-up step (eager decoding of the same token
into the same cache) within `VERIFY_TOLERANCE`, relative to the largest logit. A graph that does not, or that CUDA
refuses to record, is refused with a warning, and its signature decodes eagerly from then on: no graph ever picks
other tokens than eager decoding silently.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference.graphs import (VERIFY_TOLERANCE, GraphCaptureError, capture_streams, record_graph,
                                       relative_deviation)

if TYPE_CHECKING:
    from pi0_torch.models.modeling_pi0_fast import DecodingCache, PI0FastForActionGeneration

logger = logging.getLogger(__name__)


@dataclass
class CapturedDecoding:
    graph: Any  # torch.cuda.CUDAGraph
    cache: DecodingCache  # the static cache the graph reads, and writes each decoded token's k/v into
    token: torch.Tensor  # long [B]: the token a replay feeds
    step: torch.Tensor  # long [1]: its step
    logits: torch.Tensor  # [B, V]: where a replay writes the next token's logits


def cache_tensors(cache: DecodingCache) -> list[torch.Tensor]:
    """Every tensor of `cache`, in a fixed order (the absent mask left out)."""
    tensors = [*cache.keys, *cache.values, cache.cos, cache.sin, cache.slots, cache.first]
    return tensors + ([] if cache.masks is None else [cache.masks]) + list(cache.norm_scales or ())


def cache_signature(cache: DecodingCache) -> tuple[Any, ...]:
    """What a graph is specialised to: the fused kernels or the modules, and every cache tensor's shape, dtype and
    device."""
    fused = cache.norm_scales is not None
    return (fused, *((tuple(tensor.shape), tensor.dtype, tensor.device) for tensor in cache_tensors(cache)))


def clone_cache(cache: DecodingCache) -> DecodingCache:
    """A copy of `cache` with tensors of its own (the static buffers of a graph)."""
    def clone(value: Any) -> Any:
        if isinstance(value, (list, tuple)):
            return [tensor.clone() for tensor in value]
        return None if value is None else value.clone()

    return dataclasses.replace(cache, **{field.name: clone(getattr(cache, field.name)) for field in dataclasses.fields(cache)})


class DecodingGraphs:
    """The captured decoding steps of one model, by cache signature, and the signatures refused at capture.

    `prepare` and `step` stand in for `prepare_decoding` and `decode_step` in `PI0FastForActionGeneration.decode`."""

    def __init__(self, model: PI0FastForActionGeneration, verify: bool = True) -> None:
        self.model = model
        self.verify = verify  # compare each graph's first replay with an eager step (see the module docstring)
        self.graphs: dict[tuple[Any, ...], CapturedDecoding] = {}
        self.refused: dict[tuple[Any, ...], str] = {}  # signature -> why its graph was refused: it decodes eagerly
        self.replays: dict[int, CapturedDecoding] = {}  # id(static cache) -> its graph (what `step` looks up)
        self.pool: Any = None  # the memory pool the graphs share
        self.stream: torch.cuda.Stream | None = None  # every capture's stream
        self.warmup_stream: torch.cuda.Stream | None = None

    def clear(self) -> None:
        """Drop every graph (the model's tensors moved, or its kernels changed)."""
        self.graphs.clear()
        self.refused.clear()
        self.replays.clear()
        self.pool = self.stream = self.warmup_stream = None

    def prepare(self, *inputs: Any) -> tuple[DecodingCache, torch.Tensor]:
        """The prefill (`prepare_decoding(*inputs)`, eager) and the cache `step` continues from: the static cache of
        the signature's graph (captured and verified on first use), holding this call's prefix; the prefill's own
        cache where the signature's graph was refused (its steps then run eagerly)."""
        cache, logits = self.model.prepare_decoding(*inputs)
        key = cache_signature(cache)
        if key in self.refused:
            return cache, logits
        captured = self.graphs.get(key)
        if captured is None:
            try:
                captured, eager = self._capture(cache, logits)
            except GraphCaptureError as error:
                captured, refusal = None, f"CUDA could not record it ({error})"
            else:
                refusal = self._verify(captured, eager) if self.verify else None
            if refusal is not None:
                self.refused[key] = refusal
                logger.warning("the CUDA graph of π0-FAST's decoding step (batch %d, %d cache slots) was refused: %s; "
                               "it decodes eagerly from now on", cache.first.shape[0], cache.keys[0].shape[2], refusal)
                return cache, logits
            self.graphs[key] = self.replays[id(captured.cache)] = captured
            return captured.cache, logits  # (a copy of this call's cache already)
        with torch.inference_mode():
            torch._foreach_copy_(cache_tensors(captured.cache), cache_tensors(cache))
        return captured.cache, logits

    def step(self, cache: DecodingCache, token: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """`decode_step(cache, token, step)`: a replay of the graph whose static cache `cache` is (its logits are
        overwritten by the next replay), or the eager step for any other cache."""
        captured = self.replays.get(id(cache))
        if captured is None or captured.cache is not cache:
            return self.model.decode_step(cache, token, step)
        with torch.inference_mode():
            captured.token.copy_(token)
            captured.step.copy_(step)
            captured.graph.replay()
        return captured.logits

    def _verify(self, captured: CapturedDecoding, eager: torch.Tensor) -> str | None:
        """Why the graph is refused (None: its first replay gives `eager`, the last warm-up step's logits, within
        `VERIFY_TOLERANCE`)."""
        with torch.inference_mode():
            captured.graph.replay()
        deviation = relative_deviation(captured.logits, eager)
        bound = VERIFY_TOLERANCE.get(self.model.dtype, VERIFY_TOLERANCE[torch.float32])
        if deviation <= bound:
            return None
        return f"its first replay deviates from an eager step by {deviation:.3g} of the largest logit (bound {bound:g})"

    def _capture(self, cache: DecodingCache, logits: torch.Tensor) -> tuple[CapturedDecoding, torch.Tensor]:
        """The graph of `decode_step` on a copy of `cache` (its static buffers), feeding the most likely first token at
        step 0 (the call's own first step writes that slot again), and the last warm-up step's logits."""
        with torch.inference_mode():
            static = clone_cache(cache)
            token = logits.argmax(dim=-1)  # [B]
            step = torch.zeros(1, dtype=torch.long, device=token.device)
            graph, output, eager = self._record(static, token, step)
        return CapturedDecoding(graph, static, token, step, output), eager

    def _record(self, cache: DecodingCache, token: torch.Tensor, step: torch.Tensor) -> tuple[Any, torch.Tensor, torch.Tensor]:
        """Warm up and record `decode_step(cache, token, step)` (`graphs.record_graph`; inference mode): the graph,
        where its replay writes the logits, and the logits of the last warm-up step."""
        device = token.device
        with torch.cuda.device(device):
            if self.stream is None:
                self.stream, self.warmup_stream = capture_streams(device)
            pool = self.pool if self.pool is not None else torch.cuda.graph_pool_handle()
            try:
                recorded = record_graph(lambda: self.model.decode_step(cache, token, step), device, self.stream,
                                        self.warmup_stream, pool)
            except GraphCaptureError:
                self.pool = None  # (never captured into again)
                raise
            self.pool = pool
        return recorded
