"""`pi0-torch doctor`: proof that this install computes the right actions on this machine.

Every sampling path runs on the chosen device with random weights and is compared with its reference, and one table
says path, device, dtype, the deviation (max |ours - reference| / max |reference|), its bound, pass or FAIL, and the
seconds the row took:

- π0 and π0.5: eager float32 and bf16 against `sample_actions_reference` (openpi's sampling written plainly, float32);
  on CUDA also the fused kernels, the CUDA graph and compiled layers inside the graph (against eager); real-time
  chunking's conditioning and guidance, eager and (CUDA) as graphs, against float32 references (guidance: plain
  autograd through the training forward); the training forward against the reference's first step, a bf16-autocast
  training step against float32, and LoRA (a training step on openpi's adapters, then merged) against the adapted model;
- π0-FAST: cached decoding of 1, 2 and 60 tokens against decoding without a cache (the training forward over the
  growing sequence), and on CUDA its compiled decoding (CUDA graphs) against eager.

Bounds: float32 1e-4 and bf16 3e-2, the openpi fixtures' (tests/test_parity.py); graph against eager
`pi0_torch.inference.checks.VERIFY_TOLERANCE`. A CUDA error fails its row; one that loses the CUDA context stops the
run, naming the row. Exits 1 on any FAIL.

    pi0-torch doctor                          # small sizes, on CUDA when present (seconds)
    pi0-torch doctor --full --device cuda     # full size (π0 3.3 B, π0.5 3.4 B, π0-FAST 2.9 B parameters)

Needs the core install only.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import gc
import importlib.util
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import psutil
import torch

from pi0_torch.inference.checks import VERIFY_TOLERANCE, relative_deviation
from pi0_torch.inference.layer_pass import decoder_sampling_weights
from pi0_torch.kernels import ops
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.inference.conditioning import euler_times
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.inference.rtc import chunk_prefix, guidance_weight
from pi0_torch.utils.hardware import usable_device
from pi0_torch.utils.triton_guard import set_aside_broken_triton

FLOAT32_BOUND, BF16_BOUND = 1e-4, 3e-2  # tests/test_parity.py: FLOAT32_TOLERANCE, BF16_TOLERANCE
STEPS, DELAY, EXECUTED = 10, 3, 5  # Euler steps; real-time chunking's inference delay and steps executed
FAST_PROMPT = 16  # π0-FAST's prompt tokens (the decoded ones follow: the training forward takes them all)
# What a family or a row takes, in multiples of the model's float32 weights (rows: beyond the model, which they share),
# with room to spare: a row that would not fit is skipped, naming what it needs and what is available (`--full` on a
# 24 GB CPU machine: the training step's gradients and their two float32 copies alone are three models)
MEMORY_NEEDS = {"model": 1.2, "sampling": 0.15, "guidance": 0.5, "training step": 3.3, "lora": 1.4}


@dataclasses.dataclass
class Row:
    path: str
    device: str
    dtype: str
    deviation: float | None = None
    bound: float | None = None
    result: str = "not run"
    seconds: float = 0.0
    note: str = ""

    def line(self) -> str:
        deviation = "-" if self.deviation is None else f"{self.deviation:.2e}"
        bound = "-" if self.bound is None else f"{self.bound:.0e}"
        note = f"  {self.note}" if self.note else ""
        return (f"{self.path:44s} {self.device:6s} {self.dtype:9s} {deviation:>10s} {bound:>7s} {self.result:>7s} "
                f"{self.seconds:7.1f}{note}")


class ContextLost(RuntimeError):
    """A CUDA error left the process's CUDA context unusable."""


class Doctor:
    def __init__(self, device: torch.device, full: bool) -> None:
        self.device, self.full = device, full
        self.rows: list[Row] = []
        self.cuda = device.type == "cuda"
        self.model_bytes = 0  # the float32 weights of the model the rows run now

    def available_bytes(self) -> int:
        """Memory this process may still take: the GPU's free memory plus what torch's allocator holds unused, or the
        machine's available RAM, and no more than an address-space limit leaves (`ulimit -v`: a row past it failed
        with the allocator's traceback)."""
        if self.device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(self.device)
            return free + torch.cuda.memory_reserved(self.device) - torch.cuda.memory_allocated(self.device)
        return min(psutil.virtual_memory().available, _address_space_left())

    def memory_note(self, needed: float) -> str | None:
        """Why `needed` more bytes do not fit (None: they do)."""
        if needed <= 0:
            return None
        available, limited = self.available_bytes(), None if self.cuda else _address_space_left()
        if needed <= available:
            return None
        if limited is not None and limited <= available:
            return (f"needs about {_size(needed)}, this process's address-space limit (ulimit -v) leaves "
                    f"{_size(limited)}")
        return f"needs about {_size(needed)}, this machine has {_size(available)} available"

    def skip(self, path: str, dtype: torch.dtype | str, note: str) -> None:
        row = Row(path, self.device.type, str(dtype).removeprefix("torch."), result="skip", note=note)
        self.rows.append(row)
        print(row.line(), flush=True)

    def row(self, path: str, dtype: torch.dtype | str, check: Callable[[], tuple[float | None, float | None, str]],
            needs_cuda: bool = False, needs: float = MEMORY_NEEDS["sampling"]) -> None:
        """Run one check: `check()` returns (deviation, bound, note); an exception fails the row. `needs`: the memory
        it takes beyond the model, in multiples of the model's float32 weights (`MEMORY_NEEDS`): a row that would not
        fit is skipped, saying so."""
        if needs_cuda and not self.cuda:
            self.skip(path, dtype, "needs CUDA")
            return
        if (note := self.memory_note(needs * self.model_bytes)) is not None:
            self.skip(path, dtype, note)
            return
        row = Row(path, self.device.type, str(dtype).removeprefix("torch."))
        self.rows.append(row)
        start = time.perf_counter()
        try:
            row.deviation, row.bound, row.note = check()
            row.result = "pass" if row.deviation is None or row.deviation <= row.bound else "FAIL"
            if row.note.startswith("skip"):
                row.result, row.note = "skip", row.note.removeprefix("skip: ")
        except Exception as error:  # a row fails; the doctor goes on (unless CUDA itself is gone)
            row.result, row.note = "FAIL", f"{type(error).__name__}: {str(error).splitlines()[0][:160] if str(error) else ''}"
            if self.cuda and not _cuda_usable(self.device):
                row.seconds = time.perf_counter() - start
                print(row.line(), flush=True)
                raise ContextLost(f"the CUDA context was lost in the row {path!r} ({row.note}); the rows after it did not run")
        row.seconds = time.perf_counter() - start
        print(row.line(), flush=True)

    def fits(self, path: str, model_class: Any, config: Any) -> bool:
        """Whether the float32 model of `config` fits (with room for its rows' sampling); else one skip row for the
        family. Sets `model_bytes` for the rows' own needs."""
        with torch.device("meta"):
            self.model_bytes = 4 * sum(parameter.numel() for parameter in model_class(config).parameters())
        note = self.memory_note(MEMORY_NEEDS["model"] * self.model_bytes)
        if note is not None:
            self.skip(path, torch.float32, f"the model {note}")
        return note is None

    # -- π0 / π0.5 --------------------------------------------------------------------------------------------------

    def pi0_rows(self, preset: str) -> None:
        device = self.device
        config = PI0Config.from_preset(preset, rtc_max_delay=DELAY)
        name = "π0.5" if config.pi05 else "π0"
        if not self.fits(f"{name} (every row)", PI0ForActionGeneration, config):
            return
        torch.manual_seed(0)
        with device:
            model = PI0ForActionGeneration(config).eval()
        inputs, noise = pi0_inputs(config, device)
        previous = torch.randn(noise.shape, generator=torch.Generator().manual_seed(5)).to(device)
        start = time.perf_counter()
        if (note := self.memory_note(MEMORY_NEEDS["guidance"] * self.model_bytes)) is not None:  # (the references' own)
            self.skip(f"{name} (every row)", torch.float32, f"its float32 references {note}")
            return
        reference = model.sample_actions_reference(**inputs, noise=noise, num_steps=STEPS)

        def against(got: torch.Tensor, want: torch.Tensor, bound: float, note: str = "") -> tuple[float, float, str]:
            return relative_deviation(got, want), bound, note

        def sample(model: PI0ForActionGeneration, **options: Any) -> torch.Tensor:
            with torch.inference_mode():  # (as a policy or server calls it)
                return model.generate_actions(**inputs, noise=noise, num_steps=STEPS, **options).clone()

        model.sampling_kernels = "torch"
        rtc = dict(previous_actions=previous, inference_delay=DELAY, execution_horizon=EXECUTED)
        guided32 = autograd_guidance(model, inputs, noise, previous)
        conditioned32 = sample(model, **rtc, rtc_method="conditioning")
        print(f"({name}: the float32 references took {time.perf_counter() - start:.1f} s)", flush=True)
        self.row(f"{name} eager", torch.float32, lambda: against(sample(model), reference, FLOAT32_BOUND))
        self.row(f"{name} RTC guidance, eager", torch.float32,
                 lambda: against(sample(model, **rtc, rtc_method="guidance"), guided32, FLOAT32_BOUND),
                 needs=MEMORY_NEEDS["guidance"])
        self.row(f"{name} training forward vs reference step", torch.float32,
                 lambda: training_forward_check(model, inputs, noise))
        self.row(f"{name} training step, bf16 autocast", torch.bfloat16, lambda: training_step_check(model, inputs, noise),
                 needs=MEMORY_NEEDS["training step"])
        self.row(f"{name} LoRA (adapters, merged)", torch.float32, lambda: lora_check(model, inputs, noise),
                 needs=MEMORY_NEEDS["lora"])

        model = model.to(torch.bfloat16)
        model.sampling_kernels = "torch"
        eager16: list[torch.Tensor] = []  # (the compiled row's reference)
        self.row(f"{name} eager", torch.bfloat16, lambda: against(eager16.append(sample(model)) or eager16[0], reference, BF16_BOUND))
        self.row(f"{name} RTC guidance, eager", torch.bfloat16,
                 lambda: against(sample(model, **rtc, rtc_method="guidance"), guided32, BF16_BOUND))

        def conditioning() -> tuple[float, float, str]:
            conditioned = sample(model, **rtc, rtc_method="conditioning")
            if bool((conditioned[:, :DELAY] - previous[:, EXECUTED : EXECUTED + DELAY]).abs().max() > 0):
                return float("inf"), BF16_BOUND, "the committed actions changed"
            return against(conditioned, conditioned32, BF16_BOUND)

        self.row(f"{name} RTC conditioning, eager", torch.bfloat16, conditioning)

        def fused() -> tuple[float, float, str]:
            if (reason := ops.triton_reason(device)) is not None:
                return None, None, f"skip: {reason}"
            from pi0_torch.kernels.launch import launch_mode

            model.sampling_kernels = "triton"
            try:
                return against(sample(model), reference, BF16_BOUND, launch_mode())
            finally:
                model.sampling_kernels = "torch"

        self.row(f"{name} fused kernels", torch.bfloat16, fused, needs_cuda=True)

        def auto_eager() -> tuple[float, float, str]:  # (what a notebook's eager call runs on CUDA)
            model.sampling_kernels = "auto"
            try:
                got = sample(model)
                route = model.last_sampling_route
            finally:
                model.sampling_kernels = "torch"
            if route.steps == "torch":
                note = f"torch path: {route.why_unfused}"
            else:
                note = "persistent layers" if route.steps == "persistent" else "five launches per layer"
                note += f" ({'; '.join(route.refusals)})" if route.refusals else ""
            return against(got, reference, BF16_BOUND, note)

        self.row(f"{name} auto kernels, eager", torch.bfloat16, auto_eager, needs_cuda=True)

        def graph(method: str | None, want: torch.Tensor, guidance: bool = False,
                  kernels: str = "auto") -> Callable[[], tuple[float, float, str]]:
            def check() -> tuple[float, float, str]:
                model.sampling_kernels = kernels
                model.capture_sampling(guidance=guidance)
                try:  # ("persistent" raises where its first call's verification refuses it)
                    options = {} if method is None else dict(rtc, rtc_method=method)
                    replays = [sample(model, **options) for _ in range(2)]
                    route = model.last_sampling_route
                finally:
                    model.capture_sampling(disable=True)
                    model.sampling_kernels = "torch"
                deviation = max(relative_deviation(replay, want) for replay in replays)
                refusals = "; ".join(route.refusals)
                if not route.graph and method == "guidance":  # (not yet proven on a GPU: refused means eager, correct)
                    return deviation, BF16_BOUND, f"no graph, guided chunks sample eagerly ({refusals or 'CUDA refused the capture'})"
                if not route.graph:
                    return float("inf"), BF16_BOUND, f"graph refused at capture ({refusals})"
                return deviation, BF16_BOUND, f"refused at first call, graph of {route.steps} steps ({refusals})" if refusals else ""
            return check

        self.row(f"{name} CUDA graph", torch.bfloat16, graph(None, reference), needs_cuda=True)
        # (each step's decoder layers in one launch, verified eagerly on its first call; "auto" keeps it out of graphs)
        self.row(f"{name} persistent layers, CUDA graph", torch.bfloat16, graph(None, reference, kernels="persistent"),
                 needs_cuda=True)
        self.row(f"{name} RTC conditioning, CUDA graph", torch.bfloat16, graph("conditioning", conditioned32), needs_cuda=True)
        self.row(f"{name} RTC guidance, CUDA graph", torch.bfloat16, graph("guidance", guided32, guidance=True), needs_cuda=True)

        def compiled_graph() -> tuple[float, float, str]:
            model.compile_sampling(mode="reduce-overhead")
            try:
                replays = [sample(model) for _ in range(2)]
                refused = list(model._graphs.refused.values()) if model._graphs is not None else []
            finally:
                model.compile_sampling(disable=True)
            if refused:
                return float("inf"), VERIFY_TOLERANCE[torch.bfloat16], f"graph refused at capture: {refused[0]}"
            return max(relative_deviation(replay, eager16[0]) for replay in replays), VERIFY_TOLERANCE[torch.bfloat16], "vs eager bf16"

        self.row(f"{name} compiled layers + CUDA graph", torch.bfloat16, compiled_graph, needs_cuda=True)

    # -- π0-FAST ------------------------------------------------------------------------------------------------------

    def fast_rows(self, preset: str) -> None:
        device = self.device
        # decoded tokens at the positions training gives them (later openpi; the fixtures' openpi adds 1), no EOS stop:
        # the cached decoding then equals the training forward over the growing sequence
        config = PI0FastConfig.from_preset(preset, eos_token_id=None, decoding_position_offset=0, max_token_len=FAST_PROMPT + 61)
        if not self.fits("π0-FAST (every row)", PI0FastForActionGeneration, config):
            return
        torch.manual_seed(0)
        with device:
            model = PI0FastForActionGeneration(config).eval()
        inputs = fast_inputs(config, device)
        for dtype, counts in ((torch.float32, (1, 2, 60)), (torch.bfloat16, (60,))):
            model = model.to(dtype)
            bound = FLOAT32_BOUND if dtype == torch.float32 else BF16_BOUND
            for count in counts:
                self.row(f"π0-FAST decoding, {count} new token{'s' if count > 1 else ''}", dtype,
                         lambda count=count, bound=bound: fast_decoding_check(model, inputs, count, bound))

        def captured() -> tuple[float | None, float | None, str]:
            eager = model.generate_tokens(**inputs, max_new_tokens=8)
            model.capture_decoding()
            graphs = model._decoding_graphs
            try:
                calls = [model.generate_tokens(**inputs, max_new_tokens=8) for _ in range(2)]  # (captured, replayed)
            finally:
                model.capture_decoding(disable=True)
            if graphs.refused:
                return float("inf"), 0.0, f"hand-captured decoding refused: {next(iter(graphs.refused.values()))}"
            return float(max(int((tokens != eager).sum()) for tokens in calls)), 0.0, "tokens differing from eager"

        self.row("π0-FAST decoding, hand-captured CUDA graphs", torch.bfloat16, captured, needs_cuda=True)

        def compiled() -> tuple[float | None, float | None, str]:
            reason = model.decoding_graphs_reason()
            if reason is not None:
                return None, None, f"skip: {reason}"
            eager = model.generate_tokens(**inputs, max_new_tokens=8)
            model.compile_decoding(mode="reduce-overhead")
            try:
                calls = [model.generate_tokens(**inputs, max_new_tokens=8) for _ in range(model.VERIFY_CALLS + 1)]
                refused = not model.decoding_compiled
            finally:
                model.compile_decoding(disable=True)
            if refused:
                return float("inf"), 0.0, "compiled decoding refused by its verification (see the log)"
            return float(max(int((tokens != eager).sum()) for tokens in calls)), 0.0, "tokens differing from eager"

        self.row("π0-FAST compiled decoding (CUDA graphs)", torch.bfloat16, compiled, needs_cuda=True)


def _size(count: float) -> str:
    return f"{count / 1e9:.1f} GB" if count >= 1e9 else f"{count / 1e6:.0f} MB"


def pi0_inputs(config: PI0Config, device: torch.device) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Two samples that exercise the layout: prompts of 48 and 19 valid tokens, the second without its last camera."""
    generator = torch.Generator().manual_seed(0)
    size, text = config.image_size, min(48, config.max_token_len)
    masks = torch.ones(2, config.num_cameras, dtype=torch.bool)
    masks[1, -1] = False
    inputs = dict(
        pixel_values=torch.rand(2, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        image_masks=masks,
        input_ids=torch.randint(1, config.vocab_size, (2, text), generator=generator),
        attention_mask=torch.arange(text)[None] < torch.tensor([[text], [min(19, text)]]),
        state=torch.randn(2, config.action_dim, generator=generator),
    )
    noise = torch.randn(2, config.action_horizon, config.action_dim, generator=generator)
    return {key: value.to(device) for key, value in inputs.items()}, noise.to(device)


def fast_inputs(config: PI0FastConfig, device: torch.device) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    size, text = config.image_size, FAST_PROMPT
    inputs = dict(
        pixel_values=torch.rand(1, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        image_masks=torch.ones(1, config.num_cameras, dtype=torch.bool),
        input_ids=torch.randint(2, config.vocab_size, (1, text), generator=generator),
        attention_mask=torch.ones(1, text, dtype=torch.bool),
        token_ar_mask=torch.zeros(1, text, dtype=torch.bool),
    )
    return {key: value.to(device) for key, value in inputs.items()}


def autograd_guidance(model: PI0ForActionGeneration, inputs: dict[str, torch.Tensor], noise: torch.Tensor,
                      previous: torch.Tensor) -> torch.Tensor:
    """Real-time chunking's guided sampling with plain autograd through the training forward (no cache, no torch.func,
    no inference mode): every step `v + w * grad_x 0.5 * sum(W * (Y - x0(x))^2)` with `x0 = x - t v(x)`."""
    prefix = chunk_prefix(previous, DELAY, EXECUTED)
    x_t = noise.float()
    for flow_time in euler_times(STEPS):
        with torch.enable_grad():
            x = x_t.clone().requires_grad_(True)
            velocity = model(**inputs, noise=x, time=torch.full((x.shape[0],), flow_time, device=x.device)).velocity
            estimate = x - flow_time * velocity
            objective = 0.5 * (prefix.weights[..., None] * (prefix.target - estimate) ** 2).sum()
            (gradient,) = torch.autograd.grad(objective, x)
        x_t = x_t - (velocity.detach() + guidance_weight(flow_time, 5.0) * gradient) / STEPS
    return x_t


def training_forward_check(model: PI0ForActionGeneration, inputs: dict[str, torch.Tensor], noise: torch.Tensor) -> tuple[float, float, str]:
    """The training forward (prefix and suffix in one joint pass) at t = 1 against the reference sampler's first step:
    one Euler step of size 1 from `noise` is `noise - v(noise, 1)`."""
    with torch.no_grad():
        velocity = model(**inputs, noise=noise, time=torch.ones(noise.shape[0], device=noise.device)).velocity
        stepped = model.sample_actions_reference(**inputs, noise=noise, num_steps=1)
    return relative_deviation(noise - velocity, stepped), FLOAT32_BOUND, ""


def training_step_check(model: PI0ForActionGeneration, inputs: dict[str, torch.Tensor], noise: torch.Tensor) -> tuple[float, float, str]:
    """A bf16-autocast training step's loss and gradients against float32's (same batch, noise and time)."""
    actions = torch.randn(noise.shape, generator=torch.Generator().manual_seed(3)).to(noise.device)
    time = torch.full((noise.shape[0],), 0.4, device=noise.device)
    results = []
    for autocast in (False, True):
        model.zero_grad(set_to_none=True)
        with torch.autocast(noise.device.type, dtype=torch.bfloat16, enabled=autocast):
            loss = model(**inputs, actions=actions, noise=noise, time=time).loss
        loss.backward()
        gradient = torch.cat([p.grad.flatten().float() for p in model.parameters() if p.grad is not None])
        if not bool(torch.isfinite(gradient).all()):
            return float("inf"), BF16_BOUND, f"non-finite gradients (autocast {autocast})"
        results.append((loss.detach().float(), gradient))
    model.zero_grad(set_to_none=True)
    (loss32, grad32), (loss16, grad16) = results
    deviation = max(relative_deviation(loss16, loss32), float((grad16 - grad32).norm() / grad32.norm()))
    return deviation, BF16_BOUND, f"loss {float(loss32):.4f}; gradient's relative L2 error included"


def lora_check(model: PI0ForActionGeneration, inputs: dict[str, torch.Tensor], noise: torch.Tensor) -> tuple[float, float, str]:
    """LoRA: after a training step on the adapters, the merged model samples what the adapted one does."""
    from pi0_torch.training.lora import apply_lora, merge_lora

    adapted = apply_lora(copy.deepcopy(model), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        plain = model.sample_actions_reference(**inputs, noise=noise, num_steps=2)
    optimizer = torch.optim.SGD([p for p in adapted.parameters() if p.requires_grad], lr=1e-2)
    actions = torch.randn(noise.shape, generator=torch.Generator().manual_seed(4)).to(noise.device)
    time = torch.full((noise.shape[0],), 0.5, device=noise.device)
    adapted(**inputs, actions=actions, noise=noise, time=time).loss.backward()
    optimizer.step()
    with torch.no_grad():
        trained = adapted.sample_actions_reference(**inputs, noise=noise, num_steps=2)
        merged = merge_lora(adapted).sample_actions_reference(**inputs, noise=noise, num_steps=2)
    return relative_deviation(merged, trained), FLOAT32_BOUND, \
        f"the adapters and the step moved the actions by {relative_deviation(trained, plain):.1e}"


def fast_decoding_check(model: PI0FastForActionGeneration, inputs: dict[str, torch.Tensor], count: int,
                        bound: float) -> tuple[float, float, str]:
    """Cached decoding (`prepare_decoding` + `decode_step`, attending as `generate_tokens` does on this device) along
    the greedy tokens of decoding without a cache (the training forward over the prompt and the tokens so far, plus a
    placeholder token whose position's logits predict the next one): the largest deviation of their logits, step by
    step."""
    prompt = inputs["input_ids"].shape[1]
    ids, valid, ar_mask = inputs["input_ids"], inputs["attention_mask"], inputs["token_ar_mask"]
    reference = []
    with torch.no_grad():
        for _ in range(count):
            placeholder = torch.zeros_like(ids[:, :1])
            grown = dict(inputs, input_ids=torch.cat([ids, placeholder], dim=1),
                         attention_mask=torch.cat([valid, placeholder.bool().logical_not()], dim=1),
                         token_ar_mask=torch.cat([ar_mask, placeholder.bool().logical_not()], dim=1))
            reference.append(model(**grown).logits[:, -1].float())  # (the placeholder's own block: nothing before sees it)
            token = reference[-1].argmax(dim=-1, keepdim=True)
            ids, valid, ar_mask = grown["input_ids"].clone(), grown["attention_mask"], grown["token_ar_mask"]
            ids[:, -1:] = token
        images = inputs["pixel_values"]
        slots = model.decoding_slots(images.shape[1], inputs["input_ids"].shape[1], count)
        fused = model.decoding_kernels_reason(images.device, model.dtype, images.shape[0], slots) is None
        arguments = (inputs["pixel_values"], inputs["image_masks"], inputs["input_ids"], inputs["attention_mask"],
                     inputs["token_ar_mask"], count, decoder_sampling_weights(model.layers) if fused else None)
        _, cached = model.decode(model.prepare_decoding, model.decode_step, arguments, 0.0, None, forced=ids[:, prompt:])
    deviation = max(relative_deviation(got, want) for got, want in zip(cached, reference))
    return deviation, bound, "decoded tokens: fused kernels" if fused else "decoded tokens: modules"


def _cuda_usable(device: torch.device) -> bool:
    try:
        torch.cuda.synchronize(device)
        torch.zeros(1, device=device).add_(1).item()
        return True
    except Exception:  # (any error here means the context is gone)
        return False


def _free(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()


@contextlib.contextmanager
def _quiet_warnings() -> Iterator[None]:
    """The rows' expected warnings (a refused guidance graph, refused fused steps) are in the table; keep the output
    to the table."""
    import logging

    names = ("pi0_torch.inference.graphs", "pi0_torch.inference.fused_pass", "pi0_torch.inference.sampling")
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # (transformers' deprecations)
            yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                        help="torch device (default: cuda when present)")
    parser.add_argument("--full", action="store_true", help="full-size models (random weights) instead of the small "
                        "presets; each row that would not fit this machine's memory is skipped, saying what it needs "
                        "(π0 in float32: about 16 GB for its sampling rows, 56 GB for all of them)")


def _address_space_left() -> float:
    """Bytes of address space this process may still map under its limit (`ulimit -v`, RLIMIT_AS; inf: none)."""
    try:
        import resource
    except ImportError:  # (not on Windows)
        return float("inf")
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return float("inf")
    return max(soft - psutil.Process().memory_info().vms, 0)


def _triton_row() -> tuple[float | None, float | None, str]:
    """FAIL where an installed triton does not import (it was set aside: `pi0_torch.utils.triton_guard`), skip where
    none is installed, pass with its version."""
    if (broken := set_aside_broken_triton()) is not None:
        raise ImportError(broken)
    if importlib.util.find_spec("triton") is None:
        return None, None, "skip: not installed (torch's CUDA wheels bring it; the CPU runs without it)"
    import triton

    return None, None, f"triton {triton.__version__} imports"


def run(args: argparse.Namespace) -> int:
    try:
        device = usable_device(args.device, "--device")
    except ValueError as error:
        print(f"pi0-torch doctor: error: {error}", file=sys.stderr)
        return 2
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU ({torch.get_num_threads()} threads)"
    print(f"pi0-torch doctor on {where}, torch {torch.__version__}, {'full size' if args.full else 'small presets'}, random "
          f"weights; deviation = max |ours - reference| / max |reference|")
    print(f"{'path':44s} {'device':6s} {'dtype':9s} {'deviation':>10s} {'bound':>7s} {'result':>7s} {'seconds':>7s}")
    doctor = Doctor(device, args.full)
    doctor.row("triton (the fused kernels' compiler)", "-", _triton_row)
    sizes = ("pi0", "pi05", "pi0_fast") if args.full else ("pi0_small", "pi05_small", "pi0_fast_small")
    try:
        with _quiet_warnings():
            for rows, preset in ((doctor.pi0_rows, sizes[0]), (doctor.pi0_rows, sizes[1]), (doctor.fast_rows, sizes[2])):
                rows(preset)
                _free(device)  # (each model's memory back before the next)
    except ContextLost as error:
        print(f"STOPPED: {error}")
        return 1
    failed = [row for row in doctor.rows if row.result == "FAIL"]
    passed = sum(row.result == "pass" for row in doctor.rows)
    skipped = sum(row.result == "skip" for row in doctor.rows)
    print(f"\n{passed} passed, {len(failed)} failed, {skipped} skipped" + (": " + ", ".join(row.path for row in failed) if failed else ""))
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(prog="pi0-torch doctor", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    return run(parser.parse_args())


if __name__ == "__main__":
    sys.exit(main())
