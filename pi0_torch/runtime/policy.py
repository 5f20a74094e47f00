"""`PI0Policy`: one observation in, one action chunk in robot units out (the π0 / π0.5 model and its processor
together; what every family member's policy shares is `pi0_torch.runtime.policy_base`).

This is the object a policy server wraps, and the shortest way to run a saved model from Python. Usually
`PI0Policy.from_pretrained(folder)` on a converted checkpoint; here a tiny random model:

```python
>>> import numpy as np
>>> from pi0_torch import PI0Config, PI0ForActionGeneration
>>> from pi0_torch.processing.normalization import NormStats
>>> from pi0_torch.processing.tokenization import build_test_tokenizer
>>> config = PI0Config.from_preset("pi0_small")
>>> stats = {key: NormStats(mean=np.zeros(dim), std=np.ones(dim)) for key, dim in (("state", 8), ("actions", 7))}
>>> processor = PI0Processor.from_config(config, tokenizer=build_test_tokenizer(), norm_stats=stats)
>>> policy = PI0Policy(PI0ForActionGeneration(config), processor, num_steps=2, seed=0)
>>> out = policy.infer({
...     "images": {"base_0_rgb": np.zeros((480, 640, 3), np.uint8)},
...     "state": np.zeros(8),
...     "prompt": "pick up the fork",
... })
>>> out["actions"].shape, out["actions"].dtype  # [action_horizon, robot action dims]
((50, 7), dtype('float32'))

```
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pi0_torch.inference.checks import PERSISTENT_ABANDONED, persistent_abandoned
from pi0_torch.inference.graphs import SamplingCaptureError
from pi0_torch.models.configuration_base import PI0BaseConfig
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.inference.rtc import DEFAULT_MAX_GUIDANCE, MAX_GUIDANCE, METHODS, SCHEDULES, check_rtc_inputs
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.runtime.observation_formats import ObservationError, step_count
from pi0_torch.runtime.policy_base import BasePolicy, ChunkContinuation, PreparedObservation
from pi0_torch.runtime.policy_settings import MAX_NOISE_SCALE
from pi0_torch.runtime.policy_fast import PI0FastPolicy
from pi0_torch.shipped_policy import policy_location
from pi0_torch.utils.limits import SIZE_LIMITS
from pi0_torch.utils.validation import check_float

logger = logging.getLogger(__name__)



class PI0Policy(BasePolicy):
    """[`PI0ForActionGeneration`] + [`PI0Processor`] behind openpi's policy interface (`infer(obs) -> dict`): a
    [`BasePolicy`] whose chunks are sampled from noise by flow matching, and which continues the chunk a robot is
    executing (real-time chunking). (`from_pretrained` of a π0-FAST folder gives its sibling
    [`pi0_torch.runtime.policy_fast.PI0FastPolicy`].)

    Observations use the default layout `{"images": {camera_name: frame}, "state": [...], "prompt": str}` (see
    [`pi0_torch.runtime.observation_formats`] for other layouts). `infer` returns `{"actions": float32 [action_horizon,
    robot action dims], "policy_timing": {"infer_ms": model time, "batch_size": observations run together}}`,
    actions unnormalized by the processor.

    Optional observation fields (all plain values, so they travel over the websocket too):

    - real-time chunking: `previous_actions` (the chunk being executed, robot units `[action_horizon, robot action
      dims]`, as this policy returned it), `execution_horizon` (its steps executed before this observation),
      `inference_delay` (its steps the robot executes while this chunk computes) and `rtc_method` ("guidance", or
      "conditioning" for a model trained with `--rtc-max-delay`; default: the policy's `rtc_method`);
    - `noise_seed` (int): this chunk's sampling noise comes from its own generator, so results do not depend on which
      requests were batched together (reproducible evaluation, locally and through the server).

    Args:
        model: the model, already on its device and dtype.
        processor: its processor.
        num_steps: Euler steps per chunk (default: `model.config.num_inference_steps`).
        seed: seeds the sampling noise, so a fresh policy gives the same chunks for the same requests.
        rtc_method: how chunks continue a `previous_actions` (default: "conditioning" for a model trained with delays,
            `config.rtc_max_delay > 0`, else "guidance").
        rtc_max_guidance: the guidance weight's clip (beta) for "guidance".
        rtc_schedule: the soft mask of "guidance" over the overlap with the previous chunk (`SCHEDULES`): "exp" (the
            paper's exponential decay), "linear", "ones" (full weight on the whole overlap) or "hard" (the delayed
            steps only). In the demo's closed-loop benchmark at d = 4, "ones" had 0.45-0.65x the jerk at chunk
            boundaries of "exp" (docs/closed_loop.md).
        noise_scale: the standard deviation of the noise each chunk's flow starts from (1: the training
            distribution, openpi's sampler). Below 1 the flow starts nearer the middle of the noise and returns
            actions nearer the most likely chunk; a small policy that grasps imprecisely gains from it (the demo
            policy samples at `pi0_torch.demo.DEMO_NOISE_SCALE` = 0.1, docs/closed_loop.md, measured). 0 gives one
            deterministic chunk per observation.
        compile: compile the model's repeated layers with `torch.compile` ([`PI0ForActionGeneration.compile_sampling`];
            on CUDA the sampling also replays as a CUDA graph). The first chunk compiles (seconds): call [`warmup`].
        cuda_graph: on CUDA, replay each chunk's sampling as one CUDA graph, captured by hand without a compiler
            ([`PI0ForActionGeneration.capture_sampling`]); the first chunk of each batch size and prompt-length bucket
            captures it (about three eager calls) and verifies it against eager sampling, and so does the first chunk
            continued by real-time chunking "conditioning" (a graph of its own; "guidance" samples eagerly, see
            [`PI0ForActionGeneration.capture_sampling`]): call [`warmup`] first, which captures both. Should CUDA
            refuse a capture, the policy logs a warning and samples eagerly from then on (only its guided chunks, if
            guidance is what was refused); a graph refused by its verification samples eagerly too.
    """

    model_class = PI0ForActionGeneration
    processor_class = PI0Processor
    num_steps_setting = "num_inference_steps"
    max_num_steps = SIZE_LIMITS["num_inference_steps"]
    continues_chunks = True  # real-time chunking requests (see the class docstring)
    recommended_settings = ("noise_scale", "rtc_method")

    def __init__(
        self,
        model: PI0ForActionGeneration,
        processor: PI0Processor,
        num_steps: int | None = None,
        seed: int | None = None,
        compile: bool = False,
        rtc_method: str | None = None,
        rtc_max_guidance: float = DEFAULT_MAX_GUIDANCE,
        rtc_schedule: str = "exp",
        noise_scale: float = 1.0,
        cuda_graph: bool = False,
    ) -> None:
        self.noise_scale = check_float("noise_scale", noise_scale, minimum=0.0, maximum=MAX_NOISE_SCALE)
        self.rtc_method = rtc_method or ("conditioning" if model.config.rtc_max_delay > 0 else "guidance")
        if self.rtc_method not in METHODS:
            raise ValueError(f"rtc_method must be one of {METHODS}, got {self.rtc_method!r}")
        self.rtc_max_guidance = check_float("rtc_max_guidance", rtc_max_guidance, minimum=0.0, maximum=MAX_GUIDANCE)
        if rtc_schedule not in SCHEDULES:
            raise ValueError(f"rtc_schedule must be one of {SCHEDULES}, got {rtc_schedule!r}")
        self.rtc_schedule = rtc_schedule
        super().__init__(model, processor, num_steps=num_steps, seed=seed)
        if compile:
            model.compile_sampling(**({"mode": "reduce-overhead"} if self.device.type == "cuda" else {}))
        if cuda_graph:
            if self.device.type != "cuda":
                raise ValueError(f"cuda_graph needs a CUDA device; this policy runs on {self.device}")
            model.capture_sampling()

    @classmethod
    def from_pretrained(  # type: ignore[override]
        cls,
        directory: str | Path,
        device: str | torch.device | None = None,
        dtype: str | torch.dtype | None = None,
        num_steps: int | None = None,
        seed: int | None = None,
        default_prompt: str | None = None,
        compile: bool = False,
        rtc_method: str | None = None,
        rtc_schedule: str = "exp",
        noise_scale: float | None = None,
        cuda_graph: bool = False,
        threads: int | None = None,
    ) -> PI0Policy | PI0FastPolicy:
        """Load the model and processor saved in `directory` (by `save_pretrained` or the converter; `"demo"`: the
        policy shipped with the package): a `PI0Policy`, or for a π0-FAST folder a [`PI0FastPolicy`]
        ([`policy_class`]).

        `device` defaults to CUDA when available, else CPU; `dtype` ("float32" / "bfloat16" or a torch dtype)
        defaults to bfloat16 on CUDA and float32 on CPU. `default_prompt` replaces the processor's (used for
        observations without a prompt). `compile`, `cuda_graph`, `rtc_method`, `rtc_schedule` and `noise_scale` as in
        the class (a π0-FAST folder decodes tokens: it takes no `noise_scale`, and `cuda_graph` replays its prefill
        and each decoded token as CUDA graphs, see [`PI0FastPolicy`]).
        `num_steps`, `noise_scale` and `rtc_method` left None take the folder's recommended values
        (`policy_settings.json`, logged; the demo policy's: noise_scale 0.1, replan_steps 4), else the class's
        defaults. On a CPU `threads` chooses torch's threads as `pi0-torch eval` does (see
        [`BasePolicy.from_pretrained`]: one for a small model by default).
        """
        directory = policy_location(directory)
        loading = dict(device=device, dtype=dtype, num_steps=num_steps, seed=seed, default_prompt=default_prompt,
                       compile=compile, threads=threads)
        if cls is PI0Policy and policy_class(directory) is PI0FastPolicy:
            if noise_scale is not None:
                raise ValueError(f"noise_scale applies to flow-matching π0 / π0.5 sampling; {directory} is a π0-FAST "
                                 "model, which decodes tokens (see its temperature)")
            return PI0FastPolicy.from_pretrained(directory, **loading, cuda_graph=cuda_graph)
        return super().from_pretrained(directory, **loading, rtc_method=rtc_method, rtc_schedule=rtc_schedule,
                                       noise_scale=noise_scale, cuda_graph=cuda_graph)

    @property
    def metadata(self) -> dict[str, Any]:
        return {
            **super().metadata,
            "noise_scale": self.noise_scale,
            "real_time_chunking": {"methods": list(METHODS), "default_method": self.rtc_method,
                                   "guidance_schedule": self.rtc_schedule,
                                   "rtc_max_delay": self.model.config.rtc_max_delay},
        }

    def prepare(self, observation: Mapping[str, Any]) -> PreparedObservation:
        """[`BasePolicy.prepare`], plus the real-time chunking fields (`previous_actions` into this observation's
        model space, `inference_delay`, `execution_horizon`, `rtc_method`)."""
        prepared = super().prepare(observation)
        previous = observation.get("previous_actions")
        if previous is None:
            if any(observation.get(name) is not None for name in ("inference_delay", "execution_horizon")):
                raise ObservationError("inference_delay / execution_horizon: given without previous_actions")
            return prepared
        try:  # into this observation's model space (delta actions relative to its state)
            encoded = self.processor.encode_actions(previous, observation.get("state"), "previous_actions")
            prepared.continuation = self._continuation(observation, torch.from_numpy(encoded)[None])
        except (ValueError, TypeError) as error:
            raise ObservationError(str(error)) from None
        return prepared

    def _continuation(self, observation: Mapping[str, Any], previous: torch.Tensor) -> ChunkContinuation:
        horizon = self.model.config.action_horizon
        method = observation.get("rtc_method")
        if isinstance(method, np.ndarray) and method.ndim == 0:
            method = method.item()  # a numpy string scalar packed as a 0-d array
        if method is None:
            method = self.rtc_method
        elif not isinstance(method, str) or method not in METHODS:
            raise ObservationError(f"rtc_method: expected one of {list(METHODS)} (or no field: this policy's "
                                   f"{self.rtc_method!r}), got {method!r:.60}")
        check_rtc_inputs("previous_actions (normalized)", previous, self.rtc_max_guidance)
        executed = step_count(observation.get("execution_horizon"), "execution_horizon", 0, horizon - 1)
        delay = step_count(observation.get("inference_delay", 0), "inference_delay", 0, horizon - executed)
        if method == "conditioning" and delay > self.model.config.rtc_max_delay:
            raise ObservationError(f"inference_delay: {delay} exceeds the {self.model.config.rtc_max_delay} steps this "
                                   "model was trained to take as given (rtc_method 'conditioning'); use 'guidance'")
        return ChunkContinuation(previous, delay, executed, method)

    def _generate(self, prepared: Sequence[PreparedObservation], method: str | None) -> np.ndarray:
        """One model call for observations sampled alike (plain, or continued with `method`)."""
        batch = self._batch(prepared)
        config = self.model.config
        options: dict[str, Any] = {}
        if any(p.noise_seed is not None for p in prepared):
            shape = (1, config.action_horizon, config.action_dim)
            options["noise"] = self.noise_scale * torch.cat([
                torch.randn(shape, generator=torch.Generator().manual_seed(p.noise_seed)).to(self.device)
                if p.noise_seed is not None else torch.randn(shape, generator=self.generator, device=self.device)
                for p in prepared
            ])
        if method is not None:
            continuations = [p.continuation for p in prepared]
            options.update(
                previous_actions=torch.cat([c.previous_actions for c in continuations]).to(self.device),
                inference_delay=torch.tensor([c.inference_delay for c in continuations]),
                execution_horizon=torch.tensor([c.execution_horizon for c in continuations]),
                rtc_method=method,
                rtc_max_guidance=self.rtc_max_guidance,
                rtc_schedule=self.rtc_schedule,
            )
        return self.model_actions(batch, **options)

    def _warmup_options(self, batch: int) -> list[dict[str, Any]]:
        """A plain chunk; with graphs or compiled layers also a chunk continued by this policy's real-time chunking
        method (a graph of its own, which the first continued request would otherwise capture while the robot waits)."""
        guided_at_all = self.rtc_method != "guidance" or self.rtc_max_guidance > 0
        if not (self.compiled or self.model.replays_graphs(self.rtc_method)) or not guided_at_all:
            return [{}]
        config = self.model.config
        previous = torch.zeros(batch, config.action_horizon, config.action_dim, device=self.device)
        continued = dict(previous_actions=previous, inference_delay=0, execution_horizon=0, rtc_method=self.rtc_method,
                         rtc_max_guidance=self.rtc_max_guidance, rtc_schedule=self.rtc_schedule)
        return [{}, continued]

    def model_actions(self, batch: Mapping[str, torch.Tensor], warmup: bool = False, **options: Any) -> np.ndarray:  # type: ignore[override]
        """Model-space action chunks `[B, horizon, action_dim]` (float32 numpy) for a batch of model inputs.
        `options` go to `generate_actions` (`noise`, real-time chunking); without `noise` the policy's seeded
        generator draws it (times `noise_scale`), which a warm-up run leaves untouched."""
        if warmup:
            config = self.model.config
            options["noise"] = torch.zeros(len(batch["input_ids"]), config.action_horizon, config.action_dim, device=self.device)
        elif "noise" not in options:
            config = self.model.config
            shape = (len(batch["input_ids"]), config.action_horizon, config.action_dim)
            options["noise"] = self.noise_scale * torch.randn(shape, generator=self.generator, device=self.device)
        try:
            actions = self.model.generate_actions(**batch, num_steps=self.num_steps, **options)
        except SamplingCaptureError as error:  # a robot is better served eagerly than not at all
            logger.warning("%s; this policy samples eagerly from now on", error)
            self.model.capture_sampling(disable=True)
            actions = self.model.generate_actions(**batch, num_steps=self.num_steps, **options)
        return actions.float().cpu().numpy()

    def _sampling_cause(self, prepared: PreparedObservation) -> str:
        continuation = prepared.continuation
        if continuation is not None and continuation.method == "guidance":
            return (f"real-time chunking guidance diverged (rtc_max_guidance {self.rtc_max_guidance:g}, previous_actions "
                    f"up to {float(continuation.previous_actions.abs().max()):.3g} in model space)")
        kernels = self.model.sampling_kernels
        if kernels in ("auto", "persistent") and persistent_abandoned(self.model.device):  # ("auto": at batch 1-2)
            instead = "samples without it" if kernels == "persistent" else "samples without it from the next chunk"
            return f"{PERSISTENT_ABANDONED.removeprefix('its ')} (sampling_kernels='auto' {instead})"
        return (f"the model returned NaN/inf from finite inputs ({self._dtype_name} weights, noise_scale "
                f"{self.noise_scale:g})")

    @property
    def compiled(self) -> bool:
        return self.model.sampling_compiled

    @property
    def captured(self) -> bool:
        """Whether chunks replay CUDA graphs (`cuda_graph`, or `compile` on CUDA)."""
        return self.model.sampling_captured

    @property
    def model_type(self) -> str:
        return "pi05" if self.model.config.pi05 else "pi0"


def policy_class(directory: str | Path) -> type[PI0Policy] | type[PI0FastPolicy]:
    """The policy for the model saved in `directory`, from its `config.json` (π0 / π0.5, or π0-FAST); a file that
    is not a JSON object is a `ValueError` naming it."""
    config_path = Path(directory) / "config.json"
    if config_path.is_file() and PI0BaseConfig._dict_from_json_file(config_path).get("model_type") == PI0FastConfig.model_type:
        return PI0FastPolicy
    return PI0Policy
