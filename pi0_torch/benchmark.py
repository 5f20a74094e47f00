"""`pi0-torch bench`: latency, memory and FLOP/s of `generate_actions`, a training step, and loading.

Prints tables; nothing here is asserted. Every configuration runs in this process one after another, after
warm-up, with the median/min/max over `--repeats` runs. Peak memory is the whole footprint, weights included: the
CUDA allocator's peak on GPU, the process's peak resident set size (sampled every 2 ms) on CPU.

    pi0-torch bench                                     # small + medium, 1 and 3 cameras, batch 1 and 8
    pi0-torch bench --presets pi0 --dtypes bfloat16 --cameras 3 --batches 1   # full size
    pi0-torch bench --presets pi0,pi05 --dtypes bfloat16 --compile --device cuda
                                                        # GPU: eager, graph, compiled, compiled+graph rows, set-up,
                                                        # and each row's GPU work (profiler: activities, GPU ms,
                                                        # the host's time to its last launch and its waits)
    pi0-torch bench --rtc guidance,conditioning         # also chunks continued by real-time chunking
    pi0-torch bench --ops                               # ATen ops of one generate_actions (a launch-count proxy)
    pi0-torch bench --device cuda --kernels auto,torch --gemms   # fused kernels against the torch path, per GEMM too
    pi0-torch bench --side-by-side                      # against transformers' PI0, identical weights
    pi0-torch bench --loading                           # peak RSS of from_pretrained on a full-size bf16 checkpoint
    pi0-torch bench --fast --compile                    # π0-FAST decoding (tokens/s, ms per chunk) after π0's rows
    pi0-torch bench --export                            # the exported sampling: eager against onnxruntime and AOTInductor

bfloat16 rows are skipped, with a note, on a device without bfloat16 instructions (`pi0_torch.utils.hardware`, read
from the device's capabilities): there bfloat16 is emulated, many times slower than float32, and its rows would time
the emulation.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import itertools
import io
import statistics
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import psutil
import torch

from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
from pi0_torch.utils.timing import seconds, time_alternating
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
from pi0_torch.inference.conditioning import euler_times
from pi0_torch.kernels.reference import rope_cos_sin
from pi0_torch.inference.checks import relative_deviation
from pi0_torch.inference.layer_pass import decoder_sampling_weights
from pi0_torch.inference.layout import InputFacts
from pi0_torch.inference.plan import SamplingInputs, SamplingPlan, SamplingRoute
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.inference.rtc import DEFAULT_MAX_GUIDANCE, METHODS
from pi0_torch.utils import hardware
from pi0_torch.utils.op_count import AtenOpCounter

TEXT_TOKENS = 48
DEFAULT_PRESETS, DEFAULT_CAMERAS = ["pi0_small", "pi0_medium"], [1, 3]
RTC_DELAY, RTC_EXECUTED = 3, 5  # --rtc rows: the continued chunk's inference delay and the steps executed before it


# -- measuring ------------------------------------------------------------------------------------------------------------


@dataclass
class Timing:
    median: float
    minimum: float
    maximum: float
    peak_bytes: int

    def row(self) -> str:
        return f"{self.median * 1e3:10.1f} {self.minimum * 1e3:10.1f} {self.maximum * 1e3:10.1f} {self.peak_bytes / 2**20:10.0f}"


@contextlib.contextmanager
def peak_memory(device: torch.device) -> Iterator[list[int]]:
    """Yields a one-element list that holds the peak bytes in use during the block once it ends. On CUDA: what the
    caching allocator held at most (freed blocks given back first), CUDA graphs' memory pools included, whose
    intermediate tensors count as freed between replays but stay reserved."""
    result = [0]
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        yield result
        torch.cuda.synchronize(device)
        result[0] = torch.cuda.max_memory_reserved(device)
        return
    process = psutil.Process()
    peak = process.memory_info().rss
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.wait(0.002):
            peak = max(peak, process.memory_info().rss)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        yield result
    finally:
        done.set()
        sampler.join()
        result[0] = max(peak, process.memory_info().rss)


def time_call(fn: Callable[[], object], device: torch.device, repeats: int, warmup: int = 1) -> Timing:
    for _ in range(warmup):
        fn()
    with peak_memory(device) as peak:
        durations = [seconds(fn, device) for _ in range(repeats)]
    return Timing(statistics.median(durations), min(durations), max(durations), peak[0])


@dataclass(frozen=True)
class GpuWork:
    """What one call ran on a CUDA device, by the profiler (CUPTI): its GPU activities (kernels, copies, memsets), their
    summed GPU time, per activity name its count and GPU seconds (longest first), and the host's side of the call:
    `issue_seconds`, from the call's start to the end of its last launch (kernel, graph, copy or memset), and
    `wait_seconds`, what the host spent before that in copies and synchronizing calls (a read of a device value waits
    there for the device), or None where the profile has no launch events. Against the call's wall time they tell a call
    bound by the host's launches (issue near the wall time) from a GPU-bound one (GPU time near it) and from one
    that waits on the device mid-call. The profiler's own work per op makes the host's numbers a little high."""

    activities: int
    gpu_seconds: float
    table: list[tuple[str, int, float]]
    issue_seconds: float | None
    wait_seconds: float | None


# the CUDA runtime and driver calls the profiler records on the host (`cuLaunchKernel*`: triton's launches)
LAUNCH_CALLS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaGraphLaunch", "cudaMemcpyAsync", "cudaMemsetAsync")
WAITING_CALLS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cuStreamSynchronize",
                 "cuCtxSynchronize", "cudaMemcpy")  # (a copy to the host waits inside `cudaMemcpyAsync`)


def gpu_work(fn: Callable[[], object], device: torch.device) -> GpuWork:
    """What one call of `fn` runs on a CUDA `device`, by the profiler: see `GpuWork`."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize(device)
    with warnings.catch_warnings():  # (torch 2.11 warns, once, that a profile keeps only its own events: it is one call)
        warnings.filterwarnings("ignore", message=".*Profiler clears events")
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as profiler:
            fn()
            torch.cuda.synchronize(device)  # (its wait comes after the last launch: not counted as the call's)
    events = profiler.events()
    work = [event for event in events  # (not the GPU copies of annotated ranges: compiled code's calls)
            if event.device_type == torch.autograd.DeviceType.CUDA and not getattr(event, "is_user_annotation", False)]
    by_name: dict[str, list[float]] = {}
    for event in work:
        by_name.setdefault(event.name, []).append(event.time_range.elapsed_us() / 1e6)
    table = sorted(((name, len(times), sum(times)) for name, times in by_name.items()), key=lambda row: -row[2])
    return GpuWork(len(work), sum(event.time_range.elapsed_us() for event in work) / 1e6, table, *host_side(events))


def host_side(events: Sequence[Any]) -> tuple[float | None, float | None]:
    """`GpuWork.issue_seconds` and `wait_seconds` from a profile's events (None, None: no launch among them)."""
    host = [event for event in events if event.device_type == torch.autograd.DeviceType.CPU]
    launches = [event for event in host if event.name.startswith(LAUNCH_CALLS)]
    if not launches:
        return None, None
    start = min(event.time_range.start for event in host)
    issued = max(event.time_range.end for event in launches)
    waits = sum(event.time_range.elapsed_us() for event in host
                if event.name.startswith(WAITING_CALLS) and event.time_range.end <= issued)
    return (issued - start) / 1e6, waits / 1e6


def print_kernel_table(table: list[tuple[str, int, float]], limit: int) -> None:
    """The `limit` activities of a call that took the most GPU time: count, GPU ms, microseconds each, name."""
    total = sum(spent for _, _, spent in table)
    for name, count, spent in table[:limit]:
        print(f"      {count:6d} x {spent * 1e3:7.3f} ms {spent / count * 1e6:8.1f} us {100 * spent / total:5.1f}%  {name[:110]}")


def graph_time(fn: Callable[[], object], device: torch.device, calls: int = 50, repeats: int = 10) -> float:
    """Median seconds of one call of `fn` on CUDA, `calls` of them captured in one CUDA graph and replayed `repeats`
    times: the kernels' own time, without the host's launch cost (tens of microseconds for a triton launch, as much
    as a skinny GEMM takes)."""
    stream = torch.cuda.Stream(device)
    stream.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(stream):
        for _ in range(3):
            fn()
    torch.cuda.current_stream(device).wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        for _ in range(calls):
            fn()
    graph.replay()
    durations = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        graph.replay()
        end.record()
        end.synchronize()
        durations.append(start.elapsed_time(end) / 1e3 / calls)
    return statistics.median(durations)


def matmul_throughput(device: torch.device, dtype: torch.dtype, size: int | None = None, repeats: int = 5) -> float:
    """Measured FLOP/s of a square matmul: the machine's ceiling to compare the model against."""
    size = size or (8192 if device.type == "cuda" else 2048)
    a = torch.randn(size, size, device=device, dtype=dtype)
    b = torch.randn(size, size, device=device, dtype=dtype)
    timing = time_call(lambda: a @ b, device, repeats)
    return 2 * size**3 / timing.minimum


def generate_flops(config: PI0Config, cameras: int, batch: int, text_tokens: int = TEXT_TOKENS, steps: int | None = None) -> float:
    """Multiply-add FLOPs (x2) of `generate_actions` as this implementation runs it (matmuls and attention)."""
    steps = steps or config.num_inference_steps
    W, M, T = config.vision_hidden_size, config.vision_intermediate_size, config.tokens_per_image
    siglip = T * (3 * config.patch_size**2 * W + config.vision_num_layers * (4 * W * W + 2 * W * M + 2 * T * W) + W * config.vlm_hidden_size)
    N, K, H = config.num_attention_heads, config.num_key_value_heads, config.head_dim

    def layer(width: int, mlp: int, kv_len: int) -> int:  # per token
        return width * (N + 2 * K) * H + N * H * width + 3 * width * mlp + 2 * kv_len * N * H

    P = cameras * T + text_tokens
    S = config.suffix_len
    vlm = P * ((config.num_hidden_layers - 1) * layer(config.vlm_hidden_size, config.vlm_intermediate_size, P)
               + config.vlm_hidden_size * (N + 2 * K) * H)  # the last layer only computes its k/v
    suffix = S * config.num_hidden_layers * layer(config.expert_hidden_size, config.expert_intermediate_size, P + S)
    return 2.0 * batch * (cameras * siglip + vlm + steps * suffix)


def example_batch(config: PI0Config, cameras: int, batch: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random inputs with the first `cameras` cameras present and the rest masked."""
    generator = torch.Generator().manual_seed(seed)
    size = config.image_size
    image_masks = torch.zeros(batch, config.num_cameras, dtype=torch.bool)
    image_masks[:, :cameras] = True
    inputs = dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        image_masks=image_masks,
        input_ids=torch.randint(1, config.vocab_size, (batch, TEXT_TOKENS), generator=generator),
        attention_mask=torch.ones(batch, TEXT_TOKENS, dtype=torch.bool),
        state=torch.randn(batch, config.action_dim, generator=generator),
    )
    return {k: v.to(device) for k, v in inputs.items()}


def random_model(config: PI0Config, dtype: torch.dtype, device: torch.device) -> PI0ForActionGeneration:
    """A model with random weights, initialised on `device` (a full-size one: a minute on a CPU, a second on a GPU)."""
    torch.manual_seed(0)
    with device:
        model = PI0ForActionGeneration(config)
    return model.to(dtype).eval()


# -- benchmarks -------------------------------------------------------------------------------------------------------------


def generate_modes(compile: bool, device: torch.device) -> dict[str, dict[str, Any] | None]:
    """How π0-FAST's `generate_tokens` runs, by name -> `compile_decoding` arguments (None: eager; "cuda-graph": the
    prefill and each token replay hand-captured CUDA graphs, `capture_decoding`, on CUDA). With `--compile`: also
    compiled, and on CUDA compiled and replayed as inductor's CUDA graphs ("compiled-graph")."""
    cuda = device.type == "cuda"
    modes: dict[str, dict[str, Any] | None] = {"eager": None, **({"cuda-graph": None} if cuda else {})}
    if compile:
        modes["compiled"] = {}
        if cuda:
            modes["compiled-graph"] = {"mode": "reduce-overhead"}
    return modes


def sampling_modes(compile: bool, device: torch.device) -> list[str]:
    """How π0's `generate_actions` runs: eager; on CUDA one hand-captured CUDA graph (`capture_sampling`, no
    compiler); with `--compile` also the regionally compiled layers (`compile_sampling`), and on CUDA those replayed
    inside the graph."""
    cuda = device.type == "cuda"
    return ["eager"] + (["graph"] if cuda else []) + (["compiled"] + (["compiled+graph"] if cuda else []) if compile else [])


def set_sampling_mode(model: PI0ForActionGeneration, mode: str) -> None:
    model.compile_sampling(disable=True)  # (and no graphs)
    if mode.startswith("compiled"):
        model.compile_sampling()
    if mode.endswith("graph"):
        model.capture_sampling()


def rtc_options(config: PI0Config, batch: int, device: torch.device, method: str) -> dict[str, Any]:
    """`generate_actions` arguments that continue a (random) previous chunk by real-time chunking with `method`:
    `RTC_DELAY` steps of inference delay, `RTC_EXECUTED` executed since the previous chunk started."""
    generator = torch.Generator().manual_seed(1)
    previous = torch.randn(batch, config.action_horizon, config.action_dim, generator=generator).to(device)
    return dict(previous_actions=previous, inference_delay=RTC_DELAY, execution_horizon=RTC_EXECUTED, rtc_method=method)


def bench_generate(args: argparse.Namespace, device: torch.device) -> None:
    plotted: list[tuple[str, float, float, float]] = []  # (row, median, fastest, slowest ms): --plot
    print(f"\ngenerate_actions on {device_name(device)}, {TEXT_TOKENS} text tokens, 50 actions, 10 steps; set-up: the "
          "first call in each mode (compiling, capturing)"
          + (f"; rtc: continuing a chunk (delay {RTC_DELAY}, {RTC_EXECUTED} steps executed; FLOP/s of plain sampling "
             "not shown)" if args.rtc else ""))
    peaks = {dtype: matmul_throughput(device, getattr(torch, dtype)) for dtype in args.dtypes}
    print("measured matmul ceiling: " + ", ".join(f"{d} {v / 1e9:.0f} GFLOP/s" for d, v in peaks.items()))
    cuda = device.type == "cuda"  # (then also the GPU work of one call: activities and their time, by the profiler)
    if cuda:
        from pi0_torch.kernels import ops

        if (reason := ops.triton_reason(device)) is None:
            from pi0_torch.kernels.launch import launch_mode

            reason = launch_mode()
        print(f"fused kernels: {reason}")
    print(f"{'preset':12s} {'dtype':9s} {'mode':14s} {'steps':8s} {'rtc':12s} {'cams':>4s} {'batch':>5s} {'set-up s':>8s} {'median ms':>10s} "
          f"{'min ms':>10s} {'max ms':>10s} {'peak MiB':>10s} {'GFLOP/s':>8s} {'% peak':>6s}"
          + (f" {'GPU ops':>7s} {'GPU ms':>7s} {'host ms':>7s} {'waits':>7s}" if cuda else ""))
    for preset in args.presets:
        config = PI0Config.from_preset(preset, rtc_max_delay=RTC_DELAY if "conditioning" in args.rtc else 0)
        for dtype_name in args.dtypes:
            model = random_model(config, getattr(torch, dtype_name), device)
            for mode, kernels in ((mode, kernels) for mode in sampling_modes(args.compile, device) for kernels in args.kernels):
                if mode.startswith("compiled") and kernels != args.kernels[0]:
                    continue  # (compiled layers run their own kernels)
                set_sampling_mode(model, mode)
                model.sampling_kernels = kernels
                for cameras in args.cameras:
                    for batch in args.batches:
                        inputs = example_batch(config, cameras, batch, device)
                        for method in [None, *args.rtc]:
                            options = {} if method is None else rtc_options(config, batch, device, method)
                            # in inference mode, as a policy or server runs the model: compiled layers see the same
                            # grad mode in every row, CUDA graphs' warm-ups included, and compile once
                            call = torch.inference_mode()(functools.partial(model.generate_actions, **inputs, **options))
                            setup = seconds(call, device)
                            timing = time_call(call, device, args.repeats)
                            achieved = generate_flops(config, cameras, batch) / timing.median
                            rate = f"{achieved / 1e9:8.0f} {100 * achieved / peaks[dtype_name]:6.0f}" if method is None else f"{'-':>8s} {'-':>6s}"
                            work, table = "", []
                            if cuda:
                                profiled = gpu_work(call, device)
                                table = profiled.table
                                work = f" {profiled.activities:7d} {profiled.gpu_seconds * 1e3:7.1f} " + " ".join(
                                    "      -" if host is None else f"{host * 1e3:7.1f}"
                                    for host in (profiled.issue_seconds, profiled.wait_seconds))
                            refused = method == "guidance" and model.sampling_captured and not model.replays_graphs(method)
                            label = "guid. eager" if refused else method or "-"  # (guided chunks replay no graph)
                            fused = steps_label(model.last_sampling_route)
                            print(f"{preset:12s} {dtype_name:9s} {mode:14s} {fused:8s} {label:12s} {cameras:4d} {batch:5d} "
                                  f"{setup:8.1f} {timing.row()} {rate}{work}")
                            row = f"{preset} {dtype_name} {mode} {fused}{'' if method is None else ' ' + label}"
                            plotted.append((f"{row} {cameras} cam b{batch}", timing.median * 1e3, timing.minimum * 1e3,
                                            timing.maximum * 1e3))
                            print_kernel_table(table, args.kernel_table)
            del model
            gc.collect()
    if args.plot:
        from pi0_torch.utils.charts import bar_chart

        title = (f"generate_actions on {device_name(device)}: median ms per chunk ({TEXT_TOKENS} text tokens, "
                 "50 actions)")
        bar_chart(plotted, title, " ms").save(args.plot)
        print(f"wrote {args.plot}")


def steps_label(route: SamplingRoute) -> str:
    """What ran a row's Euler steps (its last call's `SamplingRoute`): "fused" (five launches per decoder layer),
    "persist." (fused, each step's decoder layers in one launch), "torch", or "refused" (a first call's verification
    refused the fused steps for this batch size and camera count, or under "auto" the persistent launch: the row ran
    unfused, or five launches per layer)."""
    if any(not refusal.startswith("CUDA graph") for refusal in route.refusals):
        return "refused"
    return {"triton": "fused", "persistent": "persist."}.get(route.steps, route.steps)


def bench_op_counts(args: argparse.Namespace) -> None:
    """ATen ops of one `generate_actions` on the CPU (a proxy for GPU kernel launches; `pi0_torch.utils.op_count`)."""
    print("\nATen ops of one generate_actions (CPU, float32, 3 cameras, batch 1, 20 of 48 prompt tokens, 10 steps; "
          "RMSNorm and attention counted as the one op each is on CUDA)")
    print(f"{'preset':12s} {'ops':>6s} {'views':>6s} {'kernels':>7s} {'CPU ops':>7s} {'host reads':>10s}")
    for preset in args.presets:
        config = PI0Config.from_preset(preset)
        model = random_model(config, torch.float32, torch.device("cpu"))
        inputs = example_batch(config, 3, 1, torch.device("cpu"))
        inputs["attention_mask"] = torch.arange(TEXT_TOKENS)[None] < 20
        model.generate_actions(**inputs)
        with AtenOpCounter() as counter:
            model.generate_actions(**inputs)
        print(f"{preset:12s} {counter.total:6d} {counter.views:6d} {counter.kernels:7d} {counter.dispatched:7d} "
              f"{counter.host_reads:10d}")
        del model
        gc.collect()
    print(f"\nATen ops of the sampling a CUDA graph captures, full size, bfloat16, batch 1, {TEXT_TOKENS} prompt tokens, "
          "10 steps (counted on the meta device: no weights)")
    print("(steps 'fused': the fused kernels, as on CUDA in bf16, each kernel one op; 'persist.': the same with each "
          "step's decoder layers in one (sampling_kernels='persistent'); per layer and step: the kernels of the 10 steps "
          "/ (10 x layers))")
    print(f"{'preset':12s} {'steps':8s} {'cameras':>7s} {'ops':>6s} {'views':>6s} {'kernels':>7s} {'host copies':>11s} "
          f"{'per layer-step':>14s}")
    for preset in ("pi0", "pi05"):
        for steps, fused, persistent in (("torch", False, False), ("fused", True, False), ("persist.", True, True)):
            for cameras in (1, 3):
                config = PI0Config.from_preset(preset)
                shown = tuple(camera < cameras for camera in range(config.num_cameras))
                facts = InputFacts((shown,), (TEXT_TOKENS,), TEXT_TOKENS)
                _, counter = sample_on_meta(config, facts, config.num_inference_steps, torch.bfloat16, fused=fused,
                                            persistent=persistent)
                _, one_step = sample_on_meta(config, facts, 1, torch.bfloat16, fused=fused, persistent=persistent)
                per_step = (counter.kernels - one_step.kernels) / ((config.num_inference_steps - 1) * config.num_hidden_layers)
                print(f"{preset:12s} {steps:8s} {cameras:7d} {counter.total:6d} {counter.views:6d} "
                      f"{counter.kernels:7d} {counter.host_copies:11d} {per_step:14.2f}")
    print("\nATen ops of one π0-FAST decoded token (decode_step), full size, bfloat16, batch 1, 3 cameras, "
          f"{TEXT_TOKENS} prompt tokens (meta device; layers 'fused': decoding_kernels as on CUDA in bf16)")
    print(f"{'preset':12s} {'layers':7s} {'ops':>6s} {'views':>6s} {'kernels':>7s} {'host copies':>11s} {'per layer':>9s}")
    config = PI0FastConfig.from_preset("pi0_fast")
    for fused in (False, True):
        counter = decode_step_on_meta(config, fused)
        print(f"{'pi0_fast':12s} {'fused' if fused else 'torch':7s} {counter.total:6d} {counter.views:6d} {counter.kernels:7d} "
              f"{counter.host_copies:11d} {counter.kernels / config.num_hidden_layers:9.2f}")


@dataclass
class StepGemm:
    """One GEMM of a fused sampling step: cuBLAS's `torch.mm` on the transposed weight (what the torch path runs),
    the fused op that replaces it (its norm, RoPE, GeGLU or residual included; from `triton_kernels.CUBLAS_ROWS`
    rows on that op is cuBLAS's GEMM with the epilogue kernels around it), the bytes of one weight, and
    `deviation()`: the fused op against its torch reference on the same operands (max |diff| / max |reference|). Each
    call of `cublas` and `fused` takes the next of several copies of the weight, together larger than the GPU's L2
    cache, as each layer of a step reads its own weights from memory."""

    cublas: Callable[[], object]
    fused: Callable[[], object]
    weight_bytes: int
    deviation: Callable[[], float]


def step_gemms(config: PI0Config, batch: int, device: torch.device, cache_bytes: int = 256 * 2**20) -> dict[str, StepGemm]:
    """The GEMMs of one fused sampling step of `config` (bf16, batch x action_horizon rows, random operands), by
    name; see `StepGemm`."""
    from pi0_torch.kernels import reference, triton_kernels

    generator = torch.Generator(device).manual_seed(0)
    width, mlp, heads, head_dim = (config.expert_hidden_size, config.expert_intermediate_size, config.num_attention_heads,
                                   config.head_dim)
    rows = batch * config.action_horizon

    def randn(*shape: int) -> torch.Tensor:
        return (torch.randn(*shape, generator=generator, device=device) * shape[-1] ** -0.5).to(torch.bfloat16)

    def weights(columns: int, depth: int) -> Callable[[], torch.Tensor]:  # the next copy at each call, [depth, columns]
        copies = [randn(columns, depth).t() for _ in range(max(2, -(-cache_bytes // (2 * columns * depth))))]
        turn = itertools.cycle(copies)
        return lambda: next(turn)

    def deviation(name: str, *arguments: Any) -> Callable[[], float]:
        def measure() -> float:
            ours = [a.clone() if isinstance(a, torch.Tensor) else a for a in arguments]
            theirs = [a.clone() if isinstance(a, torch.Tensor) else a for a in arguments]
            got, want = getattr(triton_kernels, name)(*ours), getattr(reference, name)(*theirs)
            return relative_deviation(got, want) if got is not None else relative_deviation(ours[0], theirs[0])  # (in place)
        return measure

    x, scale = randn(rows, width), 1 + randn(width)
    positions = torch.arange(config.action_horizon, device=device)[None] + 900  # (a RoPE table: its halves repeat)
    cos, sin = rope_cos_sin(positions.expand(batch, -1), head_dim, 10_000.0)
    cache = torch.zeros(batch, 1024, head_dim, device=device, dtype=torch.bfloat16)
    qkv_w, o_w = weights((heads + 2) * head_dim, width), weights(width, heads * head_dim)
    gate_up_w, down_w = weights(2 * mlp, width), weights(width, mlp)
    attended, hidden = randn(rows, heads * head_dim), randn(rows, mlp)
    return {
        "qkv": StepGemm(lambda: x @ qkv_w(), lambda: triton_kernels.norm_qkv_rope(x, scale, None, qkv_w(), cos, sin, cache, cache, 0, 1e-6),
                        2 * width * (heads + 2) * head_dim,
                        deviation("norm_qkv_rope", x, scale, None, qkv_w(), cos, sin, cache, cache.clone(), 0, 1e-6)),
        "o": StepGemm(lambda: attended @ o_w(), lambda: triton_kernels.matmul_residual_(x, attended, o_w(), None),
                      2 * width * heads * head_dim, deviation("matmul_residual_", x, attended, o_w(), None)),
        "gate_up": StepGemm(lambda: x @ gate_up_w(), lambda: triton_kernels.norm_gate_up_geglu(x, scale, None, gate_up_w(), 1e-6),
                            4 * width * mlp, deviation("norm_gate_up_geglu", x, scale, None, gate_up_w(), 1e-6)),
        "down": StepGemm(lambda: hidden @ down_w(), lambda: triton_kernels.matmul_residual_(x, hidden, down_w(), None),
                         2 * width * mlp, deviation("matmul_residual_", x, hidden, down_w(), None)),
    }


def bench_gemms(args: argparse.Namespace, device: torch.device) -> None:
    """The GEMMs of one fused sampling step of each preset (bf16, batch x 50 rows): cuBLAS against the fused op that
    replaces it, in microseconds and GB/s of weights read (the bound of a skinny GEMM: HBM bandwidth), each timed as
    50 calls in one CUDA graph (a triton launch's host cost is as long as the kernel) over weights that do not fit
    the L2 cache together, and the fused op's deviation from its torch reference."""
    if device.type != "cuda":
        print(f"\nGEMM shapes: skipped on {device.type} (the fused kernels run on CUDA)")
        return
    print(f"\nsampling-step GEMMs on {device_name(device)}, bf16: cuBLAS against the fused kernel (50 calls in a CUDA "
          f"graph, median of {args.repeats} replays)")
    print(f"{'preset':8s} {'GEMM':9s} {'M':>5s} {'MiB':>6s} {'cuBLAS us':>10s} {'GB/s':>7s} {'fused us':>9s} {'GB/s':>7s} "
          f"{'deviation':>9s}")
    for preset in args.presets:
        config = PI0Config.from_preset(preset)
        for batch in args.batches:
            for name, gemm in step_gemms(config, batch, device).items():
                size = gemm.weight_bytes
                cublas_us, fused_us = (graph_time(fn, device, repeats=args.repeats) * 1e6 for fn in (gemm.cublas, gemm.fused))
                print(f"{preset:8s} {name:9s} {batch * config.action_horizon:5d} {size / 2**20:6.1f} {cublas_us:10.1f} "
                      f"{size / cublas_us / 1e3:7.0f} {fused_us:9.1f} {size / fused_us / 1e3:7.0f} {gemm.deviation():9.1e}")


def sample_on_meta(
    config: PI0Config, facts: InputFacts, steps: int, dtype: torch.dtype = torch.float32, rtc_method: str | None = None,
    fused: bool = False, count: bool = True, persistent: bool = False,
) -> tuple[torch.Tensor, AtenOpCounter | None]:
    """Run `generate_actions`' sampling region (`sample_planned`: everything after the input checks, what `capture_sampling`
    records) for a model built on the meta device, with inputs laid out as `facts` says: the actions (shapes only)
    and the ops it ran (`fused`: the steps in the fused kernels, as on CUDA in bf16, each kernel one op, with
    `persistent` each step's decoder layers in one, as `sampling_kernels="persistent"` runs them; `count=False`:
    not counted, None, and the fused ops call their implementations instead of their fakes). No weights are needed,
    so a full-size model costs no memory, and any read of a device value on the host (`.item()`, `bool()`,
    `.tolist()`, `nonzero`) raises."""
    meta = torch.device("meta")
    with meta:
        model = PI0ForActionGeneration(config).eval().to(dtype)
    layout = facts.layout(config.tokens_per_image)
    batch, text = len(facts.text_counts), facts.text_length
    actions = (batch, config.action_horizon, config.action_dim)
    inputs = SamplingInputs(
        pixel_values=torch.empty(batch, len(layout.cameras), 3, config.image_size, config.image_size, device=meta),
        image_masks=torch.empty(batch, len(layout.cameras), dtype=torch.bool, device=meta),
        input_ids=torch.empty(batch, text, dtype=torch.long, device=meta),
        attention_mask=torch.empty(batch, text, dtype=torch.bool, device=meta),
        state=None if config.pi05 else torch.empty(batch, config.action_dim, device=meta),
        noise=torch.empty(actions, device=meta),
        times=torch.empty(steps, device=meta),
        target=None if rtc_method is None else torch.empty(actions, device=meta),
        weights=torch.empty(actions[:2], device=meta) if rtc_method == "guidance" else None,
        committed=torch.empty(actions[:2], dtype=torch.bool, device=meta) if rtc_method == "conditioning" else None,
    )
    max_guidance = DEFAULT_MAX_GUIDANCE if rtc_method == "guidance" else 0.0
    with torch.no_grad(), (AtenOpCounter() if count else contextlib.nullcontext()) as counter:
        plan = SamplingPlan(layout, tuple(euler_times(steps)), rtc_method, max_guidance,
                            ("persistent" if persistent else "triton") if fused else "torch")
        sampled = model.sample_planned(inputs, plan)
    return sampled, counter


def decode_step_on_meta(config: PI0FastConfig, fused: bool, steps: int = 8, count: bool = True) -> AtenOpCounter | None:
    """The ops of one π0-FAST `decode_step` (the third of `steps` slots) for a model built on the meta device, after
    a prefill of every camera and `TEXT_TOKENS` prompt tokens (`fused`: the fused kernels, as `decoding_kernels` runs
    them on CUDA in bf16, each one op; `count=False`: not counted, as `sample_on_meta`). No weights; any host read of
    a device value raises."""
    meta = torch.device("meta")
    with meta:
        model = PI0FastForActionGeneration(config).eval().to(torch.bfloat16)
    cameras, size = config.num_cameras, config.image_size
    prompt = (torch.empty(1, TEXT_TOKENS, dtype=torch.long, device=meta), torch.empty(1, TEXT_TOKENS, dtype=torch.bool, device=meta),
              torch.empty(1, TEXT_TOKENS, dtype=torch.bool, device=meta))
    with torch.no_grad():
        cache, _ = model.prepare_decoding(torch.empty(1, cameras, 3, size, size, dtype=torch.bfloat16, device=meta),
                                          torch.empty(1, cameras, dtype=torch.bool, device=meta), *prompt, steps,
                                          decoder_sampling_weights(model.layers) if fused else None)
        token, step = torch.empty(1, dtype=torch.long, device=meta), torch.arange(steps, device=meta)[2:3]
        with (AtenOpCounter() if count else contextlib.nullcontext()) as counter:
            model.decode_step(cache, token, step)
    return counter


def bench_fast_decoding(args: argparse.Namespace, device: torch.device) -> None:
    """π0-FAST: a chunk of `--fast-tokens` decoded tokens (no EOS stop), every camera, as `generate_tokens` runs it:
    the prefill (SigLIP + prompt through the decoder, k/v kept, first token) and then one decoder pass per token."""
    tokens = args.fast_tokens
    print(f"\nπ0-FAST generate_tokens on {device_name(device)}, 3 cameras, {TEXT_TOKENS} prompt tokens, {tokens} decoded "
          f"tokens per chunk (prefill: up to the first token; per token: each later one)")
    print(f"{'preset':16s} {'dtype':9s} {'mode':14s} {'kernels':7s} {'batch':>5s} {'chunk ms':>9s} {'prefill ms':>10s} "
          f"{'ms/token':>8s} {'tokens/s':>9s} {'peak MiB':>9s}")
    for preset in args.fast_presets:
        config = PI0FastConfig.from_preset(preset, eos_token_id=None)  # every row decodes all the tokens
        for dtype_name in args.dtypes:
            torch.manual_seed(0)
            with device:  # (initialized where it runs: a full-size model's random init is slow on the host)
                model = PI0FastForActionGeneration(config).to(getattr(torch, dtype_name)).eval()
            for (mode, compile_arguments), kernels in itertools.product(generate_modes(args.compile, device).items(), args.kernels):
                reason = model.decoding_graphs_reason() if mode == "compiled-graph" else None
                if reason is not None:
                    print(f"{preset:16s} {dtype_name:9s} {mode:14s} skipped: {reason}")
                    continue
                model.decoding_kernels = kernels  # (the same names as sampling_kernels: see `decoding_kernels`)
                model.compile_decoding(**(compile_arguments if compile_arguments is not None else {"disable": True}))
                model.capture_decoding(disable=mode != "cuda-graph")
                warmup = 1 if compile_arguments is None else 3  # compiling; inductor's graphs record on a later call
                for batch in args.batches:
                    inputs = fast_example_batch(config, batch, device)
                    chunk = time_call(lambda: model.generate_tokens(**inputs, max_new_tokens=tokens), device, args.repeats, warmup)
                    prefill = time_call(lambda: model.generate_tokens(**inputs, max_new_tokens=1), device, args.repeats, warmup)
                    per_token = max(chunk.median - prefill.median, 0.0) / max(tokens - 1, 1)
                    rate = f"{batch / per_token:9.1f}" if per_token > 0 else f"{'-':>9s}"
                    print(f"{preset:16s} {dtype_name:9s} {mode:14s} {kernels:7s} {batch:5d} {chunk.median * 1e3:9.1f} "
                          f"{prefill.median * 1e3:10.1f} {per_token * 1e3:8.2f} {rate} {chunk.peak_bytes / 2**20:9.0f}")
            del model
            gc.collect()


def fast_example_batch(config: PI0FastConfig, batch: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random π0-FAST inference inputs: every camera present, a prompt of `TEXT_TOKENS` tokens (all bidirectional)."""
    generator = torch.Generator().manual_seed(seed)
    size = config.image_size
    inputs = dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        image_masks=torch.ones(batch, config.num_cameras, dtype=torch.bool),
        input_ids=torch.randint(2, config.vocab_size, (batch, TEXT_TOKENS), generator=generator),
        attention_mask=torch.ones(batch, TEXT_TOKENS, dtype=torch.bool),
        token_ar_mask=torch.zeros(batch, TEXT_TOKENS, dtype=torch.bool),
    )
    return {k: v.to(device) for k, v in inputs.items()}


def bench_train_step(args: argparse.Namespace, device: torch.device) -> None:
    print(f"\ntraining step (forward + backward + AdamW) on {device_name(device)}, 3 cameras")
    print(f"{'preset':12s} {'dtype':9s} {'batch':>5s} {'median ms':>10s} {'min ms':>10s} {'max ms':>10s} {'peak MiB':>10s}")
    for preset in args.presets:
        config = PI0Config.from_preset(preset)
        for dtype_name in args.dtypes:
            model = random_model(config, torch.float32, device).train()
            optimizer = torch.optim.AdamW(model.parameters(), lr=1e-5, betas=(0.9, 0.95))
            autocast_dtype = getattr(torch, dtype_name)
            for batch in args.batches:
                inputs = example_batch(config, 3, batch, device)
                actions = torch.randn(batch, config.action_horizon, config.action_dim, device=device)

                def step() -> None:
                    with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype != torch.float32):
                        loss = model(**inputs, actions=actions).loss
                    loss.backward()
                    optimizer.step()
                    optimizer.zero_grad(set_to_none=True)

                timing = time_call(step, device, args.repeats)
                print(f"{preset:12s} {dtype_name:9s} {batch:5d} {timing.row()}")
            del model, optimizer
            gc.collect()


def bench_side_by_side(args: argparse.Namespace, device: torch.device) -> None:
    """Ours vs transformers' `PI0ForConditionalGeneration` with identical weights, inputs and noise (π0)."""
    from transformers import PI0ForConditionalGeneration

    from pi0_torch.conversion.convert_hf import export_to_transformers, transformers_pi0_inputs

    preset = args.side_by_side_preset
    config = PI0Config.from_preset(preset)
    ours = random_model(config, torch.float32, device)
    with tempfile.TemporaryDirectory(dir=args.tmp_dir) as folder:
        ours.save_pretrained(f"{folder}/ours")
        export_to_transformers(f"{folder}/ours", f"{folder}/transformers")
        theirs = PI0ForConditionalGeneration.from_pretrained(f"{folder}/transformers").to(device).eval()
    print(f"\nside by side with transformers PI0 ({preset}, 3 cameras, batch 1, {TEXT_TOKENS} text tokens, 10 steps) "
          f"on {device_name(device)}; median (min) of {args.repeats} alternating runs")
    inputs = example_batch(config, 3, 1, device)
    noise = torch.randn(1, config.action_horizon, config.action_dim, generator=torch.Generator().manual_seed(1)).to(device)
    their_inputs = transformers_pi0_inputs(inputs, config)
    eager_sample = theirs.sample_actions
    modes = [(mode, torch.float32) for mode in sampling_modes(args.compile, device)]
    if not args.bf16_note:  # last: the weights are rounded to bf16 in place
        modes += [(mode, torch.bfloat16) for mode in sampling_modes(args.compile, device)]
    print(f"{'mode':14s} {'dtype':9s} {'ours ms':>15s} {'transformers ms':>17s} {'speedup':>8s} {'max |diff|':>11s}")
    print("(transformers' PI0 runs eager in eager and graph modes, compiled with mode='reduce-overhead' (CUDA) or "
          "default (CPU) in the compiled ones)")
    for label, dtype in modes:
        set_sampling_mode(ours, label)
        theirs_compile = {"mode": "reduce-overhead"} if device.type == "cuda" else {}
        theirs.sample_actions = (  # type: ignore[method-assign]
            torch.compile(eager_sample, **theirs_compile) if label.startswith("compiled") else eager_sample
        )
        ours.to(dtype)
        theirs.to(dtype)
        # transformers' PI0 takes floating inputs (noise too) in its weights' dtype
        their_dtype_inputs = {k: v.to(dtype) if v.is_floating_point() else v for k, v in their_inputs.items()}
        their_dtype_inputs["noise"] = noise.to(dtype)
        ours_call = torch.inference_mode()(lambda: ours.generate_actions(**inputs, noise=noise))  # (as bench_generate)
        their_call = torch.inference_mode()(lambda: theirs.sample_actions(**their_dtype_inputs))
        difference = (ours_call() - their_call().float()).abs().max().item()
        ours_times, their_times = time_alternating([ours_call, their_call], device, args.repeats)
        ours_median, their_median = statistics.median(ours_times), statistics.median(their_times)
        print(f"{label:14s} {str(dtype).removeprefix('torch.'):9s} {ours_median * 1e3:7.1f} ({min(ours_times) * 1e3:5.1f}) "
              f"{their_median * 1e3:9.1f} ({min(their_times) * 1e3:5.1f}) {their_median / ours_median:7.2f}x {difference:11.2e}")


def bench_loading(args: argparse.Namespace, device: torch.device) -> None:
    """Peak RSS of `from_pretrained` on a full-size bf16 π0 checkpoint (written with random weights first)."""
    config = PI0Config.from_preset(args.loading_preset)
    with tempfile.TemporaryDirectory(dir=args.tmp_dir) as folder:
        with torch.device("meta"):  # no float32 copy of 3B parameters: allocate bf16 directly, fill with noise
            model = PI0ForActionGeneration(config)
        model = model.to_empty(device="cpu").to(torch.bfloat16)
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.normal_(std=0.02)
        weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
        model.save_pretrained(folder)
        del model
        gc.collect()
        baseline = psutil.Process().memory_info().rss
        with peak_memory(torch.device("cpu")) as peak:
            start = time.perf_counter()
            loaded = PI0ForActionGeneration.from_pretrained(folder, dtype=torch.bfloat16)
            elapsed = time.perf_counter() - start
            # safetensors are memory-mapped: read every weight once so its pages count as resident
            with torch.no_grad():
                checksum = sum(float(p.sum(dtype=torch.float32)) for p in loaded.parameters())
        assert next(loaded.parameters()).dtype == torch.bfloat16 and checksum == checksum
    print(f"\nfrom_pretrained of {args.loading_preset} (bf16, {weight_bytes / 2**30:.2f} GiB of weights): "
          f"{elapsed:.1f} s; loading and reading every weight once: peak RSS increase {(peak[0] - baseline) / 2**30:.2f} GiB = "
          f"{(peak[0] - baseline) / weight_bytes:.2f}x the weight bytes")


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({torch.get_num_threads()} threads)"


# -- command line ---------------------------------------------------------------------------------------------------------


def _csv(kind: Callable[[str], object]) -> Callable[[str], list]:
    return lambda text: [kind(item) for item in text.split(",") if item]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter  # --help shows every default
    parser.add_argument("--presets", type=_csv(str), default=",".join(DEFAULT_PRESETS), help=f"comma list of {preset_names()}")
    parser.add_argument("--dtypes", type=_csv(str), default="float32,bfloat16",
                        help="comma list of float32, bfloat16 (bfloat16 is skipped, with a note, where the device "
                             "has no bfloat16 instructions)")
    parser.add_argument("--cameras", type=_csv(int), default=",".join(map(str, DEFAULT_CAMERAS)), help="comma list of camera counts")
    parser.add_argument("--batches", type=_csv(int), default="1,8", help="comma list of batch sizes")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per row, after warm-up")
    parser.add_argument("--compile", action="store_true", help="also time regionally compiled sampling (on CUDA also "
                        "compiled inside the CUDA graph); on CUDA the hand-captured graph is always timed")
    parser.add_argument("--kernels", type=_csv(str), default="auto", help="comma list of sampling_kernels to time: "
                        "auto (the fused kernels on CUDA in bf16 where they pass their check), torch, triton, "
                        "persistent (each step's decoder layers in one launch, as auto runs eager calls of 1-2 samples)")
    parser.add_argument("--gemms", action="store_true", help="also time the sampling steps' GEMM shapes (CUDA): cuBLAS "
                        "against the fused kernels, microseconds and GB/s of weights read")
    parser.add_argument("--rtc", type=_csv(str), default="", help="also time chunks continued by real-time chunking "
                        "with these methods (comma list of guidance, conditioning)")
    parser.add_argument("--kernel-table", type=int, default=0, metavar="N", help="on CUDA, also print under each row "
                        "the N kinds of GPU activity that took the most GPU time in its profiled call")
    parser.add_argument("--ops", action="store_true", help="also count the ATen ops of one generate_actions per preset")
    parser.add_argument("--train", action="store_true", help="also time a training step")
    parser.add_argument("--side-by-side", action="store_true", help="also compare with transformers' PI0")
    parser.add_argument("--side-by-side-preset", default="pi0_medium", help="preset of --side-by-side")
    parser.add_argument("--loading", action="store_true", help="also measure from_pretrained peak RSS")
    parser.add_argument("--loading-preset", default="pi0", help="preset of --loading")
    parser.add_argument("--tmp-dir", default=None, help="where --loading writes its checkpoint")
    parser.add_argument("--skip-generate", action="store_true", help="leave out the generate_actions table")
    parser.add_argument("--plot", metavar="PNG", help="also draw the generate_actions table as a bar chart (median ms, "
                        "whiskers from the fastest to the slowest run) into this PNG file")
    parser.add_argument("--export", action="store_true", help="only the exported sampling: the eager engine against "
                        "onnxruntime and AOTInductor on the same inputs (default presets pi0_medium,pi05_medium, 3 "
                        "cameras, 2 threads, float32, batch 1; pi0_torch.deploy.benchmark)")
    parser.add_argument("--threads", type=int, default=None, help="--export: CPU threads of every runtime (default 2)")
    parser.add_argument("--fast", action="store_true", help="also time π0-FAST decoding (generate_tokens)")
    parser.add_argument("--fast-presets", type=_csv(str), default="pi0_fast_small,pi0_fast_medium",
                        help=f"comma list of {fast_preset_names()}")
    parser.add_argument("--fast-tokens", type=int, default=60, help="tokens decoded per π0-FAST chunk (no EOS stop)")


def run(args: argparse.Namespace) -> int:
    try:
        device = hardware.usable_device(args.device, "--device")
    except ValueError as error:
        print(f"pi0-torch bench: error: {error}", file=sys.stderr)
        return 2
    if isinstance(sys.stdout, io.TextIOWrapper):  # each row as soon as it is measured, into a pipe too (a run cut short)
        sys.stdout.reconfigure(line_buffering=True)
    unknown = sorted(set(args.dtypes) - {"float32", "bfloat16"})
    if unknown:
        print(f"pi0-torch bench: error: --dtypes: expected float32 and/or bfloat16, got {', '.join(unknown)}", file=sys.stderr)
        return 2
    unknown = sorted(set(args.kernels) - set(PI0ForActionGeneration.SAMPLING_KERNELS))
    if unknown:
        print(f"pi0-torch bench: error: --kernels: expected auto, torch and/or triton, got {', '.join(unknown)}", file=sys.stderr)
        return 2
    unknown = sorted(set(args.rtc) - set(METHODS))
    if unknown:
        print(f"pi0-torch bench: error: --rtc: expected guidance and/or conditioning, got {', '.join(unknown)}", file=sys.stderr)
        return 2
    args.bf16_note = hardware.bf16_unsupported(device) if "bfloat16" in args.dtypes or args.side_by_side else None
    if args.bf16_note:
        print(f"bfloat16 rows skipped: {args.bf16_note}")
        args.dtypes = [dtype for dtype in args.dtypes if dtype != "bfloat16"]
    if args.export:
        from pi0_torch.deploy.benchmark import bench_export

        if args.presets == DEFAULT_PRESETS:
            args.presets = ["pi0_medium", "pi05_medium"]
        if args.cameras == DEFAULT_CAMERAS:
            args.cameras = [3]
        bench_export(args, device)
        return 0
    with torch.inference_mode(False):
        if not args.skip_generate:
            bench_generate(args, device)
        if args.ops:
            bench_op_counts(args)
        if args.gemms:
            bench_gemms(args, device)
        if args.fast:
            bench_fast_decoding(args, device)
        if args.train:
            bench_train_step(args, device)
        if args.side_by_side:
            bench_side_by_side(args, device)
        if args.loading:
            bench_loading(args, device)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(prog="bench_generate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    return run(parser.parse_args())
