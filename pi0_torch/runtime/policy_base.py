"""[`BasePolicy`]: what every policy of the π0 family does around its model -- one observation in, one action chunk in
robot units out -- so that [`PI0Policy`] (π0 / π0.5, `pi0_torch.runtime.policy`) and [`PI0FastPolicy`] (π0-FAST,
`pi0_torch.runtime.policy_fast`) differ only in how a batch of model inputs becomes chunks.

The base loads a saved model and its processor, checks each observation and turns it into model inputs through the
processor, batches observations into one model call, unnormalizes the chunks, withholds a chunk that is not finite
(naming the likeliest cause), warms up and describes itself to clients (`metadata`). A member supplies
[`BasePolicy.model_actions`]: π0 samples a flow from noise (and continues an executing chunk: real-time chunking),
π0-FAST decodes action tokens.
"""

from __future__ import annotations

import abc
import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from safetensors import SafetensorError

from pi0_torch import __version__
from pi0_torch.models.configuration_base import SIZE_LIMITS
from pi0_torch.models.pretrained import is_quantized
from pi0_torch.runtime.action_safety import withhold_unsafe
from pi0_torch.runtime.observation_formats import ObservationError, default_layout_sample
from pi0_torch.runtime.policy_settings import SETTINGS_FILE, PolicySettings
from pi0_torch.shipped_policy import policy_location
from pi0_torch.utils.hardware import usable_device
from pi0_torch.utils.threads import MAX_THREADS, set_threads
from pi0_torch.utils.validation import check_int, first_line

logger = logging.getLogger(__name__)

_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
# The most sampling steps (π0's Euler steps) or decoded tokens (π0-FAST) any member takes: `from_pretrained` refuses a
# larger `num_steps` before loading anything; the member's own bound applies once it is built.
_MAX_NUM_STEPS = max(SIZE_LIMITS["num_inference_steps"], SIZE_LIMITS["max_decoding_steps"])


@dataclasses.dataclass
class ChunkContinuation:
    """A request to continue the chunk the robot is executing (real-time chunking, see `pi0_torch.inference.rtc`)."""

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


# (processor setting, model config setting) that must agree: π0.5's prompt and normalization against π0's (pi05 on a π0
# model moved its actions by 2.0), the chunk length the model was trained at, the prompt and image sizes, the action dims
MATCHED_SETTINGS = (("pi05", "pi05"), ("action_horizon", "action_horizon"), ("max_token_len", "max_token_len"),
                    ("image_size", "image_size"), ("model_action_dim", "action_dim"))


class BasePolicy(abc.ABC):
    """A model and its processor behind openpi's policy interface (`infer(obs) -> dict`).

    Observations use the default layout `{"images": {camera_name: frame}, "state": [...], "prompt": str}` (see
    [`pi0_torch.runtime.observation_formats`] for other layouts). `infer` returns `{"actions": float32 [action_horizon,
    robot action dims], "policy_timing": {"infer_ms": model time, "batch_size": observations run together}}`,
    actions unnormalized by the processor.

    Args:
        model: the model, already on its device and dtype.
        processor: its processor.
        num_steps: sampling steps or decoded tokens per chunk (default: the config's `num_steps_setting`).
        seed: seeds the sampling, so a fresh policy gives the same chunks for the same requests.
    """

    model_class: ClassVar[Any]  # what `from_pretrained` loads
    processor_class: ClassVar[Any]
    num_steps_setting: ClassVar[str]  # the config setting that gives the default `num_steps`
    max_num_steps: ClassVar[int]
    continues_chunks: ClassVar[bool] = False  # takes real-time chunking requests (`previous_actions`, ...)
    # the constructor's settings that a folder's `policy_settings.json` may recommend (`num_steps` for every policy)
    recommended_settings: ClassVar[tuple[str, ...]] = ()

    def __init__(self, model: Any, processor: Any, num_steps: int | None = None, seed: int | None = None) -> None:
        self.settings = PolicySettings()  # the folder's recommended settings (`from_pretrained` sets them)
        self.model = model.eval()
        self.processor = processor
        self.num_steps = check_int("num_steps", num_steps if num_steps is not None else getattr(model.config, self.num_steps_setting),
                                   minimum=1, maximum=self.max_num_steps)
        self.device = next(model.parameters()).device
        self.generator = torch.Generator(self.device).manual_seed(seed) if seed is not None else None
        if list(processor.camera_names) != list(model.config.camera_names):
            raise ValueError(f"processor cameras {list(processor.camera_names)} differ from the model's "
                             f"{list(model.config.camera_names)}")
        for setting, config_setting in MATCHED_SETTINGS:  # (a processor setting None: not recorded, nothing to match)
            ours, theirs = getattr(processor, setting, None), getattr(model.config, config_setting, None)
            if ours is not None and theirs is not None and ours != theirs:
                raise ValueError(f"the processor's {setting} is {ours!r} but the model's config.json has {config_setting} "
                                 f"{theirs!r}: processor_config.json and config.json describe different models (the "
                                 "actions would be wrong, not refused); save the model and its processor together again")

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
        threads: int | None = None,
        **options: Any,
    ) -> Any:
        """Load the model and processor saved in `directory` (by `save_pretrained` or the converter; `"demo"`: the demo
        policy shipped with the package) into this policy.

        `device` defaults to CUDA when available, else CPU; `dtype` ("float32" / "bfloat16" or a torch dtype)
        defaults to bfloat16 on CUDA and float32 on CPU. `default_prompt` replaces the processor's (used for
        observations without a prompt). `compile` and `options` go to the policy's constructor. Settings left None
        (`num_steps`, and a member's own such as `noise_scale`) take the folder's recommended values
        (`policy_settings.json`, see `pi0_torch.runtime.policy_settings`), logged when used; the policy keeps them
        as `settings`.

        On a CPU, torch's threads are chosen as `pi0-torch eval` / `serve` choose them: `threads` (an int), or by
        default one thread for a model under 10 M parameters (the demo policy: 21 ms a chunk on one thread, 1.1-1.3 s
        on two busy cores) and torch's default for a larger one (`pi0_torch.utils.threads.set_threads`). torch's
        thread count is the process's: pass `threads` to choose another.
        """
        directory = policy_location(directory)
        if not Path(directory).is_dir():
            raise FileNotFoundError(f"model folder not found: {directory} (a folder written by save_pretrained or "
                                    "the openpi converter; 'demo' is the policy shipped with pi0-torch)")
        if num_steps is not None:  # before loading: a bad value fails in a moment, not after the weights load
            check_int("num_steps", num_steps, minimum=1, maximum=_MAX_NUM_STEPS)
        if threads is not None:
            check_int("threads", threads, minimum=1, maximum=MAX_THREADS)
        settings = PolicySettings.load(directory)
        device = usable_device(device)
        if dtype is None and is_quantized(directory):
            dtype = "auto"  # (a quantized model runs in the dtype it was quantized in: its kernels take that one)
        elif dtype is None:
            dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
        elif isinstance(dtype, str) and dtype != "auto":
            if dtype not in _DTYPES:
                raise ValueError(f"dtype must be one of {', '.join(_DTYPES)}, got {dtype!r}")
            dtype = _DTYPES[dtype]
        try:
            model = cls.model_class.from_pretrained(directory, dtype=dtype).to(device)
        except SafetensorError as error:  # truncated or foreign weights: one line naming the folder
            raise ValueError(f"{directory}: the weights are not a readable safetensors file ({first_line(error)}); "
                             "the folder is damaged (convert or copy it again)") from None
        if device.type == "cpu":
            set_threads(threads, model)
        overrides = {"default_prompt": default_prompt} if default_prompt is not None else {}
        processor = cls.processor_class.from_pretrained(directory, **overrides)
        given = dict(num_steps=num_steps, **{key: options.pop(key) for key in cls.recommended_settings if key in options})
        resolved = settings.resolve(**given)
        used = {key: value for key, value in resolved.items() if given[key] is None and value is not None}
        if used:
            logger.info("%s: using its recommended %s (%s)", directory, ", ".join(f"{k} {v}" for k, v in used.items()),
                        SETTINGS_FILE)
        policy = cls(model, processor, seed=seed, compile=compile, **{k: v for k, v in resolved.items() if v is not None},
                     **options)
        policy.settings = settings
        return policy

    # -- what a member supplies ------------------------------------------------------------------------------------

    @abc.abstractmethod
    def model_actions(self, batch: Mapping[str, torch.Tensor], warmup: bool = False) -> np.ndarray:
        """Model-space action chunks `[B, horizon, action_dim]` (float32 numpy) for a batch of model inputs; a
        `warmup` run leaves the policy's seeded randomness untouched."""

    @property
    @abc.abstractmethod
    def model_type(self) -> str:
        """`pi0`, `pi05` or `pi0_fast` (in `metadata`)."""

    @property
    @abc.abstractmethod
    def compiled(self) -> bool:
        """Whether chunks run through `torch.compile`."""

    @property
    @abc.abstractmethod
    def captured(self) -> bool:
        """Whether chunks replay hand-captured CUDA graphs."""

    # -- the policy interface --------------------------------------------------------------------------------------

    @property
    def camera_names(self) -> list[str]:
        return list(self.model.config.camera_names)

    @property
    def metadata(self) -> dict[str, Any]:
        """What a client may want to know before sending observations (sent first by the policy server)."""
        return {
            "policy": f"pi0-torch {__version__}",
            "model_type": self.model_type,
            "camera_names": self.camera_names,
            "state_dim": self.processor.state_dim,
            "action_dim": self.processor.action_dim_robot,
            "action_horizon": self.model.config.action_horizon,
            "num_steps": self.num_steps,
            "default_prompt": self.processor.default_prompt,
            "device": str(self.device),
            "cuda_graph": self.captured,
            "dtype": self._dtype_name,
            "real_time_chunking": None,
            "replan_steps": self.settings.replan_steps,  # the actions to execute per chunk it was validated with (or None)
        }

    def prepare(self, observation: Mapping[str, Any]) -> PreparedObservation:
        """Check one default-layout observation and build its model inputs; raises [`ObservationError`].

        The processor checks every field (cameras, frame shapes and ranges, state length, NaN/inf, prompt) and its
        message names the field, what was expected and what came.
        """
        refusal = None if self.continues_chunks else f"this {self.model_type} policy decodes tokens"
        sample, seed = default_layout_sample(observation, self.processor.state_dim, refusal)
        try:
            inputs = dict(self.processor(sample, return_tensors="pt"))
            raw_state = np.asarray(sample["state"], dtype=np.float32)
        except (ValueError, TypeError) as error:
            raise ObservationError(str(error)) from None
        return PreparedObservation(inputs=inputs, state=raw_state, noise_seed=seed)

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
        robot = [self.processor.postprocess_actions(chunk, state=p.state) for chunk, p in zip(actions, prepared)]
        normalized = None if self.processor.norm_stats is None or self.processor.norm_mode == "none" else [
            chunk[..., : self.processor.action_dim_robot] for chunk in actions]
        return withhold_unsafe(robot, lambda index: self._unsafe_cause(actions[index], prepared[index]), model_ms,
                               self.settings.max_abs_action, normalized)

    def infer(self, observation: Mapping[str, Any]) -> dict[str, Any]:
        """Actions for one observation: `{"actions": float32 [horizon, robot action dims], "policy_timing": ...}`."""
        return self.infer_prepared([self.prepare(observation)])[0]

    @torch.inference_mode()
    def warmup(self, max_batch_size: int = 1) -> float:
        """Run chunks on a blank observation (black frames, zero state) so that real requests do not pay for
        compilation, CUDA graph capture or first allocations; returns the seconds it took. A compiled or captured
        policy runs every batch size up to `max_batch_size` (each is its own graph), an eager one batch 1. (Graphs are
        per prompt-length bucket and set of cameras shown too: the warm-up shows every camera, so a prompt much longer
        than the default one, or a request that leaves a camera out, captures on its first chunk.) The policy's seeded
        randomness is left untouched."""
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
            for options in self._warmup_options(batch):
                self.model_actions(inputs, warmup=True, **options)
        return time.monotonic() - start

    def _warmup_options(self, batch: int) -> list[dict[str, Any]]:
        """The calls `warmup` makes per batch size, as options of a member's `model_actions`: one plain call."""
        return [{}]

    # -- inside ------------------------------------------------------------------------------------------------------

    def _generate(self, prepared: Sequence[PreparedObservation], method: str | None) -> np.ndarray:
        """One model call for observations sampled alike (plain, or continued with `method`)."""
        return self.model_actions(self._batch(prepared))

    def _batch(self, prepared: Sequence[PreparedObservation]) -> dict[str, torch.Tensor]:
        """The model inputs of `prepared`, as one batch on the policy's device."""
        return {name: torch.cat([p.inputs[name] for p in prepared]).to(self.device) for name in prepared[0].inputs}

    def _unsafe_cause(self, chunk: np.ndarray, prepared: PreparedObservation) -> str:
        """The likeliest reason an action chunk is not finite (model space `chunk`), for the error withholding it. (Its
        unnormalizing cannot overflow: the norm stats are bounded at load, `normalization.MAX_STATISTIC`, and the
        model-space actions by `action_safety.MAX_NORMALIZED_ACTION` before it.)"""
        broken = next((name for name, value in self.model.named_parameters() if not bool(torch.isfinite(value).all())), None)
        if broken is not None:
            return f"the model's weights hold NaN/inf (the first: {broken})"
        return self._sampling_cause(prepared)

    def _sampling_cause(self, prepared: PreparedObservation) -> str:
        """Why finite weights gave a chunk that is not finite from a finite observation."""
        return f"the model returned NaN/inf from finite inputs ({self._dtype_name} weights)"

    @property
    def _dtype_name(self) -> str:
        return str(self.model.dtype).removeprefix("torch.")
