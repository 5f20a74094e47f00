"""`PI0Policy`: one observation in, one action chunk in robot units out (the model and its processor together).

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

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from safetensors import SafetensorError

from pi0_torch import __version__
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.configuration_pi0 import MAX_INFERENCE_STEPS, SIZE_LIMITS
from pi0_torch.models.rtc import DEFAULT_MAX_GUIDANCE, MAX_GUIDANCE, METHODS, SCHEDULES, check_rtc_inputs
from pi0_torch.runtime.action_safety import UnsafeActionsError, non_finite_count
from pi0_torch.runtime.observation_formats import CHUNK_FIELDS, ObservationError
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.utils.validation import check_float, check_int, first_line

_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
MAX_NOISE_SCALE = 10.0  # ten times the training noise; 1e30 gave NaN actions


@dataclasses.dataclass
class ChunkContinuation:
    """A request to continue the chunk the robot is executing (real-time chunking, see `pi0_torch.models.rtc`)."""

    previous_actions: torch.Tensor  # [1, horizon, model action dims], the previous chunk in this observation's model space
    inference_delay: int  # d: steps of the previous chunk the robot executes while this one is computed
    execution_horizon: int  # s: steps of the previous chunk executed before this observation
    method: str  # "guidance" or "conditioning"


@dataclasses.dataclass
class PreparedObservation:
    """A checked observation turned into model inputs (batch of one, on the CPU) plus the raw robot state."""

    inputs: dict[str, torch.Tensor]
    state: np.ndarray  # [robot state dims], for the processor's delta-action inverse
    continuation: ChunkContinuation | None = None
    noise_seed: int | None = None  # this chunk's noise from its own generator (independent of batching)


class PI0Policy:
    """[`PI0ForActionGeneration`] + [`PI0Processor`] behind openpi's policy interface (`infer(obs) -> dict`).
    (`from_pretrained` of a π0-FAST folder gives its sibling [`pi0_torch.runtime.policy_fast.PI0FastPolicy`].)

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
            captures it (about two eager calls): call [`warmup`] first. Chunks guided by real-time chunking
            ("guidance") run eagerly.
    """

    model_class: Any = PI0ForActionGeneration
    processor_class: Any = PI0Processor

    continues_chunks: ClassVar[bool] = True  # real-time chunking requests (see the class docstring)
    max_num_steps: ClassVar[int] = MAX_INFERENCE_STEPS

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
        self.model = model.eval()
        self.noise_scale = check_float("noise_scale", noise_scale, minimum=0.0, maximum=MAX_NOISE_SCALE)
        self.rtc_method = rtc_method or ("conditioning" if getattr(model.config, "rtc_max_delay", 0) > 0 else "guidance")
        if self.rtc_method not in METHODS:
            raise ValueError(f"rtc_method must be one of {METHODS}, got {self.rtc_method!r}")
        self.rtc_max_guidance = check_float("rtc_max_guidance", rtc_max_guidance, minimum=0.0, maximum=MAX_GUIDANCE)
        if rtc_schedule not in SCHEDULES:
            raise ValueError(f"rtc_schedule must be one of {SCHEDULES}, got {rtc_schedule!r}")
        self.rtc_schedule = rtc_schedule
        self.processor = processor
        self.num_steps = check_int("num_steps", num_steps if num_steps is not None else model.config.num_inference_steps,
                                   minimum=1, maximum=self.max_num_steps)
        self.device = next(model.parameters()).device
        self.generator = torch.Generator(self.device).manual_seed(seed) if seed is not None else None
        if list(processor.camera_names) != list(model.config.camera_names):
            raise ValueError(f"processor cameras {list(processor.camera_names)} differ from the model's "
                             f"{list(model.config.camera_names)}")
        if compile:
            model.compile_sampling(**({"mode": "reduce-overhead"} if self.device.type == "cuda" else {}))
        if cuda_graph:
            if self.device.type != "cuda":
                raise ValueError(f"cuda_graph needs a CUDA device; this policy runs on {self.device}")
            model.capture_sampling()

    @classmethod
    def from_pretrained(
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
        noise_scale: float = 1.0,
        cuda_graph: bool = False,
    ) -> PI0Policy:
        """Load the model and processor saved in `directory` (by `save_pretrained` or the converter).

        `device` defaults to CUDA when available, else CPU; `dtype` ("float32" / "bfloat16" or a torch dtype)
        defaults to bfloat16 on CUDA and float32 on CPU. `default_prompt` replaces the processor's (used for
        observations without a prompt). `compile`, `cuda_graph`, `rtc_method`, `rtc_schedule` and `noise_scale` as in
        the class (a π0-FAST folder decodes tokens: it takes no `noise_scale`, and `compile` gives its CUDA graphs).
        """
        if not Path(directory).is_dir():
            raise FileNotFoundError(f"model folder not found: {directory} (a folder written by save_pretrained or "
                                    "the openpi converter)")
        if num_steps is not None:  # before loading: a bad value fails in a moment, not after the weights load
            check_int("num_steps", num_steps, minimum=1, maximum=max(MAX_INFERENCE_STEPS, SIZE_LIMITS["max_decoding_steps"]))
        device = torch.device(device if device is not None else ("cuda" if torch.cuda.is_available() else "cpu"))
        if dtype is None:
            dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
        elif isinstance(dtype, str):
            if dtype not in _DTYPES:
                raise ValueError(f"dtype must be one of {', '.join(_DTYPES)}, got {dtype!r}")
            dtype = _DTYPES[dtype]
        policy_class = _policy_class(directory) if cls is PI0Policy else cls
        try:
            model = policy_class.model_class.from_pretrained(directory, dtype=dtype).to(device)
        except SafetensorError as error:  # truncated or foreign weights: one line naming the folder
            raise ValueError(f"{directory}: the weights are not a readable safetensors file ({first_line(error)}); "
                             "the folder is damaged (convert or copy it again)") from None
        overrides = {"default_prompt": default_prompt} if default_prompt is not None else {}
        processor = policy_class.processor_class.from_pretrained(directory, **overrides)
        if noise_scale != 1.0 and not policy_class.continues_chunks:
            raise ValueError(f"noise_scale applies to flow-matching π0 / π0.5 sampling; {directory} is a π0-FAST "
                             "model, which decodes tokens (see its temperature)")
        if cuda_graph and not policy_class.continues_chunks:
            raise ValueError(f"{directory} is a π0-FAST model, which decodes token by token: compile=True replays its "
                             "decoding steps as CUDA graphs")
        options = (dict(rtc_method=rtc_method, rtc_schedule=rtc_schedule, noise_scale=noise_scale, cuda_graph=cuda_graph)
                   if policy_class.continues_chunks else {})
        return policy_class(model, processor, num_steps=num_steps, seed=seed, compile=compile, **options)

    @property
    def camera_names(self) -> list[str]:
        return list(self.model.config.camera_names)

    @property
    def metadata(self) -> dict[str, Any]:
        """What a client may want to know before sending observations (sent first by the policy server)."""
        config = self.model.config
        return {
            "policy": f"pi0-torch {__version__}",
            "model_type": self.model_type,
            "camera_names": self.camera_names,
            "state_dim": self.processor.state_dim,
            "action_dim": self.processor.action_dim_robot,
            "action_horizon": config.action_horizon,
            "num_steps": self.num_steps,
            **({"noise_scale": self.noise_scale} if self.continues_chunks else {}),
            "default_prompt": self.processor.default_prompt,
            "device": str(self.device),
            "cuda_graph": self.captured,
            "dtype": str(self.model.dtype).removeprefix("torch."),
            "real_time_chunking": {"methods": list(METHODS), "default_method": self.rtc_method,
                                   "guidance_schedule": self.rtc_schedule,
                                   "rtc_max_delay": config.rtc_max_delay} if self.continues_chunks else None,
        }

    def prepare(self, observation: Mapping[str, Any]) -> PreparedObservation:
        """Check one default-layout observation and build its model inputs; raises [`ObservationError`].

        The processor checks every field (cameras, frame shapes and ranges, state length, NaN/inf, prompt) and its
        message names the field, what was expected and what came.
        """
        if not isinstance(observation, Mapping):
            raise ObservationError(f"observation must be a dict, got {type(observation).__name__}")
        state = observation.get("state")
        if state is not None and np.ndim(state) != 1:  # a 2-D state would mean a batch to the processor
            raise ObservationError(f"observation.state: expected shape [{self.processor.state_dim}], "
                                   f"got {list(np.shape(state))}")
        sample = {"images": observation.get("images"), "state": state, "prompt": observation.get("prompt")}
        previous = observation.get("previous_actions")
        chunk_fields = [name for name in CHUNK_FIELDS if name != "noise_seed" and observation.get(name) is not None]
        if chunk_fields and not self.continues_chunks:
            raise ObservationError(f"{', '.join(chunk_fields)}: this {self.model_type} policy decodes tokens; it does "
                                   "not continue chunks")
        continuation = None
        try:
            inputs = dict(self.processor(sample, return_tensors="pt"))
            raw_state = np.asarray(state, dtype=np.float32)
            if previous is not None:  # into this observation's model space (delta actions relative to its state)
                encoded = self.processor.encode_actions(previous, state, "previous_actions")
                continuation = self._continuation(observation, torch.from_numpy(encoded)[None])
        except (ValueError, TypeError) as error:
            raise ObservationError(str(error)) from None
        if previous is None and any(observation.get(name) is not None for name in ("inference_delay", "execution_horizon")):
            raise ObservationError("inference_delay / execution_horizon: given without previous_actions")
        seed = observation.get("noise_seed")
        if seed is not None:
            seed = _step_count(seed, "noise_seed", 0, 2**63 - 1)
        return PreparedObservation(inputs=inputs, state=raw_state, continuation=continuation, noise_seed=seed)

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
        executed = _step_count(observation.get("execution_horizon"), "execution_horizon", 0, horizon - 1)
        delay = _step_count(observation.get("inference_delay", 0), "inference_delay", 0, horizon - executed)
        if method == "conditioning" and delay > self.model.config.rtc_max_delay:
            raise ObservationError(f"inference_delay: {delay} exceeds the {self.model.config.rtc_max_delay} steps this "
                                   "model was trained to take as given (rtc_method 'conditioning'); use 'guidance'")
        return ChunkContinuation(previous, delay, executed, method)

    @torch.inference_mode()
    def infer_prepared(self, prepared: Sequence[PreparedObservation]) -> list[dict[str, Any]]:
        """Run the model once on a batch of prepared observations; one action dict per observation.

        A chunk with NaN or inf (after unnormalizing) is never handed back: [`UnsafeActionsError`] names its cause,
        and its `outcomes` hold the other observations' replies."""
        start = time.monotonic()
        actions: list[np.ndarray | None] = [None] * len(prepared)
        groups: dict[str | None, list[int]] = {}  # one model call per way of sampling
        for index, p in enumerate(prepared):
            groups.setdefault(p.continuation.method if p.continuation else None, []).append(index)
        for method, members in groups.items():
            chunks = self._generate([prepared[i] for i in members], method)  # [b, horizon, action_dim]
            for index, chunk in zip(members, chunks):
                actions[index] = chunk
        model_ms = (time.monotonic() - start) * 1000
        outcomes: list[dict[str, Any] | UnsafeActionsError] = []
        for index, (chunk, p) in enumerate(zip(actions, prepared)):
            robot = np.asarray(self.processor.postprocess_actions(chunk, state=p.state), dtype=np.float32)
            bad = non_finite_count(robot)
            if bad:
                where = f"observation {index} of a batch of {len(prepared)}: " if len(prepared) > 1 else ""
                outcomes.append(UnsafeActionsError(f"{where}the action chunk holds {bad} NaN/inf values and was "
                                                   f"withheld; cause: {self._unsafe_cause(chunk, p)}"))
            else:
                outcomes.append({"actions": robot, "policy_timing": {"infer_ms": model_ms, "batch_size": len(prepared)}})
        unsafe = [outcome for outcome in outcomes if isinstance(outcome, UnsafeActionsError)]
        if unsafe:
            raise UnsafeActionsError(str(unsafe[0]), outcomes)
        return outcomes  # type: ignore[return-value]

    def _unsafe_cause(self, chunk: np.ndarray, prepared: PreparedObservation) -> str:
        """The likeliest reason an action chunk is not finite (model space `chunk`), for the error withholding it."""
        if np.isfinite(chunk).all():
            return "unnormalizing with the processor's action norm stats overflowed float32 (see its norm_stats.json)"
        broken = next((name for name, value in self.model.named_parameters() if not bool(torch.isfinite(value).all())), None)
        if broken is not None:
            return f"the model's weights hold NaN/inf (the first: {broken})"
        continuation = prepared.continuation
        if continuation is not None and continuation.method == "guidance":
            return (f"real-time chunking guidance diverged (rtc_max_guidance {self.rtc_max_guidance:g}, previous_actions "
                    f"up to {float(continuation.previous_actions.abs().max()):.3g} in model space)")
        return (f"the model returned NaN/inf from finite inputs ({str(self.model.dtype).removeprefix('torch.')} "
                f"weights, noise_scale {getattr(self, 'noise_scale', 0.0):g})")

    def _generate(self, prepared: Sequence[PreparedObservation], method: str | None) -> np.ndarray:
        """One model call for observations sampled alike (plain, or continued with `method`)."""
        batch = {name: torch.cat([p.inputs[name] for p in prepared]).to(self.device) for name in prepared[0].inputs}
        config = self.model.config
        options: dict[str, Any] = {}
        if self.continues_chunks and any(p.noise_seed is not None for p in prepared):  # (FAST decodes greedily)
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

    def model_actions(self, batch: Mapping[str, torch.Tensor], warmup: bool = False, **options: Any) -> np.ndarray:
        """Model-space action chunks `[B, horizon, action_dim]` (float32 numpy) for a batch of model inputs.
        `options` go to `generate_actions` (`noise`, real-time chunking); without `noise` the policy's seeded
        generator draws it (times `noise_scale`), which a warm-up run leaves untouched."""
        if warmup:
            config = self.model.config
            options = {"noise": torch.zeros(len(batch["input_ids"]), config.action_horizon, config.action_dim, device=self.device)}
        elif "noise" not in options and self.continues_chunks:
            config = self.model.config
            shape = (len(batch["input_ids"]), config.action_horizon, config.action_dim)
            options["noise"] = self.noise_scale * torch.randn(shape, generator=self.generator, device=self.device)
        elif "noise" not in options:
            options["generator"] = self.generator
        return self.model.generate_actions(**batch, num_steps=self.num_steps, **options).float().cpu().numpy()

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

    @torch.inference_mode()
    def warmup(self, max_batch_size: int = 1) -> float:
        """Run chunks on a blank observation (black frames, zero state) so that real requests do not pay for
        compilation, CUDA graph capture or first allocations; returns the seconds it took. A compiled or captured
        policy runs every batch size up to `max_batch_size` (each is its own graph), an eager one batch 1. (Graphs are
        per prompt-length bucket too: a prompt much longer than the default one captures on its first chunk.) The
        policy's seeded noise is left untouched."""
        start = time.monotonic()
        size = self.processor.image_size
        blank = {
            "images": {name: np.zeros((size, size, 3), np.uint8) for name in self.camera_names},
            "state": np.zeros(self.processor.state_dim, np.float32),
            "prompt": self.processor.default_prompt or "warm-up",
        }
        one = {name: tensor.to(self.device) for name, tensor in self.prepare(blank).inputs.items()}
        for batch in range(1, (max_batch_size if self.compiled or self.captured else 1) + 1):
            inputs = {name: torch.cat([tensor] * batch) for name, tensor in one.items()}  # laid out as real batches
            self.model_actions(inputs, warmup=True)
        return time.monotonic() - start

    def infer(self, observation: Mapping[str, Any]) -> dict[str, Any]:
        """Actions for one observation: `{"actions": float32 [horizon, robot action dims], "policy_timing": ...}`."""
        return self.infer_prepared([self.prepare(observation)])[0]


def _step_count(value: Any, name: str, low: int, high: int) -> int:
    """An integer field of an observation in `[low, high]` (a 0-d array too), or an `ObservationError` naming it."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    try:
        return check_int(name, value, low, high)
    except ValueError as error:
        raise ObservationError(str(error)) from None


def _policy_class(directory: str | Path) -> type[PI0Policy]:
    """The policy for the model saved in `directory`, from its `config.json` (π0 / π0.5, or π0-FAST); a file that
    is not a JSON object is a `ValueError` naming it."""
    from pi0_torch.models.configuration_pi0 import PI0Config
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig

    config_path = Path(directory) / "config.json"
    if config_path.is_file() and PI0Config._dict_from_json_file(config_path).get("model_type") == PI0FastConfig.model_type:
        from pi0_torch.runtime.policy_fast import PI0FastPolicy

        return PI0FastPolicy
    return PI0Policy
