"""Sampling as CUDA graphs, captured by hand (no compiler): `PI0ForActionGeneration.capture_sampling`.

Eager sampling of a full-size π0 launches thousands of small kernels per chunk, and the CPU that launches them, not
the GPU, sets the pace. A CUDA graph records those launches once and replays them with one call. The sampling after
the input checks never reads the device from the host (`PI0ForActionGeneration._sample`), so it records as is, real-time
chunking's guidance included: its vector-Jacobian product per step is autograd work on the same stream, recorded
with the rest (as PyTorch records a whole training step's backward). Should CUDA refuse to record guidance all the
same, a warning is logged and guided chunks sample eagerly from then on; the other graphs stay.

One graph per `SamplingPlan` (prefix layout, Euler times, real-time chunking method) and input shapes / dtypes: the
first call of each records it (two warm-up runs on a side stream, then the capture, on the model's own capture
stream); later calls copy their inputs into the graph's static buffers, replay it, and return a copy of its output,
which the next replay does not overwrite. The graphs share a memory pool, guided ones one of their own: a refused
capture can leave its pool marked as recording in torch's allocators (there is no Python call that ends that in
the pinned host allocator), so a pool that saw one is never captured into again, and a refused guidance capture
never touches the plain graphs' pool.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from pi0_torch.inference.sampling import SamplingInputs, SamplingPlan
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

logger = logging.getLogger(__name__)

WARMUP_RUNS = 2  # before a capture (cuBLAS / cuDNN pick and allocate on their first calls)


class SamplingCaptureError(RuntimeError):
    """CUDA refused to record the sampling as a graph (the warm-up runs before it succeeded: eager sampling works)."""


@dataclass
class CapturedSampling:
    graph: torch.cuda.CUDAGraph
    inputs: SamplingInputs  # the static buffers the graph reads
    output: torch.Tensor  # where its replay writes the actions


def _signature(inputs: SamplingInputs) -> tuple[Any, ...]:
    """Shapes, dtypes and devices of the inputs (None for the absent ones): what a graph is specialised to."""
    return tuple(None if value is None else (tuple(value.shape), value.dtype, value.device) for value in _tensors(inputs))


class SamplingGraphs:
    """The captured graphs of one model, by plan and input signature."""

    def __init__(self, model: PI0ForActionGeneration, batch_sizes: tuple[int, ...] | None = None, guidance: bool = True) -> None:
        self.model = model
        self.batch_sizes = batch_sizes  # None: any batch size (captured on first use)
        self.guidance = guidance  # False: RTC guidance samples eagerly (also once CUDA refused to record it)
        self.graphs: dict[tuple[Any, ...], CapturedSampling] = {}
        self.pools: dict[bool, Any] = {}  # guided or not -> the memory pool its graphs share
        self.stream: torch.cuda.Stream | None = None  # every capture's stream (a pool's captures share one)
        self.warmup_stream: torch.cuda.Stream | None = None  # (one: cuBLAS keeps a workspace per stream)

    def clear(self) -> None:
        """Drop every graph (the model's tensors moved, or its attention kernel changed)."""
        self.graphs.clear()
        self.pools.clear()
        self.stream = self.warmup_stream = None

    def covers(self, rtc_method: str | None) -> bool:
        """Whether sampling with this real-time chunking method (None: plain) replays graphs."""
        return rtc_method != "guidance" or self.guidance

    def run(self, inputs: SamplingInputs, plan: SamplingPlan) -> torch.Tensor:
        """Actions `[B, horizon, action_dim]` for `inputs` (on CUDA) by replaying the plan's graph (captured on first use)."""
        batch = inputs.noise.shape[0]
        if self.batch_sizes is not None and batch not in self.batch_sizes:
            raise ValueError(f"batch size {batch}: sampling is captured for batch sizes {list(self.batch_sizes)} only "
                             "(model.capture_sampling(batch_sizes=...))")
        key = (plan, _signature(inputs))
        captured = self.graphs.get(key)
        if captured is None:
            try:
                captured = self.graphs[key] = self._capture(inputs, plan)
            except SamplingCaptureError as error:
                if plan.rtc_method != "guidance":
                    raise
                logger.warning("%s; chunks guided by real-time chunking sample eagerly from now on", error)
                self.guidance = False
            if captured is None:  # (outside the `except`: its traceback holds the failed capture's tensors)
                return self.model._sample(inputs, plan)
        with torch.inference_mode():
            for static, value in zip(_tensors(captured.inputs), _tensors(inputs)):
                if static is not None:
                    static.copy_(value)
            captured.graph.replay()
        return captured.output.clone()  # (outside inference mode: a normal tensor the next replay leaves alone)

    @torch.inference_mode()
    def _capture(self, inputs: SamplingInputs, plan: SamplingPlan) -> CapturedSampling:
        device = inputs.noise.device
        with torch.cuda.device(device):  # (the model's GPU, whichever is current)
            static = type(inputs)(*(None if value is None else value.clone() for value in _tensors(inputs)))
            if self.stream is None:  # (torch's default capture stream is made once, on whichever GPU was current)
                self.stream, self.warmup_stream = torch.cuda.Stream(device=device), torch.cuda.Stream(device=device)
            self.warmup_stream.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(self.warmup_stream):
                for _ in range(WARMUP_RUNS):
                    self.model._sample(static, plan)
            torch.cuda.current_stream(device).wait_stream(self.warmup_stream)
            guided = plan.rtc_method == "guidance"
            pool = self.pools[guided] if guided in self.pools else torch.cuda.graph_pool_handle()
            graph = torch.cuda.CUDAGraph()
            try:
                with torch.cuda.stream(torch.cuda.current_stream(device)):  # (this stream again, should capture fail)
                    with torch.cuda.graph(graph, pool=pool, stream=self.stream):
                        output = self.model._sample(static, plan)
            except Exception as error:
                self.pools.pop(guided, None)  # (never captured into again)
                _release_failed_capture(device, pool)
                what = "sampling" if plan.rtc_method is None else f"sampling with RTC {plan.rtc_method}"
                raise SamplingCaptureError(f"could not capture {what} as a CUDA graph ({error}); call "
                                           "model.capture_sampling(disable=True) to sample eagerly") from error
            self.pools[guided] = pool
            torch.cuda.synchronize(device)
        return CapturedSampling(graph, static, output)


def _release_failed_capture(device: torch.device, pool: Any) -> None:
    """Best effort: end the CUDA caching allocator's routing of new memory to a refused capture's pool and give the
    pool back, in the order torch's own pool helpers use. Some torch versions end that routing only once a capture
    succeeded; others end it before raising, and then the first call raises and nothing more is done here. (The pinned
    host allocator's routing has no Python call: that pool is not captured into again, see `SamplingGraphs`.)"""
    index = device.index if device.index is not None else torch.cuda.current_device()
    try:
        torch._C._cuda_endAllocateToPool(index, pool)
    except RuntimeError:  # (a torch that ended it already)
        return
    torch._C._cuda_releasePool(index, pool)


def _tensors(inputs: SamplingInputs) -> list[torch.Tensor | None]:
    return [getattr(inputs, field.name) for field in dataclasses.fields(inputs)]
