"""`generate_actions` as it runs fast: `ActionSampling`, the mixin that gives `PI0ForActionGeneration` its sampling
(as transformers' `GenerationMixin` gives a model `generate`).

The prefix runs once into static k/v buffers (`cache_prefix`), each Euler step runs only the action tokens against
them (`denoise_step`), and nothing waits for the device after the input checks: the sampling replays as one CUDA
graph (`capture_sampling`, `pi0_torch.inference.graphs`) or runs regionally compiled layers (`compile_sampling`).

`PI0ForActionGeneration.sample_actions_reference` computes the same chunk the plain way (openpi's mask, no layout,
no cache tricks): the tests compare the two at every level.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference import fused_pass, vision_pass
from pi0_torch.inference.attention import KERNELS, choose_kernel
from pi0_torch.inference.checks import (auto_avoids_persistent, layers_reason, sampling_ops_reason, setting_reason,
                                        verify_fused_sampling)
from pi0_torch.inference.conditioning import NormParams, StepConditioning, euler_times
from pi0_torch.inference.fused_pass import FusedSteps
from pi0_torch.inference.graphs import SamplingGraphs, describe_plan, input_signature
from pi0_torch.inference.layer_pass import (CALL_MODULES, ModelSamplingWeights, SamplingWeights, activation_quantized,
                                            model_sampling_weights, sampling_layer_pass)
from pi0_torch.inference.layout import (PrefixLayout, StreamPass, camera_inputs, compact_prefix, prefix_stream, rope_tables,
                                        suffix_stream)
from pi0_torch.inference.plan import SamplingDecision, SamplingInputs, SamplingPlan, SamplingRoute
from pi0_torch.inference.program import SamplingProgram
from pi0_torch.inference.rtc import DEFAULT_MAX_GUIDANCE, METHODS, ChunkPrefix, check_rtc_inputs, chunk_prefix, guidance_weight
from pi0_torch.masks import aligned_key_count
from pi0_torch.utils.limits import MAX_BATCH_SIZE
from pi0_torch.utils.validation import check_int
from pi0_torch.utils.validation import check_tensor as _check_tensor

if TYPE_CHECKING:
    from pi0_torch.models.layers import AdaRMSNorm, RMSNorm

logger = logging.getLogger(__name__)


@dataclass
class PrefixCache:
    """The prefix (π0: and the state token) run once for sampling: every layer's post-RoPE k/v in static buffers
    `[B, K, slots, H]` whose last `action_horizon` slots each step's action tokens fill, each sample's first valid
    slot `[B]` (its valid prefix tokens end at `layout.length`), and the RoPE tables of every slot."""

    keys: list[torch.Tensor]  # per layer [B, K, slots or more, H] (fused: views of `buffers[0]`)
    values: list[torch.Tensor]
    first: torch.Tensor
    layout: PrefixLayout
    slots: int  # the prefix's and the suffix's; the buffers may hold more (zeros: `cache_prefix`)
    rope: tuple[torch.Tensor, torch.Tensor]  # `rope_tables` of every slot `[B, slots, H]`, shared by the passes
    buffers: tuple[torch.Tensor, torch.Tensor] | None  # fused: every layer's keys, values [L, B, K, slots or more, H]
    state: torch.Tensor | None = None  # π0, fused: the state token `[B, D1]` the first step runs (its k/v not written yet)


@dataclass
class ActionPass:
    """What every sampling step shares, built once per call: the cache, the action tokens' stream (RoPE, key range,
    slots), the action expert's `SamplingWeights` of each layer, and π0's time-independent parts (the action half of
    `action_time_mlp_in`, transposed, and the action expert's norm params)."""

    cache: PrefixCache
    stream: StreamPass
    expert_weights: list[SamplingWeights]
    action_weight: torch.Tensor | None  # π0: [D1, D1]
    expert_norms: list[tuple[NormParams, NormParams]] | None  # π0: per layer (attention, MLP)
    final_norm: NormParams | None  # π0


class ActionSampling:
    """`generate_actions` and its fast paths for `PI0ForActionGeneration` (which provides the layers, the embeddings,
    `conditioning` and the input checks)."""

    # prefix slots of a captured sampling graph are a multiple of this: prompts of similar length share a graph
    GRAPH_PREFIX_BUCKET = 32
    # Regional compilation shares each compiled layer's code among every model, pass, dtype and batch-size class (1, or
    # more) of the process: π0 and π0.5 in float32 and bf16 are 24 decoder-layer graphs. Dynamo's default limit of 8 per
    # code object would fail a `fullgraph` compile after a few of them, so compiled calls raise it to this
    # (`allow_recompiles`).
    RECOMPILE_LIMIT = 64

    SAMPLING_KERNELS = ("auto", "torch", "triton", "persistent")
    # "auto" runs each step's decoder layers in one persistent launch in eager calls of at most this many samples
    # (`runs_persistent`)
    PERSISTENT_EAGER_BATCH = 2

    # The engine's state: settings and what it learnt, per model (the model's `__init__` sets none of it; the
    # dictionaries are made on first use)
    _attention_kernel: str = "auto"
    _sampling_kernels: str = "auto"
    _graphs: Any = None  # `SamplingGraphs` once `capture_sampling` is called
    _last_route: SamplingRoute | None = None

    @property
    def _fused_refusals(self) -> dict[tuple[Any, ...], str | None]:
        """(plan, input signature) -> why its fused steps were refused (None: they run), as verified on its first call."""
        return self.__dict__.setdefault("_fused_verdicts", {})

    @property
    def last_sampling_route(self) -> SamplingRoute | None:
        """What ran the last `generate_actions` call that returned actions (None before the first): the kernels of its
        Euler steps ("torch", "triton" or "persistent"), whether it replayed a CUDA graph, why its steps ran unfused,
        and what a check refused for its plan (see "Correct first" in docs/gpu.md). An eager call of one sample on an
        H100 in bf16 says `SamplingRoute(steps='persistent', graph=False, why_unfused=None, refusals=())`; one on a CPU
        `SamplingRoute(steps='torch', graph=False, why_unfused="the fused kernels run on CUDA in bf16 / fp16 ...")`."""
        return self._last_route

    @property
    def attention_kernel(self) -> str:
        """The attention kernel of sampling passes (`pi0_torch.inference.attention.KERNELS`): "auto" (FlashAttention's
        varlen kernel on CUDA in bf16 / fp16 where the installed torch has it, else SDPA), "sdpa" or "varlen"."""
        return self._attention_kernel

    @attention_kernel.setter
    def attention_kernel(self, kernel: str) -> None:
        if kernel not in KERNELS:
            raise ValueError(f"attention_kernel must be one of {KERNELS}, got {kernel!r}")
        self._attention_kernel = kernel
        if self._graphs is not None:
            self._graphs.clear()

    @property
    def sampling_kernels(self) -> str:
        """What runs the Euler steps of plain sampling: "auto" (the fused Triton kernels of `pi0_torch.kernels` on CUDA
        in bf16 / fp16 where they passed their check against the torch references on that device: five launches per
        decoder layer, or one per step in eager calls of one or two samples, `runs_persistent`; else "torch"), "torch"
        (the layers' GEMMs and ATen ops; the CPU's path), "triton" (five launches per decoder layer wherever triton
        runs them, `TRITON_INTERPRET=1` included, or a `ValueError` naming why not) or "persistent" (every decoder
        layer of a step in one persistent launch: `pi0_torch.kernels.persistent`; or a `ValueError`). Fused, π0's state
        token runs with the first step's action tokens. Real-time chunking's steps always run "torch"; each fused plan
        is checked against it on its first call."""
        return self._sampling_kernels

    @sampling_kernels.setter
    def sampling_kernels(self, kernels: str) -> None:
        if kernels not in self.SAMPLING_KERNELS:
            raise ValueError(f"sampling_kernels must be one of {self.SAMPLING_KERNELS}, got {kernels!r}")
        self._sampling_kernels = kernels
        self._fused_refusals.clear()
        if self._graphs is not None:
            self._graphs.clear()

    def runs_persistent(self, batch: int, replayed: bool, device: torch.device) -> bool:
        """Whether fused Euler steps of `batch` samples on `device` run each step's decoder layers in one persistent
        launch rather than five launches per layer: always under `sampling_kernels="persistent"`; under "auto" in an
        eager call (`replayed`: a CUDA graph of `capture_sampling` replays it) of at most `PERSISTENT_EAGER_BATCH`
        samples, unless a persistent launch on `device` has abandoned a wait (`checks.auto_avoids_persistent`:
        every later one returns NaN; the chunk it happened in is NaN, the next ones take five launches per layer).

        Measured on an H200 (full-size π0 and π0.5, bf16, 3 cameras; docs/gpu.md): eagerly the host's launches bound a
        chunk, and one launch per step instead of 90 took batch 1 from 45-90 ms to 32-47 ms and batch 2 from 101-105
        ms to 48-56 ms; at batch 4 it was once faster and once slower, at batch 8 slower (133 against 74 ms). Inside a
        CUDA graph launches cost little and the five launches per layer are faster (21.3 against 22.7 ms at batch 1)."""
        if self._sampling_kernels == "persistent":
            return True
        return (self._sampling_kernels == "auto" and not replayed and batch <= self.PERSISTENT_EAGER_BATCH
                and not auto_avoids_persistent(device))

    def fused_steps_reason(self, device: torch.device, dtype: torch.dtype, rtc_method: str | None = None,
                           weights: ModelSamplingWeights | None = None) -> str | None:
        """Why plain sampling's steps on `device` in `dtype` do not run the fused kernels (None: they do); see
        `sampling_kernels`. `weights`: the call's plain-weights check (`layer_pass.model_sampling_weights`; made here
        where not given). Raises `ValueError` with the reason where "triton" or "persistent" was asked for and cannot
        be had."""
        config = self.config

        def check() -> str | None:
            plain = model_sampling_weights(self) if weights is None else weights
            experts = [expert for _, expert in plain.layers]
            return layers_reason(config.num_key_value_heads, config.head_dim, experts, self.sampling_compiled,
                                 plain.plain_action_linears) or sampling_ops_reason(
                device, dtype, config.expert_hidden_size, config.num_attention_heads, config.head_dim,
                config.expert_intermediate_size, config.action_dim, config.vision_hidden_size)

        unsupported = None if rtc_method is None else f"real-time chunking ({rtc_method}) steps run unfused"
        return setting_reason(self._sampling_kernels, "sampling_kernels", device, dtype, check, unsupported)

    def decide(self, inputs: SamplingInputs, plan: SamplingPlan, weights: ModelSamplingWeights,
               replayed: bool) -> tuple[SamplingDecision, torch.Tensor | None]:
        """What a call with these checked inputs runs, decided once: `plan` (its layout, times and real-time chunking)
        with the steps `sampling_kernels` allows here (`fused_steps_reason`, `runs_persistent`; `replayed`: a CUDA
        graph replays the call), each fused plan verified on its first call with these input shapes
        (`verify_fused_sampling`: unfused against fused, eagerly; the verdict is kept in `_fused_refusals`). A refusal
        steps the plan down and is logged once, or raised (`ValueError`) where `sampling_kernels` names the kernels
        ("triton", "persistent"). Returns the decision, and the call's actions where its verification sampled them
        (None else)."""
        device, batch = inputs.noise.device, inputs.noise.shape[0]
        why_unfused = self.fused_steps_reason(device, self.dtype, plan.rtc_method, weights)
        if why_unfused is None:
            plan = replace(plan, steps="persistent" if self.runs_persistent(batch, replayed, device) else "triton")
        decision = SamplingDecision(plan, why_unfused)
        signature, sampled, unfused = input_signature(inputs), None, None
        while decision.plan.fused:
            key = (decision.plan, signature)
            if key not in self._fused_refusals:
                refusal, sampled = verify_fused_sampling(self, inputs, decision.plan, weights, unfused)
                if refusal is not None:
                    described = describe_plan(decision.plan, batch)
                    if self._sampling_kernels != "auto":
                        raise ValueError(f"sampling_kernels={self._sampling_kernels!r} cannot run {described}: {refusal}")
                    instead = "five launches per decoder layer" if decision.plan.persistent else "the torch path"
                    logger.warning("the fused kernels were refused for %s: %s; it runs %s from now on", described,
                                   refusal, instead)
                    unfused = sampled  # (the unfused actions: a fallback's verification compares with them)
                self._fused_refusals[key] = refusal
            if self._fused_refusals[key] is None:
                break
            decision.step_down(self._fused_refusals[key])
        return decision, sampled

    def attention_kernel_for(self, device: torch.device, dtype: torch.dtype, differentiable: bool,
                             setting: str | None = None) -> str:
        """The attention kernel of a pass: SDPA where gradients flow through attention (training, RTC guidance; the
        varlen kernel has no backward with per-sample key counts), else the choice of `setting` (default:
        `attention_kernel`'s)."""
        config = self.config
        setting = self._attention_kernel if setting is None else setting
        return choose_kernel("sdpa" if differentiable else setting, device, dtype, config.num_key_value_heads,
                             config.head_dim)

    @torch.no_grad()
    def generate_actions(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        num_steps: int | None = None,
        generator: torch.Generator | None = None,
        previous_actions: torch.Tensor | None = None,
        inference_delay: int | torch.Tensor = 0,
        execution_horizon: int | torch.Tensor | None = None,
        rtc_method: str = "guidance",
        rtc_max_guidance: float = DEFAULT_MAX_GUIDANCE,
        rtc_schedule: str = "exp",
    ) -> torch.Tensor:
        """Sample an action chunk by Euler integration of the flow from noise (t = 1) to actions (t = 0).

        The prefix runs once (`cache_prefix`); each of the `num_steps` steps (default `config.num_inference_steps`)
        runs only the action tokens against the cached k/v. Everything that depends only on the flow time is computed
        for all steps up front. The Euler state is kept in float32 whatever the weights' dtype. The inputs are read on
        the host once, by their checks; after that nothing waits for the device (see `capture_sampling`).

        Real-time chunking (see `pi0_torch.inference.rtc`): with `previous_actions`, the new chunk continues the one
        the robot is executing. Its index 0 is the step at which this inference starts, `execution_horizon` (`s`)
        steps after the previous one started, and the robot executes `inference_delay` (`d`) more of the previous
        chunk while this one computes. `rtc_method="guidance"` (inference-time RTC) steers every Euler step toward
        the previous chunk's remaining actions with the soft mask `rtc_schedule` and guidance weight clipped at
        `rtc_max_guidance` (beta; 0 gives plain sampling, bit for bit); `"conditioning"` (training-time RTC, for a
        model trained with `config.rtc_max_delay >= d`) gives the first `d` actions as committed (flow time 0) and
        returns them unchanged.

        Args: as [`forward`], plus `noise` `[B, horizon, action_dim]` (drawn with `generator` when not given),
            `previous_actions` float `[B, horizon, action_dim]` (model space, as this method returned it),
            `inference_delay` / `execution_horizon` ints or long `[B]`.

        Returns:
            float32 `[B, horizon, action_dim]` actions in normalized model space (see `PI0Processor` to map them
            back to robot units).
        """
        config = self.config
        times = tuple(euler_times(config.num_inference_steps if num_steps is None else num_steps))
        facts = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state, noise=noise)
        batch = len(facts.text_counts)
        if noise is None:
            noise = torch.randn(batch, config.action_horizon, config.action_dim, generator=generator, device=pixel_values.device)
        prefix = None if previous_actions is None else self._chunk_prefix(
            batch, previous_actions, inference_delay, execution_horizon, rtc_method, rtc_max_guidance, rtc_schedule)
        method = None if prefix is None or (rtc_method == "guidance" and rtc_max_guidance == 0) else rtc_method
        if method == "guidance":
            self._check_differentiable_steps()
        graphs = self._graphs if pixel_values.is_cuda and self.replays_graphs(method) else None
        layout = facts.layout(config.tokens_per_image, self.GRAPH_PREFIX_BUCKET if graphs is not None else 1)
        pixel_values, image_masks = camera_inputs(pixel_values, image_masks, layout)
        inputs = SamplingInputs(
            pixel_values, image_masks, input_ids, attention_mask, state, noise.float(), self._times_on(times, pixel_values.device),
            target=prefix.target if method is not None else None,
            weights=prefix.weights if method == "guidance" else None,
            committed=prefix.committed if method == "conditioning" else None,
        )
        weights = model_sampling_weights(self)  # (the plain-weights check of this call, shared by all that follows)
        planned = SamplingPlan(layout, times, method, float(rtc_max_guidance) if method == "guidance" else 0.0,
                               attention=self._attention_kernel)
        decision, sampled = self.decide(inputs, planned, weights, graphs is not None)
        if graphs is not None:
            sampled, refusal = graphs.run(inputs, decision.plan, weights)
            decision.graph_outcome(refusal)
        elif sampled is None:  # (else the first call's actions, from its verification)
            if self.sampling_compiled:
                allow_recompiles(self.RECOMPILE_LIMIT)
            sampled = self.sample_planned(inputs, decision.plan, weights)
        self._last_route = decision.route()
        return sampled

    def sampling_program(self, batch_size: int = 1, num_steps: int | None = None,
                         text_length: int | None = None) -> SamplingProgram:
        """The exportable core of `generate_actions`: its sampling after the input checks for `batch_size` samples,
        `num_steps` Euler steps (default `config.num_inference_steps`) and prompts of `text_length` token slots
        (default `config.max_token_len`), as a module whose `forward(pixel_values, image_masks, input_ids,
        attention_mask, state, noise)` is a pure function of tensors (`pi0_torch.inference.program`):
        `torch.export.export(program, program.example_inputs(), strict=False)` traces it. Its steps run the torch path
        and its attention SDPA (what exporters take); it returns `generate_actions`' actions for the same noise."""
        config = self.config
        batch_size = check_int("batch_size", batch_size, minimum=1, maximum=MAX_BATCH_SIZE)
        text_length = check_int("text_length", config.max_token_len if text_length is None else text_length, minimum=1,
                                maximum=config.max_token_len)
        num_steps = config.num_inference_steps if num_steps is None else num_steps
        return SamplingProgram(self, batch_size, num_steps, text_length)

    def _check_differentiable_steps(self) -> None:
        """RTC guidance differentiates the action expert's layers (a vector-Jacobian product per step): refuse, by
        name, an activation-quantized linear there (`layer_pass.activation_quantized`), which has no rule for it."""
        for index, layer in enumerate(self.layers):
            if (quantized := activation_quantized(layer.expert, f"layers.{index}.expert")) is not None:
                raise ValueError(f"rtc_method='guidance' differentiates every step (a vector-Jacobian product), which "
                                 f"{quantized}'s activation-quantized linear (torchao int8-dynamic / fp8) has no rule "
                                 "for: use rtc_method='conditioning' with a model trained for it, or weight-only "
                                 "quantization")

    def sample_planned(self, inputs: SamplingInputs, plan: SamplingPlan,
                       weights: ModelSamplingWeights | None = None) -> torch.Tensor:
        """The sampling of `generate_actions` on checked inputs: no host reads, so it can be captured as a CUDA graph.
        `weights`: the call's plain-weights check (`layer_pass.model_sampling_weights`; made here where not given).

        Guided sampling runs outside inference mode (under no_grad; functorch re-enables gradients for its vjp): before
        torch 2.12, `torch.func.vjp` inside `torch.inference_mode()` records nothing and returns zeros (pytorch#177318),
        so a policy or server, which call the model in inference mode, sampled guided chunks without guidance."""
        guided = plan.rtc_method == "guidance"
        if guided and torch.is_inference_mode_enabled():
            with torch.inference_mode(False), torch.no_grad():
                return self.sample_planned(inputs, plan, weights)
        weights = model_sampling_weights(self) if weights is None else weights
        cache = self.cache_prefix(inputs, plan.layout, differentiable_steps=guided, fused=plan.fused, attention=plan.attention,
                                  weights=weights)
        actions = self.action_pass(cache, differentiable=guided, attention=plan.attention, weights=weights)
        committed = inputs.committed
        conditioning = self.step_conditioning(inputs.times, actions.expert_weights if committed is None else None)
        dt = -1.0 / len(plan.times)
        if plan.fused:
            fused = FusedSteps.build(self, actions, conditioning, len(plan.times), plan.persistent)
            x_t = inputs.noise.clone()  # (updated in place)
            for index in range(len(plan.times)):
                fused.step_(x_t, index, dt)
            return x_t
        steps = conditioning.steps()
        if committed is not None:  # committed actions take the conditioning of flow time 0
            clean = self.conditioning(inputs.times.new_zeros(1)).steps()[0]
            steps = [step.per_token(self.config.action_horizon, committed, clean) for step in steps]
        x_t = inputs.noise if committed is None else torch.where(committed[..., None], inputs.target, inputs.noise)
        for time, step in zip(plan.times, steps):
            if plan.rtc_method == "guidance":
                velocity = self.guided_velocity(actions, x_t, time, step, inputs.target, inputs.weights, plan.max_guidance)
            else:
                velocity = self.denoise_step(actions, x_t, step)
            x_t = torch.add(x_t, velocity, alpha=dt)
            if committed is not None:  # the committed actions stay as given
                x_t = torch.where(committed[..., None], inputs.target, x_t)
        return x_t

    def step_conditioning(self, time: torch.Tensor, weights: Sequence[SamplingWeights] | None = None) -> StepConditioning:
        """`conditioning(time)` for the sampling steps, π0.5's adaRMS params of every norm computed together
        (`ada_rms_norm_params`). With the action expert's `SamplingWeights` of each layer (a sampling pass where each
        time conditions every token alike), π0.5's shifts also go through the projections after their norms
        (`NormParams.shift_projected`, see `layer_pass.project_normed`)."""
        if not self.config.pi05:
            return self.conditioning(time)
        norms = [norm for layer in self.layers for norm in (layer.expert.attn_norm, layer.expert.mlp_norm)]
        params = ada_rms_norm_params([*norms, self.expert_final_norm], self.time_conditioning(time))
        layer_norms = tuple(zip(params[:-1:2], params[1:-1:2]))  # per layer (attention, MLP)
        if weights is not None:
            layer_norms = tuple((_project_shift(attn, own.qkv), _project_shift(mlp, own.gate_up))
                                for (attn, mlp), own in zip(layer_norms, weights))
        return StepConditioning(None, layer_norms, params[-1])

    def cache_prefix(
        self, inputs: SamplingInputs, layout: PrefixLayout, differentiable_steps: bool = False, fused: bool = False,
        attention: str | None = None, weights: ModelSamplingWeights | None = None,
    ) -> PrefixCache:
        """Run the prefix once (π0: with the state token) and keep every layer's post-RoPE k/v.

        Exact for sampling because the prefix never attends to the suffix, and π0's state token only to the prefix
        and itself, so neither changes with the noisy actions or the flow time. The buffers have room for the action
        tokens, whose k/v each denoising step writes in place (no per-step copy of the prefix). `differentiable_steps`:
        the steps will attend through SDPA's mask (RTC guidance), so the buffers are laid out for it. `fused`: the
        layers run `fused_pass.prefix_layer`, SigLIP `vision_pass`, and π0's state token is left to the first fused
        step (`PrefixCache.state`, `fused_pass.FusedSteps`). `attention`: the attention kernel setting (default:
        `attention_kernel`). `weights`: the call's plain-weights check (made here where not given).
        """
        config = self.config
        pixel_values = inputs.pixel_values
        vision = vision_pass.tower_pass(self.vision_tower) if fused and pixel_values.shape[1] else None
        if vision is None:  # (the tower's modules run)
            prefix, valid = self.embed_prefix(pixel_values, inputs.image_masks, inputs.input_ids, inputs.attention_mask)
        else:
            image_tokens = self.image_projection(vision(pixel_values.flatten(0, 1))).unflatten(0, pixel_values.shape[:2])
            prefix, valid = self.join_prefix(image_tokens, inputs.image_masks, inputs.input_ids, inputs.attention_mask)
        prefix, first = compact_prefix(prefix, valid, layout)
        batch = first.shape[0]
        slots = layout.length + config.suffix_len
        kernel = self.attention_kernel_for(prefix.device, prefix.dtype, differentiable=False, setting=attention)
        # SDPA's masks (only a padded layout has any) cover a multiple of 8 keys (`pi0_torch.masks.sdpa_with_mask`), and
        # so do the buffers then: the slots past `slots` (and the suffix's, while the prefix runs) are masked out, and
        # zeros (finite) for that
        masked = layout.padded and (kernel == "sdpa" or differentiable_steps)
        shape = (batch, config.num_key_value_heads, aligned_key_count(slots) if masked else slots, config.head_dim)
        make = prefix.new_zeros if masked else prefix.new_empty
        buffers = None
        if fused:  # (one buffer for every layer: one zeroing where masked, one pointer for `kernels.persistent`)
            buffers = tuple(make(len(self.layers), *shape) for _ in range(2))
            keys, values = ([buffer[layer] for layer in range(len(self.layers))] for buffer in buffers)
        else:  # (a tensor per layer: an exported program's cache writes then stay within their layer's tensor)
            keys, values = ([make(shape) for _ in self.layers] for _ in range(2))
        rope = rope_tables(config, first, slots)  # (one table for every stream of the call)
        streams = (
            prefix_stream(config, first, layout, kernel, shape[2], self.dtype, rope),
            None if config.pi05 or fused else suffix_stream(config, first, layout, layout.length, (1,), kernel, shape[2],
                                                            self.dtype, rope),
        )
        x, state = prefix, None if config.pi05 else self.embed_state(inputs.state)
        first_step_state, state = (state, None) if fused else (None, state)  # (fused: the first step runs it)
        scales = [norm.scale for norm in rms_norm_params(  # (fused: the VLM's attention and MLP norms of each layer)
            [norm for layer in self.layers for norm in (layer.vlm.attn_norm, layer.vlm.mlp_norm)] if fused else [])]
        weights = (model_sampling_weights(self) if weights is None else weights).layers
        for index, (layer, layer_keys, layer_values, layer_weights) in enumerate(zip(self.layers, keys, values, weights)):
            last = index == len(self.layers) - 1
            if fused and layer_weights[0].usable:
                x = fused_pass.prefix_layer(x, streams[0], (layer_keys, layer_values), scales[2 * index : 2 * index + 2],
                                            layer_weights[0], config.rms_norm_eps, keys_only=last)
            else:
                x, state = self._layer_pass(layer, x, state, streams, (layer_keys, layer_values), None, layer_weights,
                                            keys_only=last)
        return PrefixCache(keys, values, first, layout, slots, rope, buffers, first_step_state)

    def action_pass(self, cache: PrefixCache, differentiable: bool = False, attention: str | None = None,
                    weights: ModelSamplingWeights | None = None) -> ActionPass:
        """What every sampling step shares (see `ActionPass`), computed once per call; `differentiable` for steps that
        are differentiated (RTC guidance); `attention`: the attention kernel setting (default: `attention_kernel`);
        `weights`: the call's plain-weights check (made here where not given)."""
        config = self.config
        first_slot = cache.slots - config.action_horizon
        kernel = self.attention_kernel_for(cache.first.device, cache.keys[0].dtype, differentiable, attention)
        stream = suffix_stream(config, cache.first, cache.layout, first_slot, (config.action_horizon,), kernel,
                               cache.keys[0].shape[2], self.dtype, cache.rope)
        weights = [CALL_MODULES if differentiable else expert
                   for _, expert in (model_sampling_weights(self) if weights is None else weights).layers]
        if config.pi05:
            return ActionPass(cache, stream, weights, None, None, None)
        norms = rms_norm_params([norm for layer in self.layers for norm in (layer.expert.attn_norm, layer.expert.mlp_norm)]
                                + [self.expert_final_norm])
        expert_norms = list(zip(norms[:-1:2], norms[1:-1:2]))  # per layer (attention, MLP)
        action_weight = self.action_time_mlp_in.weight[:, : config.expert_hidden_size].t()
        return ActionPass(cache, stream, weights, action_weight, expert_norms, norms[-1])

    def denoise_step(
        self, actions: ActionPass, x_t: torch.Tensor, conditioning: StepConditioning, write_cache: bool = True
    ) -> torch.Tensor:
        """Velocity `[B, horizon, action_dim]` (float32) at `x_t` given the cached prefix (in `actions`, from
        `action_pass`) and this step's `conditioning`. `write_cache=False` leaves the cache untouched (a pure function
        of `x_t`, to differentiate through)."""
        tokens = self.embed_actions(x_t, conditioning.condition)
        norms = conditioning.layer_norms if self.config.pi05 else actions.expert_norms
        cache = actions.cache
        for layer, keys, values, layer_norms, weights in zip(self.layers, cache.keys, cache.values, norms, actions.expert_weights):
            _, tokens = self._layer_pass(layer, None, tokens, (None, actions.stream), (keys, values), layer_norms,
                                         (CALL_MODULES, weights), write_cache=write_cache)
        final_norm = conditioning.final_norm if self.config.pi05 else actions.final_norm
        velocity = self.action_out_proj(self.expert_final_norm(tokens, final_norm))
        return velocity.view(x_t.shape[0], -1, velocity.shape[-1]).float()

    def _layer_pass(
        self,
        layer: torch.nn.Module,
        prefix: torch.Tensor | None,
        suffix: torch.Tensor | None,
        streams: tuple[StreamPass | None, StreamPass | None],
        cache: tuple[torch.Tensor, torch.Tensor],
        expert_norms: tuple[NormParams, NormParams] | None,
        weights: tuple[SamplingWeights, SamplingWeights],
        keys_only: bool = False,
        write_cache: bool = True,
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """One layer of a sampling pass: on the layer's `weights` (`layer_pass.sampling_layer_pass`) where every stream
        that runs has them and the pass writes the cache without gradients; else the layer itself (compiled, if
        `compile_sampling` compiled it; eager where the step is differentiated: functorch transforms cannot enter
        compiled code)."""
        differentiated = not write_cache or torch.is_grad_enabled()
        usable = all(own.usable for own, x in zip(weights, (prefix, suffix)) if x is not None)
        if usable and not differentiated and not _compiled(layer):
            return sampling_layer_pass(layer, prefix, suffix, streams, cache, expert_norms, weights, keys_only)
        call = layer._call_impl if differentiated and _compiled(layer) else layer
        return call(prefix, suffix, streams, cache, expert_norms, keys_only=keys_only, write_cache=write_cache)

    def guided_velocity(
        self,
        actions: ActionPass,
        x_t: torch.Tensor,
        time: float,
        conditioning: StepConditioning,
        target: torch.Tensor,
        weights: torch.Tensor,
        max_guidance: float,
    ) -> torch.Tensor:
        """Inference-time real-time chunking: the velocity at `x_t`, corrected so that the predicted clean chunk
        `x0 = x_t - t * v` moves toward the previous chunk's `target` where the soft mask `weights` asks for it.

        `v' = v - w * J^T (W * (Y - x0))` with `J = dx0 / dx_t` (one vector-Jacobian product through the suffix;
        the prefix cache is a constant) and `w = min(beta, ((1 - t)^2 + t^2) / (t (1 - t)))`. The minus sign is
        openpi's convention: v points from data to noise and the Euler steps go down in t.
        """

        def clean_estimate(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            velocity = self.denoise_step(actions, x, conditioning, write_cache=False)
            return x - time * velocity, velocity

        predicted, pullback, velocity = torch.func.vjp(clean_estimate, x_t, has_aux=True)
        (correction,) = pullback(weights[..., None] * (target - predicted))
        return velocity - guidance_weight(time, max_guidance) * correction

    def _times_on(self, times: tuple[float, ...], device: torch.device) -> torch.Tensor:
        """The Euler times as a float32 tensor on `device`, made once (no host-to-device copy per call)."""
        made = self.__dict__.setdefault("_euler_times_on", {})  # (times, device) -> the tensor
        if (times, device) not in made:
            made[times, device] = torch.tensor(times, dtype=torch.float32, device=device)
        return made[times, device]

    def _chunk_prefix(
        self,
        batch: int,
        previous_actions: torch.Tensor,
        inference_delay: int | torch.Tensor,
        execution_horizon: int | torch.Tensor | None,
        rtc_method: str,
        rtc_max_guidance: float,
        rtc_schedule: str,
    ) -> ChunkPrefix:
        """Check the real-time chunking arguments of `generate_actions` (previous chunk and guidance clip within
        `pi0_torch.inference.rtc`'s bounds) and build the new chunk's prefix."""
        config = self.config
        _check_tensor("previous_actions", previous_actions, (batch, config.action_horizon, config.action_dim), floating=True)
        if execution_horizon is None:
            raise ValueError("execution_horizon is required with previous_actions: the steps of the previous chunk executed "
                             "between its inference start and this one's")
        if not isinstance(rtc_method, str) or rtc_method not in METHODS:
            raise ValueError(f"rtc_method must be one of {METHODS}, got {rtc_method!r:.60}")
        check_rtc_inputs("previous_actions", previous_actions, rtc_max_guidance)
        prefix = chunk_prefix(previous_actions.to(self.device), inference_delay, execution_horizon, rtc_schedule)
        longest = int(prefix.committed.sum(dim=1).max())
        if rtc_method == "conditioning" and longest > config.rtc_max_delay:
            raise ValueError(
                f"rtc_method='conditioning' needs a model trained with delays up to the inference delay ({longest}); this "
                f"one was trained with rtc_max_delay={config.rtc_max_delay} (train with --rtc-max-delay, or use 'guidance')"
            )
        return prefix

    # -- fast paths: compiled layers and CUDA graphs ---------------------------------------------------------------------

    @property
    def sampling_compiled(self) -> bool:
        """Whether the repeated layers run compiled (see `compile_sampling`)."""
        return any(_compiled(layer) for layer in self.layers)

    @property
    def sampling_captured(self) -> bool:
        """Whether `generate_actions` on CUDA replays CUDA graphs (see `capture_sampling`)."""
        return self._graphs is not None

    def replays_graphs(self, rtc_method: str | None = None) -> bool:
        """Whether `generate_actions` on CUDA replays CUDA graphs for chunks sampled with this real-time chunking method
        (None: plain sampling); see `capture_sampling`."""
        return self._graphs is not None and self._graphs.covers(rtc_method)

    def compile_sampling(self, disable: bool = False, **compile_kwargs: Any) -> None:
        """Opt in to `torch.compile`, regionally: each repeated layer (a joint decoder layer, a SigLIP encoder layer) is
        compiled once and the compiled code is reused by every layer of its kind; the rest stays eager. Seconds of
        compiling (a handful of graphs: each pass's layer, batch 1 and larger batches) instead of minutes for the whole
        unrolled sampling, and no recompiling for another prompt length or batch size.

        `compile_kwargs` go to `torch.compile`, with `fullgraph=True` and `dynamic=True` unless given.
        `mode="reduce-overhead"` means: compile, and (on CUDA) replay the whole sampling as one CUDA graph
        (`capture_sampling`), which then holds the compiled kernels; graphs switched on before stay on, captured
        again with the compiled layers. The compiled layers also run the training forward (a compiled decoder layer
        skips gradient checkpointing). `compile_sampling(disable=True)` goes back to eager layers (and no graphs).
        Raises Dynamo's recompile limit to `RECOMPILE_LIMIT` when it is lower, here and in every thread that calls the
        model (Dynamo's settings are per thread): the compiled layers of every model in the process share their code.
        """
        repeated = [*self.layers, *self.vision_tower.encoder.layers]
        if disable:
            self._graphs = None
            for layer in repeated:
                layer._compiled_call_impl = None  # (what `nn.Module.compile` sets)
            return
        graph = compile_kwargs.get("mode") == "reduce-overhead"
        if graph:
            compile_kwargs.pop("mode")
        compile_kwargs.setdefault("fullgraph", True)
        compile_kwargs.setdefault("dynamic", True)  # one graph for every prompt length and batch size above 1
        allow_recompiles(self.RECOMPILE_LIMIT)
        for layer in repeated:
            layer.compile(**compile_kwargs)
        if self._graphs is not None:
            self._graphs.clear()  # (they hold the eager layers' kernels)
        elif graph and self.device.type == "cuda":
            self.capture_sampling()

    def capture_sampling(
        self, disable: bool = False, batch_sizes: Sequence[int] | None = None, guidance: bool = False, verify: bool = True
    ) -> None:
        """Opt in to CUDA graphs for `generate_actions` on CUDA: the sampling of each (batch size, step count, prompt
        length, prefix layout, real-time chunking method) is captured once (two warm-up runs, then the capture: its
        first call takes a few eager calls' time) and replayed after that, so the CPU launches one graph instead of
        thousands of kernels. Inputs are copied into the graph's static buffers; each call returns a tensor of its
        own. A model moved to another device or dtype captures again. Works with `compile_sampling` (the graphs then
        replay the compiled kernels).

        Every graph is verified when captured (`verify=True`): its first replay is compared with the last warm-up run,
        an eager run of the same inputs (so verifying costs no extra eager call); a graph whose actions deviate beyond
        `pi0_torch.inference.checks.VERIFY_TOLERANCE` is refused with a warning naming the plan and the deviation, and
        that plan samples eagerly from then on. `verify=False` opts out.

        Plain sampling and real-time chunking's "conditioning" are captured. "guidance" (a vector-Jacobian product per
        step) samples eagerly unless `guidance=True`: its graph replayed wrong actions on the first GPU it met (as if
        the product were zero), so it is only tried on request, captured with autograd's backward on the capturing
        thread, and verified like every graph. With `batch_sizes`, another batch size is refused (`ValueError`)
        rather than captured mid-run. Should CUDA refuse a capture, the call raises `SamplingCaptureError`, except for
        guidance: a warning, and guided chunks sample eagerly from then on. `capture_sampling(disable=True)` goes back
        to eager.
        """
        sizes = None if batch_sizes is None else tuple(check_int("batch_sizes", size, minimum=1) for size in batch_sizes)
        if not disable and (quantized := activation_quantized(self)) is not None:
            raise ValueError(f"capture_sampling: {quantized} quantizes its activations in each call (torchao int8-dynamic "
                             "/ fp8), which synchronizes with the GPU in every matmul and cannot be captured "
                             "(pytorch/ao#4872): sample eagerly, or quantize weight-only (int8, int4, fp8-weight)")
        self._graphs = None if disable else SamplingGraphs(self, sizes, guidance, verify)

    def _apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """`nn.Module._apply` (what `.to()`, `.cuda()`, `.half()` ... run): captured graphs read the old tensors, so
        they are dropped and captured again on the next call."""
        if getattr(self, "_graphs", None) is not None:
            self._graphs.clear()
        self.__dict__.pop("_euler_times_on", None)  # (`_times_on`'s)
        self._fused_refusals.clear()
        return super()._apply(fn, *args, **kwargs)


def rms_norm_params(norms: list[RMSNorm]) -> list[NormParams]:
    """`norm.params()` of each RMSNorm, `1 + weight`, in one op for all of them (`_foreach_add`: one or two kernels on
    CUDA instead of one per norm; the same numbers)."""
    return [NormParams(scale) for scale in torch._foreach_add([norm.weight for norm in norms], 1)] if norms else []


def ada_rms_norm_params(norms: list[AdaRMSNorm], condition: torch.Tensor) -> list[NormParams]:
    """`norm.params(condition)` of each adaRMS norm, their `1 + scale` in one op (`_foreach_add`); the same numbers."""
    chunks = [norm.modulation(condition).chunk(3, dim=-1) for norm in norms]
    scales = torch._foreach_add([scale for scale, _, _ in chunks], 1)
    return [NormParams(scale, shift, gate) for scale, (_, shift, gate) in zip(scales, chunks)]


def _project_shift(params: NormParams, weight: torch.Tensor | None) -> NormParams:
    """adaRMS params with their shift also through the (transposed) projection `weight` that follows the norm."""
    if weight is None:
        return params
    return NormParams(params.scale, params.shift, params.gate, params.shift @ weight)


def _compiled(layer: torch.nn.Module) -> bool:
    return getattr(layer, "_compiled_call_impl", None) is not None


def allow_recompiles(limit: int) -> None:
    """Raise Dynamo's recompile limit per code object to `limit` where it is lower, for the calling thread: torch keeps
    a user's Dynamo settings per thread, so a server's model thread needs its own."""
    config = torch._dynamo.config
    name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"  # (torch < 2.7)
    if getattr(config, name) < limit:
        setattr(config, name, limit)
