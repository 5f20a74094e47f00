"""Sampling as CUDA graphs, captured by hand (no compiler): `PI0ForActionGeneration.capture_sampling`.

The sampling after the input checks never reads the device from the host (`ActionSampling.sample_planned`), so it
records as is: one graph per `SamplingPlan` and input shapes / dtypes, captured, verified and replayed as
`capture_sampling` says.

The graphs share a memory pool, guided ones one of their own: a capture CUDA refuses can leave its pool marked as
recording in torch's allocators (there is no Python call that ends that in the pinned host allocator), so a pool that
saw one is never captured into again, and a refused guidance capture never touches the plain graphs' pool.

`GraphRecorder` (the warm-up runs, the capture, a refused capture's clean-up) also records π0-FAST's prefill and
decoding step (`pi0_torch.inference.decoding_graphs`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference.checks import VERIFY_TOLERANCE, bound, relative_deviation

if TYPE_CHECKING:
    from pi0_torch.inference.layer_pass import ModelSamplingWeights
    from pi0_torch.inference.plan import SamplingInputs, SamplingPlan
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

logger = logging.getLogger(__name__)

WARMUP_RUNS = 2  # before a capture (cuBLAS / cuDNN pick and allocate on their first calls)


class GraphCaptureError(RuntimeError):
    """CUDA refused to record a graph (the warm-up runs before it succeeded: the eager path works)."""


class SamplingCaptureError(GraphCaptureError):
    """CUDA refused to record the sampling as a graph (the warm-up runs before it succeeded: eager sampling works)."""


@dataclass
class CapturedSampling:
    graph: torch.cuda.CUDAGraph
    inputs: SamplingInputs  # the static buffers the graph reads
    output: torch.Tensor  # where its replay writes the actions


def input_signature(inputs: SamplingInputs) -> tuple[Any, ...]:
    """Shapes, dtypes and devices of the inputs (None for the absent ones): what a graph is specialised to."""
    return tuple(None if value is None else (tuple(value.shape), value.dtype, value.device) for value in _tensors(inputs))


def describe_plan(plan: SamplingPlan, batch: int) -> str:
    """`sampling with RTC guidance (batch 1, 10 steps, 800 prefix slots, fused steps)`: a plan in a log line."""
    what = "sampling" if plan.rtc_method is None else f"sampling with RTC {plan.rtc_method}"
    steps = {"torch": "", "triton": ", fused steps", "persistent": ", fused steps in persistent launches"}[plan.steps]
    return f"{what} (batch {batch}, {len(plan.times)} steps, {plan.layout.length} prefix slots{steps})"


class SamplingGraphs:
    """The captured graphs of one model, by plan and input signature, and the plans refused at capture."""

    def __init__(self, model: PI0ForActionGeneration, batch_sizes: tuple[int, ...] | None = None, guidance: bool = False,
                 verify: bool = True) -> None:
        self.model = model
        self.batch_sizes = batch_sizes  # None: any batch size (captured on first use)
        self.guidance = guidance  # False: RTC guidance samples eagerly (also once CUDA refused to record it)
        self.verify = verify  # compare each graph's first replay with eager sampling (see the module docstring)
        self.graphs: dict[tuple[Any, ...], CapturedSampling] = {}
        self.refused: dict[tuple[Any, ...], str] = {}  # plan key -> why its graph was refused: it samples eagerly
        self.recorder = GraphRecorder()  # (guided graphs in a pool of their own)

    def clear(self) -> None:
        """Drop every graph (the model's tensors moved, or its kernels changed)."""
        self.graphs.clear()
        self.refused.clear()
        self.recorder = GraphRecorder()

    def covers(self, rtc_method: str | None) -> bool:
        """Whether sampling with this real-time chunking method (None: plain) replays graphs."""
        return rtc_method != "guidance" or self.guidance

    def run(self, inputs: SamplingInputs, plan: SamplingPlan,
            weights: ModelSamplingWeights | None = None) -> tuple[torch.Tensor, str | None]:
        """Actions `[B, horizon, action_dim]` for `inputs` (on CUDA) by replaying the plan's graph (captured and
        verified on first use), or eagerly for a plan whose graph was refused; and why no graph replayed (None: one
        did). `weights`: the call's plain-weights check (`layer_pass.model_sampling_weights`)."""
        batch = inputs.noise.shape[0]
        if self.batch_sizes is not None and batch not in self.batch_sizes:
            raise ValueError(f"batch size {batch}: sampling is captured for batch sizes {list(self.batch_sizes)} only "
                             "(model.capture_sampling(batch_sizes=...))")
        key = (plan, input_signature(inputs))
        if key in self.refused:
            return self.model.sample_planned(inputs, plan, weights), self.refused[key]
        captured = self.graphs.get(key)
        if captured is None:
            eager, failed = None, None
            try:
                captured, eager = self._capture(inputs, plan, weights)
            except SamplingCaptureError as error:
                if plan.rtc_method != "guidance":
                    raise
                logger.warning("%s; chunks guided by real-time chunking sample eagerly from now on", error)
                self.guidance, failed = False, str(error)
            if captured is None:  # (outside the `except`: its traceback holds the failed capture's tensors)
                return self.model.sample_planned(inputs, plan, weights), failed
            refusal = replay_refusal(captured.graph, captured.output, eager, self.model.dtype, "its", "eager sampling",
                                     "action") if self.verify else None
            if refusal is not None:
                self.refused[key] = refusal
                logger.warning("the CUDA graph of %s was refused: %s; that plan samples eagerly from now on",
                               describe_plan(plan, batch), refusal)
                return eager.clone(), refusal  # (these inputs' eager actions)
            self.graphs[key] = captured
        with torch.inference_mode():
            for static, value in zip(_tensors(captured.inputs), _tensors(inputs)):
                if static is not None:
                    static.copy_(value)
            captured.graph.replay()
        return captured.output.clone(), None  # (outside inference mode: a normal tensor the next replay leaves alone)

    def _capture(self, inputs: SamplingInputs, plan: SamplingPlan,
                 weights: ModelSamplingWeights | None = None) -> tuple[CapturedSampling, torch.Tensor]:
        """Warm up and capture the plan's graph: the graph, and the last warm-up run's actions (eager sampling of the
        same inputs, to verify the graph against)."""
        device = inputs.noise.device
        guided = plan.rtc_method == "guidance"
        with torch.cuda.device(device), _capture_mode(guided):  # (the model's GPU, whichever is current)
            static = type(inputs)(*(None if value is None else value.clone() for value in _tensors(inputs)))
            try:
                graph, output, eager = self.recorder.record(lambda: self.model.sample_planned(static, plan, weights),
                                                            device, kind=guided)
            except GraphCaptureError as error:
                raise SamplingCaptureError(f"could not capture {describe_plan(plan, inputs.noise.shape[0])} as a CUDA "
                                           f"graph ({error}); call model.capture_sampling(disable=True) to sample eagerly") from error
        return CapturedSampling(graph, static, output), eager


def replay_refusal(graph: Any, output: torch.Tensor, eager: torch.Tensor, dtype: torch.dtype, whose: str,
                   reference: str, unit: str) -> str | None:
    """Replay `graph` once: why it is refused (None: `output` is then `eager`, the last warm-up run's output, within
    `VERIFY_TOLERANCE` of the largest `unit`; the sentence names `whose` replay and the eager `reference`)."""
    with torch.inference_mode():
        graph.replay()
    deviation = relative_deviation(output, eager)
    limit = bound(VERIFY_TOLERANCE, dtype)
    if deviation <= limit:
        return None
    return (f"{whose} first replay deviates from {reference} by {deviation:.3g} of the largest {unit} "
            f"(bound {limit:g})")


class GraphRecorder:
    """How one model's graphs are recorded: on one capture stream, after warm-up runs on one side stream (cuBLAS
    keeps a workspace per stream), both made on first use, into a memory pool per kind of graph, which a capture CUDA
    refused is never recorded into again (see the module docstring)."""

    def __init__(self) -> None:
        self.pools: dict[Any, Any] = {}  # kind -> the memory pool its graphs share
        self.streams: tuple[torch.cuda.Stream, torch.cuda.Stream] | None = None  # (capture, warm-up)

    def record(self, run: Callable[[], torch.Tensor], device: torch.device,
               kind: Any = None) -> tuple[torch.cuda.CUDAGraph, torch.Tensor, torch.Tensor]:
        """Run `run` `WARMUP_RUNS` times on the warm-up stream, then record one more run on the capture stream into
        the memory pool of the graphs of `kind`, on `device`: the graph, the tensor its replays write, and a copy of
        the last warm-up run's output (an eager run of the same inputs, to verify the graph against). Where CUDA
        refuses to record, the pool is released and dropped, and `GraphCaptureError` raised."""
        with torch.cuda.device(device):
            if self.streams is None:  # (torch's default capture stream is made once, on whichever GPU was current)
                self.streams = torch.cuda.Stream(device=device), torch.cuda.Stream(device=device)
            stream, warmup_stream = self.streams
            pool = self.pools[kind] if kind in self.pools else torch.cuda.graph_pool_handle()
            warmup_stream.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(warmup_stream):
                for _ in range(WARMUP_RUNS):
                    eager = run()
                eager = eager.clone()
            torch.cuda.current_stream(device).wait_stream(warmup_stream)
            graph = torch.cuda.CUDAGraph()
            try:
                with torch.cuda.stream(torch.cuda.current_stream(device)):  # (this stream again, should capture fail)
                    with torch.cuda.graph(graph, pool=pool, stream=stream):
                        output = run()
            except Exception as error:
                self.pools.pop(kind, None)  # (never captured into again)
                _release_failed_capture(device, pool)
                raise GraphCaptureError(str(error)) from error
            self.pools[kind] = pool
            torch.cuda.synchronize(device)
        return graph, output, eager


@contextlib.contextmanager
def _capture_mode(guided: bool) -> Any:
    """The autograd state a capture runs in. Plain and conditioned sampling: inference mode (as a policy or server
    calls the model). Guided sampling differentiates every step: no_grad instead (functorch's transforms re-enable
    gradients inside it), and backward on this thread (`set_multithreading_enabled(False)`): for CUDA tensors autograd
    otherwise runs the backward on its own device thread, outside the thread whose stream is being captured."""
    if not guided:
        with torch.inference_mode():
            yield
        return
    with torch.no_grad(), torch.autograd.set_multithreading_enabled(False):
        yield


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
