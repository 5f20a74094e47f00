"""`ExportedPolicy`: an exported graph (`pi0-torch export`) behind the same `infer(obs) -> {"actions": ...}` contract,
observation format and errors as `PI0Policy`, without the model classes. An ONNX export needs numpy, onnxruntime,
sentencepiece and Pillow only (no torch); a `pt2` package needs torch.

The host's part is the processor's, unchanged (`PI0Processor` loaded from the export folder, which imports no torch):
the observation is checked field by field, the frames resized with padding to uint8, the state converted and checked,
the prompt tokenized (π0.5: with the normalized state in it). The graph does the rest: normalization, the sampling,
unnormalization and delta actions. Noise is drawn on the host with numpy's generator (seeded by `seed`, or per
request by `noise_seed`), scaled by `noise_scale` (the folder's recommended one by default).

```python
>>> from pi0_torch.deploy import ExportedPolicy
>>> policy = ExportedPolicy.from_folder("exported/demo_onnx")  # doctest: +SKIP
>>> policy.infer({"images": {"base_0_rgb": frame}, "state": state, "prompt": "pick up the red block"})["actions"].shape  # doctest: +SKIP
(16, 3)

```
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pi0_torch.deploy.folder import (ACTION_TOLERANCE, DEPLOY_FILE, FORMAT_NAME, INPUT_NAMES, REFERENCE_FILE,
                                     ExportFolderError, action_deviation, check_artifact_hash, read_deploy)
from pi0_torch.deploy.runners import check_provider, load_runner
from pi0_torch.runtime.action_safety import withhold_unsafe
from pi0_torch.runtime.observation_formats import ObservationError, default_layout_sample
from pi0_torch.runtime.policy_settings import MAX_NOISE_SCALE, PolicySettings
from pi0_torch.utils.threads import MAX_THREADS, SMALL_MODEL_PARAMETERS
from pi0_torch.utils.validation import check_float, check_int

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class PreparedExportObservation:
    """A checked observation as the graph's inputs for one sample (no batch axis)."""

    images: np.ndarray  # uint8 [C, H, W, 3]
    image_masks: np.ndarray  # bool [C]
    input_ids: np.ndarray  # int64 [L]
    attention_mask: np.ndarray  # bool [L]
    state: np.ndarray  # float32 [state_dim], the checkpoint's units
    noise_seed: int | None = None


class ExportedPolicy:
    """An export folder as a policy (see the module docstring). Build it with [`from_folder`]."""

    def __init__(self, directory: Path, spec: dict[str, Any], processor: Any, runner: Any, settings: PolicySettings,
                 provider: str, seed: int | None = None, noise_scale: float | None = None) -> None:
        self.directory, self.spec, self.processor, self.runner = directory, spec, processor, runner
        self.settings, self.provider = settings, provider
        model = spec["model"]
        self.batch_size, self.num_steps = int(model["batch_size"]), int(model["num_steps"])
        self.action_horizon, self.action_dim = int(model["action_horizon"]), int(model["action_dim"])
        self.text_length = int(spec["prompt"]["length"])
        scale = noise_scale if noise_scale is not None else settings.noise_scale if settings.noise_scale is not None else 1.0
        self.noise_scale = check_float("noise_scale", scale, minimum=0.0, maximum=MAX_NOISE_SCALE)
        self.generator = np.random.default_rng(seed)
        self._conversion = None
        if processor.value_conversion is not None:
            from pi0_torch.processing.robot_spaces import get_conversion

            self._conversion = get_conversion(processor.value_conversion)

    @classmethod
    def from_folder(cls, directory: str | Path, provider: str = "cpu", threads: int | None = None, seed: int | None = None,
                    noise_scale: float | None = None, default_prompt: str | None = None, verify: bool = True) -> ExportedPolicy:
        """Load an export folder. `provider`: "cpu", "cuda", or for ONNX "tensorrt" (onnxruntime-gpu's providers);
        `threads`: the runtime's intra-op threads (default: one for a model under 10 M parameters, as `PI0Policy`,
        else the runtime's own). `noise_scale` None takes the folder's recommended one
        (`policy_settings.json`). `verify`: check the graph file's SHA-256 against `deploy.json`, and run the folder's
        `reference.npz` once, refusing a runtime whose actions deviate (`ExportFolderError`, one line)."""
        directory = Path(directory)
        spec = read_deploy(directory)
        if threads is not None:
            check_int("threads", threads, minimum=1, maximum=MAX_THREADS)
        elif int(spec["model"].get("parameters", SMALL_MODEL_PARAMETERS)) < SMALL_MODEL_PARAMETERS:
            threads = 1  # (as `pi0-torch eval` runs a small model: more threads only slow it down)
        artifact = spec["artifact"]
        check_provider(artifact["format"], provider)
        if artifact["format"] == "onnx" and provider == "cpu" and artifact["dtype"] != "float32":
            raise ExportFolderError(f"{directory} holds a {artifact['dtype']} ONNX graph, which onnxruntime runs on its "
                                    "'cuda' and 'tensorrt' providers only (its CPU provider has no such kernels): export "
                                    "with --dtype float32 for a CPU")
        if artifact["format"] == "pt2" and provider != artifact["device"]:
            raise ExportFolderError(f"{directory} is an AOTInductor package compiled for {artifact['device']}; it runs "
                                    f"there only (provider {artifact['device']!r}), not on {provider!r}")
        if not (directory / "tokenizer.model").is_file():
            raise ExportFolderError(f"{directory}: tokenizer.model is missing; copy or export the folder again")
        if verify:
            check_artifact_hash(directory, spec)
        from pi0_torch.processing.processing_pi0 import PI0Processor

        overrides = {"default_prompt": default_prompt} if default_prompt is not None else {}
        try:
            processor = PI0Processor.from_pretrained(directory, **overrides)
        except (OSError, ValueError) as error:
            raise ExportFolderError(f"{directory}: its processor files do not load ({str(error)[:300]})") from None
        runner = load_runner(directory / artifact["file"], artifact["format"], provider, threads)
        policy = cls(directory, spec, processor, runner, PolicySettings.load(directory), provider, seed, noise_scale)
        if verify:
            policy.self_check()
        return policy

    def self_check(self) -> float:
        """Run the folder's `reference.npz` inputs and compare with the actions recorded at export: the deviation
        (relative to the largest action), or `ExportFolderError` beyond the export's bound for its dtype."""
        reference = np.load(self.directory / REFERENCE_FILE)
        actions = self.runner([reference[name] for name in INPUT_NAMES])
        want = reference["actions"]
        deviation = action_deviation(actions, want)
        bound = ACTION_TOLERANCE.get(self.spec["artifact"]["dtype"], ACTION_TOLERANCE["float32"])
        if not deviation <= bound:
            raise ExportFolderError(f"{self.directory}: this runtime ({self.provider}) returns actions that deviate from "
                                    f"the export's by {deviation:.3g} of the largest action (bound {bound:g})")
        return deviation

    # -- the policy interface (as `PI0Policy`'s) ---------------------------------------------------------------------

    @property
    def camera_names(self) -> list[str]:
        return list(self.processor.camera_names)

    @property
    def metadata(self) -> dict[str, Any]:
        """What a client may want to know before sending observations (sent first by the policy server)."""
        from pi0_torch import __version__

        return {
            "policy": f"pi0-torch {__version__} (exported {self.spec['artifact']['format']})",
            "model_type": self.spec["model"]["type"],
            "camera_names": self.camera_names,
            "state_dim": self.processor.state_dim,
            "action_dim": self.processor.action_dim_robot,
            "action_horizon": self.action_horizon,
            "num_steps": self.num_steps,
            "default_prompt": self.processor.default_prompt,
            "device": self.provider,
            "cuda_graph": False,
            "dtype": self.spec["artifact"]["dtype"],
            "real_time_chunking": None,
            "replan_steps": self.settings.replan_steps,
            "noise_scale": self.noise_scale,
        }

    def prepare(self, observation: Mapping[str, Any]) -> PreparedExportObservation:
        """Check one default-layout observation and build the graph's inputs for it; raises [`ObservationError`]
        naming the field (the processor's own checks, as `PI0Policy.prepare`)."""
        sample, seed = default_layout_sample(observation, self.processor.state_dim,
                                             f"this exported {self.spec['model']['type']} policy takes no real-time chunking")
        try:
            where = "observation."  # (the processor's prefix for one observation dict, as `PI0Policy`'s errors read)
            state, _, input_ids, attention_mask = self.processor.encode_state_and_prompt(sample, where)
            images, masks = self.processor.encode_uint8_images(sample["images"], where)
        except (ValueError, TypeError) as error:
            raise ObservationError(str(error)) from None
        if attention_mask[self.text_length:].any():
            raise ObservationError(f"prompt: {int(attention_mask.sum())} tokens; this export takes at most "
                                   f"{self.text_length} (export again with a larger --text-length)")
        return PreparedExportObservation(images, masks, input_ids[: self.text_length], attention_mask[: self.text_length],
                                         state.astype(np.float32), seed)

    def infer_prepared(self, prepared: Sequence[PreparedExportObservation]) -> list[dict[str, Any]]:
        """Run the graph on prepared observations (in calls of its batch size; a short last call is padded with
        copies); one action dict per observation. A chunk with NaN or inf is never handed back:
        [`UnsafeActionsError`] names it, and its `outcomes` hold the other observations' replies."""
        start = time.monotonic()
        chunks: list[np.ndarray] = []
        for first in range(0, len(prepared), self.batch_size):
            group = list(prepared[first : first + self.batch_size])
            padded = group + [group[-1]] * (self.batch_size - len(group))
            noise = np.stack([self._noise(p.noise_seed) for p in group] + [self._noise(0)] * (len(padded) - len(group)))
            inputs = [np.stack([p.images for p in padded]), np.stack([p.image_masks for p in padded]),
                      np.stack([p.input_ids for p in padded]), np.stack([p.attention_mask for p in padded]),
                      np.stack([p.state for p in padded]), noise]
            chunks.extend(self.runner(inputs)[: len(group)])
        infer_ms = (time.monotonic() - start) * 1000
        robot = [chunk if self._conversion is None else self._conversion.actions_to_robot(chunk) for chunk in chunks]
        artifact = f"{self.spec['artifact']['dtype']}, {self.provider}, noise_scale {self.noise_scale:g}"
        return withhold_unsafe(robot, lambda index: f"the exported graph returned NaN/inf ({artifact})", infer_ms,
                               self.settings.max_abs_action)

    def infer(self, observation: Mapping[str, Any]) -> dict[str, Any]:
        """Actions for one observation: `{"actions": float32 [horizon, robot action dims], "policy_timing": ...}`."""
        return self.infer_prepared([self.prepare(observation)])[0]

    def warmup(self, max_batch_size: int = 1) -> float:
        """One call on a blank observation (first allocations; TensorRT builds its engine here); returns its seconds.
        The policy's seeded noise is left untouched."""
        start = time.monotonic()
        size = self.processor.image_size
        blank = self.prepare({"images": {name: np.zeros((size, size, 3), np.uint8) for name in self.camera_names},
                              "state": np.zeros(self.processor.state_dim, np.float32),
                              "prompt": self.processor.default_prompt or "warm-up", "noise_seed": 0})
        self.infer_prepared([blank])
        return time.monotonic() - start

    def _noise(self, seed: int | None) -> np.ndarray:
        generator = self.generator if seed is None else np.random.default_rng(seed)
        shape = (self.action_horizon, self.action_dim)
        return (self.noise_scale * generator.standard_normal(shape)).astype(np.float32)


def is_export_folder(directory: str | Path) -> bool:
    """Whether `directory` holds an exported policy (`deploy.json`), for commands that take either kind of folder."""
    path = Path(directory) / DEPLOY_FILE
    if not path.is_file():
        return False
    try:
        return json.loads(path.read_text()).get("format") == FORMAT_NAME
    except (OSError, ValueError, AttributeError, RecursionError):
        return True  # (one that claims to be: `read_deploy` names what is wrong with it)
