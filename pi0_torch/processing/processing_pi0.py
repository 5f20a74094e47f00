"""`PI0Processor`: raw robot observations -> `PI0ForActionGeneration` inputs, and model actions -> robot actions.

The processor reproduces openpi's data pipeline for π0 / π0.5 (a robot's value conversion such as ALOHA's
`adapt_to_pi` -> `DeltaActions` -> `Normalize` -> `ResizeImages` -> `TokenizePrompt` -> `PadStatesAndActions`, and on
the way out `Unnormalize` -> `AbsoluteActions` -> robot dims -> the conversion back):

- images: every camera of `camera_names`, in that order, resized with padding to `image_size` and mapped to
  [-1, 1] channels first (see `pi0_torch.processing.images` for accepted frames); an absent camera is an all -1 image with
  mask False;
- state: the robot's `state_dim` values, converted with `value_conversion` if set (`pi0_torch.processing.robot_spaces`),
  normalized (z-score for π0, quantile for π0.5, see `pi0_torch.processing.normalization`), zero-padded to `model_action_dim`;
- prompt: cleaned and tokenized in the π0 format, or for π0.5 as `Task: ..., State: <bins>;\\nAction: ` with the
  normalized state discretized (see `pi0_torch.processing.tokenization`), padded to `max_token_len`;
- actions (training only): `[horizon, action_dim_robot]`, converted, made relative to the (converted) state on the
  dims of `delta_action_mask`, normalized, zero-padded to `model_action_dim`.

It is a plain class (not a `transformers.ProcessorMixin`, whose image-processor/tokenizer plumbing does not fit a
robot policy's state/action statistics), registered with `AutoProcessor` for `PI0Config`:
`PI0Processor.from_pretrained(folder)` loads any folder written by `save_pretrained`, and
`AutoProcessor.from_pretrained(folder)` loads it from a model folder (one whose `config.json` is a `PI0Config`).

```python
>>> import numpy as np
>>> from pi0_torch import PI0Config
>>> from pi0_torch.processing.normalization import NormStats
>>> from pi0_torch.processing.tokenization import build_test_tokenizer
>>> seven = NormStats(mean=np.zeros(7), std=np.ones(7), q01=-np.ones(7), q99=np.ones(7))
>>> config = PI0Config.from_preset("pi0_small")
>>> processor = PI0Processor.from_config(config, build_test_tokenizer(), norm_stats={"state": seven, "actions": seven})
>>> inputs = processor(
...     images={"base_0_rgb": np.zeros((480, 640, 3), np.uint8)},
...     prompt="pick up the fork",
...     state=np.zeros(7),
... )
>>> for name, value in inputs.items():
...     print(name, tuple(value.shape), value.dtype)
pixel_values (1, 3, 3, 224, 224) torch.float32
image_masks (1, 3) torch.bool
input_ids (1, 48) torch.int64
attention_mask (1, 48) torch.bool
state (1, 32) torch.float32
>>> inputs["image_masks"].tolist()
[[True, False, False]]
>>> processor.postprocess_actions(np.zeros((50, 32))).shape  # model actions -> robot units
(50, 7)

```
"""

from __future__ import annotations

import inspect
import json
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pi0_torch.models.cameras import DEFAULT_CAMERA_NAMES
from pi0_torch.processing.images import check_float_range, missing_image, to_model_images, to_uint8_frame
from pi0_torch.processing.normalization import (
    DEFAULT_MIN_SCALE,
    NORM_MODES,
    MAX_STATISTIC,
    NormStats,
    apply_delta,
    load_openpi_norm_stats,
    normalize,
    save_openpi_norm_stats,
    unnormalize,
    warn_degenerate,
)
from pi0_torch.processing.robot_spaces import get_conversion
from pi0_torch.processing.tokenization import PromptTokenizer, TokenizerSource, load_tokenizer
from pi0_torch.utils import files
from pi0_torch.utils.optional import is_torch_tensor
from pi0_torch.utils.validation import (check_finite, check_float, check_pretrained_location, hub_errors, is_hub_id,
                                         read_json_file)

if TYPE_CHECKING:  # (imported where used: the processor runs without torch or transformers, `pi0_torch.deploy`)
    import torch
    from transformers import BatchFeature

    from pi0_torch.models.configuration_base import PI0BaseConfig
    from pi0_torch.models.configuration_pi0 import PI0Config

PROCESSOR_CONFIG_FILE = "processor_config.json"
NORM_STATS_FILE = "norm_stats.json"
OBSERVATION_KEYS = ("images", "prompt", "state", "actions")
# |state| in model space: a state from the training data's distribution lies within a few units of 0 (z-scores, or the
# q01..q99 span mapped to [-1, 1]); a thousand is no robot's reading (wrong units, a corrupted value, 1e30 or a uint64
# max), and the model returns unbounded actions for it (`state=[1e30, 0, 0]` gave actions of 1e30 before this bound)
MAX_NORMALIZED_STATE = 1_000.0
_HUB_KWARGS = ("trust_remote_code", "cache_dir", "force_download", "local_files_only", "revision", "token", "subfolder")


class PI0Processor:
    """Camera frames + instruction + robot state -> π0 / π0.5 model inputs; model actions -> robot actions.

    Args:
        tokenizer: a [`PromptTokenizer`], a SentencePiece `.model` path (PaliGemma's), a `SentencePieceProcessor`,
            a transformers tokenizer, or a folder holding one (see `pi0_torch.processing.tokenization.load_tokenizer`).
        camera_names: the model's cameras, in model order (`PI0Config.camera_names`).
        image_size: the model's square image size (224).
        max_token_len: prompt length in tokens (48 for π0, 200 for π0.5).
        pi05: True for π0.5's prompt (`Task: ..., State: ...;\\nAction: ` with the discretized state).
        state_in_prompt: π0.5 only: whether the discretized state is in the prompt (openpi's `discrete_state_input`;
            default True). openpi's `pi05_libero` was trained without it: its prompt is then π0's (`bos + text + "\\n"`).
        norm_mode: `"zscore"`, `"quantile"` or `"none"`; default quantile for π0.5, z-score for π0 (as openpi).
        norm_stats: `{"state": NormStats, "actions": NormStats}` at the robot's dims, or a path to openpi's
            `norm_stats.json` (file, folder or checkpoint step folder). Required unless `norm_mode="none"`. Stats
            longer than the robot's dims are cut to them (as openpi does).
        state_dim: the robot's state length; default: the length of the state stats.
        action_dim_robot: the robot's action length; default: the length of the action stats.
        model_action_dim: the model's padded action dim (`PI0Config.action_dim`, 32).
        action_horizon: steps per action chunk; when set, training `actions` must have this many steps.
        delta_action_mask: openpi's `DeltaActions` mask: action dim `i` is predicted relative to `state[i]` where
            `mask[i]` is True (may be shorter than the action dims; e.g. `[True] * 6 + [False]` for 6 joints and an
            absolute gripper). `postprocess_actions` then needs the raw state.
        min_norm_scale: floor of std / (q99 - q01) for near-constant dims (`pi0_torch.processing.normalization`); 0 = openpi.
        value_conversion: the robot's value conversion into the checkpoint's training space, `"aloha"` for openpi's
            ALOHA `adapt_to_pi` (`pi0_torch.processing.robot_spaces`); the norm stats are then those of the converted values.
        float_image_range: the value range of float frames: `(0, 1)` (default) or `(-1, 1)`.
        required_cameras: cameras every observation must have (error otherwise); by default any camera may be
            absent as long as one is present.
        default_prompt: used when an observation has no prompt (openpi's `InjectDefaultPrompt`).
        truncation: `"warn"` (truncate over-long prompts with a warning, openpi's behaviour) or `"error"`.
    """

    def __init__(
        self,
        tokenizer: TokenizerSource,
        *,
        camera_names: Sequence[str] = DEFAULT_CAMERA_NAMES,
        image_size: int = 224,
        max_token_len: int = 48,
        pi05: bool = False,
        state_in_prompt: bool | None = None,
        norm_mode: str | None = None,
        norm_stats: Mapping[str, NormStats] | str | Path | None = None,
        state_dim: int | None = None,
        action_dim_robot: int | None = None,
        model_action_dim: int = 32,
        action_horizon: int | None = None,
        delta_action_mask: Sequence[bool] | None = None,
        min_norm_scale: float = DEFAULT_MIN_SCALE,
        value_conversion: str | None = None,
        float_image_range: Sequence[float] = (0.0, 1.0),
        required_cameras: Sequence[str] | None = None,
        default_prompt: str | None = None,
        truncation: str = "warn",
    ) -> None:
        self.tokenizer = load_tokenizer(tokenizer)
        self.camera_names = [str(name) for name in camera_names]
        if not self.camera_names or len(set(self.camera_names)) != len(self.camera_names):
            raise ValueError(f"camera_names must be non-empty and unique, got {self.camera_names}")
        self.image_size = int(image_size)
        self.max_token_len = int(max_token_len)
        self.pi05 = bool(pi05)
        self.state_in_prompt = self.pi05 if state_in_prompt is None else bool(state_in_prompt)
        if self.state_in_prompt and not self.pi05:
            raise ValueError("state_in_prompt applies to π0.5 (pi05=True); π0 feeds the state to the action expert")
        self.norm_mode = norm_mode if norm_mode is not None else ("quantile" if self.pi05 else "zscore")
        if self.norm_mode not in NORM_MODES:
            raise ValueError(f"norm_mode must be one of {NORM_MODES}, got {self.norm_mode!r}")
        if isinstance(norm_stats, (str, Path)):
            norm_stats = load_openpi_norm_stats(norm_stats)
        self.norm_stats: dict[str, NormStats] | None = dict(norm_stats) if norm_stats is not None else None
        self.model_action_dim = int(model_action_dim)
        self.action_horizon = int(action_horizon) if action_horizon is not None else None
        self.min_norm_scale = float(min_norm_scale)
        self.float_image_range = check_float_range(float_image_range)
        self.default_prompt = default_prompt
        if truncation not in ("warn", "error"):
            raise ValueError(f"truncation must be 'warn' or 'error', got {truncation!r}")
        self.truncation = truncation
        if self.max_token_len < 1 or self.image_size < 1 or self.model_action_dim < 1:
            raise ValueError(f"max_token_len, image_size and model_action_dim must be positive, got {self.max_token_len}, "
                             f"{self.image_size}, {self.model_action_dim}")
        check_float("min_norm_scale", self.min_norm_scale, minimum=0.0, maximum=MAX_STATISTIC)  # (robot units)

        unknown = sorted(set(required_cameras or ()) - set(self.camera_names))
        if unknown:
            raise ValueError(f"required_cameras {unknown} are not among camera_names {self.camera_names}")
        self.required_cameras = list(required_cameras) if required_cameras is not None else None

        self._state_stats = self._action_stats = None
        if self.norm_mode != "none":
            if self.norm_stats is None:
                raise ValueError(f"norm_mode {self.norm_mode!r} needs norm_stats with 'state' and 'actions'")
            missing = [key for key in ("state", "actions") if key not in self.norm_stats]
            if missing:
                raise ValueError(f"norm_stats lacks {missing}; has {sorted(self.norm_stats)}")
            if self.norm_mode == "quantile" and not all(self.norm_stats[k].has_quantiles for k in ("state", "actions")):
                raise ValueError("norm_mode 'quantile' needs q01/q99 in the norm stats of both state and actions")
        self.state_dim = self._robot_dim(state_dim, "state", "state_dim")
        self.action_dim_robot = self._robot_dim(action_dim_robot, "actions", "action_dim_robot")
        if self.norm_mode != "none":
            self._state_stats = self.norm_stats["state"].truncated(self.state_dim)
            self._action_stats = self.norm_stats["actions"].truncated(self.action_dim_robot)
            warn_degenerate(self._state_stats, self.norm_mode, "state", self.min_norm_scale)
            warn_degenerate(self._action_stats, self.norm_mode, "actions", self.min_norm_scale)

        self.value_conversion = value_conversion
        self._conversion = get_conversion(value_conversion) if value_conversion is not None else None
        if self._conversion is not None and (self.state_dim, self.action_dim_robot) != (self._conversion.dim,) * 2:
            raise ValueError(
                f"value_conversion {value_conversion!r} applies to a state and actions of {self._conversion.dim} values, "
                f"got state_dim {self.state_dim} and action_dim_robot {self.action_dim_robot}"
            )

        self.delta_action_mask = None if delta_action_mask is None else self._check_delta_mask(delta_action_mask)

    def _check_delta_mask(self, mask: Any) -> list[bool]:
        """`delta_action_mask` as a list of bools, one per robot action dim: true / false entries (a string such as
        "110" read as three trues before), no more than the action dims, and no relative dim beyond the state's. A
        shorter mask leaves the remaining dims absolute (openpi's `DeltaActions` rule), with a warning naming them."""
        entries = list(mask) if isinstance(mask, (list, tuple, np.ndarray)) else None
        if entries is None or not all(type(m) in (bool, np.bool_) or (type(m) is int and m in (0, 1)) for m in entries):
            raise ValueError(f"delta_action_mask must be a list of true / false, one per robot action dim "
                             f"({self.action_dim_robot}), got {mask!r:.80}")
        if len(entries) > self.action_dim_robot:
            raise ValueError(f"delta_action_mask has {len(entries)} entries, more than the robot's "
                             f"{self.action_dim_robot} action dims")
        if len(entries) < self.action_dim_robot:
            absolute = list(range(len(entries), self.action_dim_robot))
            warnings.warn(f"delta_action_mask has {len(entries)} entries for {self.action_dim_robot} action dims: dims "
                          f"{absolute} are absolute (openpi's rule); give one entry per dim to say so", stacklevel=3)
            entries += [False] * len(absolute)
        relative = [index for index, entry in enumerate(entries) if entry]
        if relative and relative[-1] >= self.state_dim:
            raise ValueError(f"delta_action_mask makes action dim {relative[-1]} relative to the state, which has "
                             f"{self.state_dim} dims")
        return [bool(entry) for entry in entries]

    def _robot_dim(self, given: int | None, key: str, name: str) -> int:
        stats_dim = self.norm_stats[key].dim if self.norm_stats is not None and key in self.norm_stats else None
        if given is None:
            if stats_dim is None:
                raise ValueError(f"{name} is required when there are no '{key}' norm stats")
            given = stats_dim
        given = int(given)
        if not 1 <= given <= self.model_action_dim:
            raise ValueError(f"{name} must be in [1, model_action_dim={self.model_action_dim}], got {given}")
        if self.norm_mode != "none" and stats_dim is not None and stats_dim < given:
            raise ValueError(f"{name} is {given} but the '{key}' norm stats have only {stats_dim} dims")
        return given

    # ------------------------------------------------------------------------------------------- construction

    @classmethod
    def from_config(
        cls,
        config: PI0Config,
        tokenizer: TokenizerSource,
        norm_stats: Mapping[str, NormStats] | str | Path | None = None,
        **kwargs: Any,
    ) -> PI0Processor:
        """A processor matching `config` (cameras, image size, prompt length and format, action dim and horizon).

        `kwargs` are the remaining constructor arguments (`state_dim`, `delta_action_mask`, ...). Raises
        `ValueError` when the tokenizer's vocabulary is larger than the model's embedding table.
        """
        processor = cls(tokenizer, norm_stats=norm_stats, **{**config_settings(config), "pi05": config.pi05, **kwargs})
        processor._check_vocab_size(config)
        return processor

    def _check_vocab_size(self, config: PI0BaseConfig) -> None:
        """The prompt tokenizer's ids must all lie in the model's embedding table."""
        if self.tokenizer.vocab_size > config.vocab_size:
            raise ValueError(
                f"tokenizer has {self.tokenizer.vocab_size} tokens but the model's vocab_size is "
                f"{config.vocab_size}; ids past the embedding table would crash the model"
            )

    def to_dict(self) -> dict[str, Any]:
        """The settings saved in `processor_config.json` (everything but the tokenizer and the statistics)."""
        # No "processor_class" key: transformers resolves that name to its own, unrelated `PI0Processor` (model type
        # "pi0"); AutoProcessor finds this class through the folder's config.json (model type "pi0_torch") instead.
        return {
            "tokenizer_kind": self.tokenizer.kind,
            "camera_names": list(self.camera_names),
            "image_size": self.image_size,
            "max_token_len": self.max_token_len,
            "pi05": self.pi05,
            "state_in_prompt": self.state_in_prompt,
            "norm_mode": self.norm_mode,
            "state_dim": self.state_dim,
            "action_dim_robot": self.action_dim_robot,
            "model_action_dim": self.model_action_dim,
            "action_horizon": self.action_horizon,
            "delta_action_mask": self.delta_action_mask,
            "min_norm_scale": self.min_norm_scale,
            "value_conversion": self.value_conversion,
            "float_image_range": list(self.float_image_range),
            "required_cameras": self.required_cameras,
            "default_prompt": self.default_prompt,
            "truncation": self.truncation,
        }

    def save_pretrained(self, save_directory: str | Path, **unused: Any) -> list[str]:
        """Write `processor_config.json`, the tokenizer and (when set) openpi-layout `norm_stats.json`.

        Usually the model's folder, so `from_pretrained` of both finds everything. Returns the written paths.
        """
        directory = Path(save_directory)
        if directory.exists() and not directory.is_dir():
            raise ValueError(f"save_directory {directory} exists and is not a folder")
        directory.mkdir(parents=True, exist_ok=True)
        self.tokenizer.save(directory)
        written = [str(directory)]
        if self.norm_stats is not None:
            written.append(str(save_openpi_norm_stats(directory / NORM_STATS_FILE, self.norm_stats)))
        config_path = directory / PROCESSOR_CONFIG_FILE
        files.write_text_atomically(config_path, json.dumps(self.to_dict(), indent=2, ensure_ascii=False) + "\n")
        written.append(str(config_path))
        return written

    @classmethod
    def from_pretrained(cls, pretrained_path: str | Path, **overrides: Any) -> PI0Processor:
        """Load what [`save_pretrained`] wrote in a local folder, or a hub repository `namespace/name` holding one;
        `overrides` replace saved settings.

        The norm stats come from `norm_stats.json` in the folder (unless `norm_stats=` is given). For a hub id only
        the processor's files are downloaded; `cache_dir`, `revision`, `token`, `force_download` and
        `local_files_only` go to `huggingface_hub.snapshot_download`. A path that is neither a local folder nor a hub
        id is refused at once (see `pi0_torch.utils.validation.is_hub_id`).
        """
        hub_options = {name: overrides.pop(name) for name in list(overrides) if name in _HUB_KWARGS or name.startswith("_")}
        check_pretrained_location(pretrained_path, PROCESSOR_CONFIG_FILE, "processor")
        directory = Path(pretrained_path)
        if is_hub_id(pretrained_path):
            directory = _download_processor(str(pretrained_path), hub_options)
        config_path = directory / PROCESSOR_CONFIG_FILE
        settings = _read_processor_config(config_path, processor_settings(cls))
        kind = settings.pop("tokenizer_kind")
        tokenizer = overrides.pop("tokenizer", None) or PromptTokenizer.load(directory, kind)
        if "norm_stats" not in overrides and (directory / NORM_STATS_FILE).is_file():
            overrides["norm_stats"] = load_openpi_norm_stats(directory / NORM_STATS_FILE)
        settings.update(overrides)
        return cls(tokenizer, **settings)

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in self.to_dict().items())
        return f"{type(self).__name__}({fields}, vocab_size={self.tokenizer.vocab_size})"

    # ------------------------------------------------------------------------------------------- inputs

    def __call__(
        self,
        observations: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None,
        *,
        images: Mapping[str, Any] | None = None,
        prompt: str | Sequence[str] | None = None,
        state: Any = None,
        actions: Any = None,
        return_tensors: str = "pt",
    ) -> BatchFeature:
        """Model inputs for one observation or a batch.

        Three ways to call it:

        - one observation: `processor(images={camera: frame}, prompt="...", state=[state_dim])`;
        - a batch of arrays: `state` `[B, state_dim]` (a 2-D state means a batch), each `images[camera]` a `[B, ...]`
          array/tensor or a list of B frames (None for an absent frame), `prompt` a list of B strings (or one string
          for all), `actions` `[B, horizon, action_dim_robot]`;
        - observation dicts: `processor(obs)` or `processor([obs, ...])` with keys `images`, `prompt`, `state` and
          optionally `actions`, each as in the one-observation form.

        `actions` (training) are given for all observations or none. Returns a `BatchFeature` (`.to(device)` works)
        with `pixel_values` float32 `[B, C, 3, H, W]`, `image_masks` bool `[B, C]`, `input_ids` int64 `[B, L]`,
        `attention_mask` bool `[B, L]`, `state` float32 `[B, model_action_dim]` and, with actions, `actions`
        float32 `[B, horizon, model_action_dim]`; torch tensors, or numpy arrays with `return_tensors="np"`.
        Bad input raises `ValueError` naming the field, what was expected and what came.
        """
        if return_tensors not in ("pt", "np"):
            raise ValueError(f"return_tensors must be 'pt' or 'np', got {return_tensors!r}")
        if observations is not None:
            if any(v is not None for v in (images, prompt, state, actions)):
                raise ValueError("pass either observation dicts or images=/prompt=/state=/actions=, not both")
            samples = self._split_observations(observations)
        else:
            samples = self._split_arrays(images, prompt, state, actions)
        encoded = [self._encode(sample, where) for where, sample in samples]
        with_actions = {"actions" in e for e in encoded}
        if len(with_actions) > 1:
            raise ValueError("actions: given for some observations of the batch but not for others")
        batch = {key: np.stack([e[key] for e in encoded]) for key in encoded[0]}
        from transformers import BatchFeature

        return BatchFeature(batch, tensor_type=return_tensors)

    def _split_observations(self, observations: Any) -> list[tuple[str, dict[str, Any]]]:
        if isinstance(observations, Mapping):
            items, prefix = [observations], lambda i: "observation"
        elif isinstance(observations, Sequence) and not isinstance(observations, str):
            items, prefix = list(observations), lambda i: f"observations[{i}]"
            if not items:
                raise ValueError("observations: got an empty list")
        else:
            raise ValueError(f"observations: expected a dict or a list of dicts, got {type(observations).__name__}")
        samples = []
        for i, item in enumerate(items):
            if not isinstance(item, Mapping):
                raise ValueError(
                    f"{prefix(i)}: expected a dict with keys {OBSERVATION_KEYS}, got {type(item).__name__}"
                )
            unknown = sorted(set(item) - set(OBSERVATION_KEYS))
            if unknown:
                raise ValueError(f"{prefix(i)}: unknown keys {unknown}; expected {OBSERVATION_KEYS}")
            samples.append((prefix(i) + ".", dict(item)))
        return samples

    def _split_arrays(self, images: Any, prompt: Any, state: Any, actions: Any) -> list[tuple[str, dict[str, Any]]]:
        if state is None:
            raise ValueError(
                f"state: required, a vector of {self.state_dim} values (or [B, {self.state_dim}] for a batch)"
            )
        state_array = _as_numeric(state, "state")
        if state_array.ndim == 1:
            return [("", {"images": images, "prompt": prompt, "state": state_array, "actions": actions})]
        if state_array.ndim != 2:
            raise ValueError(
                f"state: expected [{self.state_dim}] or [B, {self.state_dim}], got shape {state_array.shape}"
            )
        size = state_array.shape[0]
        if size == 0:
            raise ValueError("state: the batch is empty")

        def pick(value: Any, name: str, i: int) -> Any:
            if value is None:
                return None
            if isinstance(value, (list, tuple)) or (hasattr(value, "shape") and not isinstance(value, str)):
                if len(value) != size:
                    one_frame = name.startswith("images") and len(getattr(value, "shape", ())) == 3
                    what = f"one frame {tuple(value.shape)}" if one_frame else f"a batch of {len(value)}"
                    raise ValueError(
                        f"{name}: {what}, but state {list(state_array.shape)} is a batch of {size} (2-D: one row per "
                        f"observation); pass the state as a vector [{self.state_dim}] for one observation, or a batch "
                        f"of {size} for each input"
                    )
                return value[i]
            raise ValueError(
                f"{name}: expected a batch (list or array) of {size} for a batched state, got {type(value).__name__}"
            )

        if images is not None and not isinstance(images, Mapping):
            raise ValueError(f"images: expected a dict {{camera name: frames}}, got {type(images).__name__}")
        if isinstance(prompt, str) or prompt is None:
            prompts = [prompt] * size
        else:
            prompts = [pick(prompt, "prompt", i) for i in range(size)]
        samples = []
        for i in range(size):
            sample_images = {name: pick(value, f"images[{name!r}]", i) for name, value in (images or {}).items()}
            sample = {"images": sample_images, "prompt": prompts[i], "state": state_array[i]}
            samples.append((f"[{i}] ", {**sample, "actions": pick(actions, "actions", i)}))
        return samples

    def _encode(self, sample: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
        """One observation -> unbatched model arrays; `where` prefixes error messages (e.g. `"[3] "`)."""
        state, normalized_state, input_ids, attention_mask = self.encode_state_and_prompt(sample, where)
        pixel_values, image_masks = self._encode_images(sample.get("images"), where)
        encoded = {
            "pixel_values": pixel_values,
            "image_masks": image_masks,
            "input_ids": input_ids,
            "attention_mask": attention_mask,
            "state": self._pad(normalized_state),
        }
        if sample.get("actions") is not None:
            encoded["actions"] = self._encode_actions(sample["actions"], state, f"{where}actions")
        return encoded

    def encode_state_and_prompt(
        self, sample: Mapping[str, Any], where: str = ""
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One observation's state and prompt, checked: the state in the checkpoint's space (`value_conversion`
        applied, not normalized) `[state_dim]`, normalized `[state_dim]`, and the prompt's `input_ids` int64 /
        `attention_mask` bool `[max_token_len]` (π0.5: with the normalized state in it). `where` prefixes errors."""
        state = self._model_space_state(self._check_vector(sample.get("state"), where + "state", self.state_dim))
        normalized_state = self._normalized_state(state, where)
        prompt = self._prompt(sample, where)
        try:
            input_ids, attention_mask = self.tokenizer.tokenize(
                prompt, self.max_token_len, normalized_state if self.state_in_prompt else None, self.truncation
            )
        except ValueError as error:
            raise ValueError(f"{where}{error}") from None
        return state, normalized_state, input_ids, attention_mask

    @property
    def state_stats(self) -> NormStats | None:
        """The state's statistics at the robot's dims (None with `norm_mode="none"`)."""
        return self._state_stats

    @property
    def action_stats(self) -> NormStats | None:
        """The actions' statistics at the robot's dims (None with `norm_mode="none"`)."""
        return self._action_stats

    def _prompt(self, sample: Mapping[str, Any], where: str) -> str:
        """The observation's prompt, or the processor's `default_prompt` when it has none."""
        prompt = sample.get("prompt")
        if prompt is None:
            if self.default_prompt is None:
                raise ValueError(f"{where}prompt: required (a task instruction string); no default_prompt is set")
            prompt = self.default_prompt
        return prompt

    def _encode_images(self, images: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
        present, named_frames = self._shown_frames(images, where)
        shown = dict(zip(present, to_model_images(named_frames, self.image_size, self.float_image_range)))
        frames = [shown[name] if name in shown else missing_image(self.image_size) for name in self.camera_names]
        masks = [name in shown for name in self.camera_names]
        return np.stack(frames), np.asarray(masks, bool)  # [C, 3, H, W], [C]

    def encode_uint8_images(self, images: Any, where: str = "") -> tuple[np.ndarray, np.ndarray]:
        """One observation's frames `{camera name: frame}`, checked as for the model, as an exported graph takes them:
        uint8 `[C, H, W, 3]` at the model's size (zeros for an absent camera) and the masks bool `[C]`
        (`pi0_torch.processing.images.to_uint8_frame`: uint8 frames resized exactly as for the model)."""
        present, named_frames = self._shown_frames(images, where)
        shown = {name: to_uint8_frame(frame, self.image_size, self.float_image_range, label)
                 for name, (label, frame) in zip(present, named_frames)}
        blank = np.zeros((self.image_size, self.image_size, 3), np.uint8)
        return (np.stack([shown.get(name, blank) for name in self.camera_names]),
                np.asarray([name in shown for name in self.camera_names], bool))

    def _shown_frames(self, images: Any, where: str) -> tuple[list[str], list[tuple[str, Any]]]:
        """The cameras an observation shows, in model order, and their `(error name, frame)`; refuses unknown cameras,
        missing required ones, and no camera at all."""
        if images is None:
            images = {}
        if not isinstance(images, Mapping):
            raise ValueError(f"{where}images: expected a dict {{camera name: frame}}, got {type(images).__name__}")
        unknown = sorted(set(images) - set(self.camera_names))
        if unknown:
            raise ValueError(
                f"{where}images: unknown camera names {unknown}; this model's cameras are {self.camera_names}"
            )
        present = [name for name in self.camera_names if images.get(name) is not None]
        missing_required = [name for name in self.required_cameras or () if name not in present]
        if missing_required:
            raise ValueError(f"{where}images: required cameras {missing_required} are missing; got {present}")
        if not present:
            raise ValueError(f"{where}images: no camera frame given; expected at least one of {self.camera_names}")
        return present, [(f"{where}images[{name!r}]", images[name]) for name in present]

    def encode_actions(self, actions: Any, state: Any, name: str = "actions") -> np.ndarray:
        """One chunk of robot actions `[horizon, action_dim_robot]` -> model space `[horizon, model_action_dim]`
        (float32): converted, relative to the robot's raw `state` on the delta dims, normalized, padded. Errors name
        the field `name` (e.g. a policy's `previous_actions`)."""
        state = self._model_space_state(self._check_vector(state, "state", self.state_dim))
        return self._encode_actions(actions, state, name)

    def _encode_actions(self, actions: Any, state: np.ndarray, name: str) -> np.ndarray:
        """Robot actions `[horizon, action_dim_robot]` -> model targets; `state` is already in model space."""
        values = _as_numeric(actions, name)
        horizon = self.action_horizon if self.action_horizon is not None else "horizon"
        if values.ndim != 2 or values.shape[1] != self.action_dim_robot or (
            self.action_horizon is not None and values.shape[0] != self.action_horizon
        ):
            raise ValueError(f"{name}: expected shape [{horizon}, {self.action_dim_robot}], got {values.shape}")
        check_finite(name, values)
        if self._conversion is not None:
            values = self._conversion.actions_to_model(values)
        if self.delta_action_mask is not None:
            values = apply_delta(values, state, self.delta_action_mask)
        normalized = self._normalize(values, self._action_stats)  # (float64: an overflow is named, not inf)
        check_finite(f"{name} (normalized)", normalized)
        return self._pad(normalized)

    def _check_vector(self, value: Any, name: str, dim: int) -> np.ndarray:
        if value is None:
            raise ValueError(f"{name}: required, a vector of {dim} values")
        array = _as_numeric(value, name)
        if array.shape != (dim,):
            raise ValueError(f"{name}: expected shape [{dim}], got {list(array.shape)}")
        check_finite(name, array)
        return array

    def _model_space_state(self, state: np.ndarray) -> np.ndarray:
        """The robot's state `[..., state_dim]` in the checkpoint's space (unchanged without a value conversion)."""
        return state if self._conversion is None else self._conversion.state_to_model(state)

    def _normalized_state(self, state: np.ndarray, where: str) -> np.ndarray:
        """The state in model space, refused (naming it) unless finite and within `MAX_NORMALIZED_STATE` of 0."""
        normalized = self._normalize(state, self._state_stats)
        check_finite(f"{where}state (normalized)", normalized)
        if self._state_stats is not None and normalized.size and np.abs(normalized).max() > MAX_NORMALIZED_STATE:
            dims = [int(i) for i in np.flatnonzero(np.abs(normalized) > MAX_NORMALIZED_STATE)[:8]]
            raise ValueError(
                f"{where}state: dims {dims} normalize to {normalized[dims[0]]:.3g} ({state[dims[0]]:.6g} raw), beyond "
                f"±{MAX_NORMALIZED_STATE:g} in the model's normalized space, where a state of the training data lies "
                f"within a few units of 0 ({self.norm_mode}); check the state's units and order against the norm stats "
                f"(a dim that never moved in the training data has a scale floored at min_norm_scale={self.min_norm_scale:g})"
            )
        return normalized

    def _normalize(self, values: np.ndarray, stats: NormStats | None) -> np.ndarray:
        if stats is None:
            return values
        return normalize(values, stats, self.norm_mode, self.min_norm_scale)

    def _pad(self, values: np.ndarray) -> np.ndarray:
        padded = np.zeros((*values.shape[:-1], self.model_action_dim), np.float32)
        padded[..., : values.shape[-1]] = values
        return padded

    # ------------------------------------------------------------------------------------------- outputs

    def postprocess_actions(self, actions: Any, state: Any = None) -> np.ndarray | torch.Tensor:
        """Model-space actions `[horizon, D]` or `[B, horizon, D]` (D = `model_action_dim` or the robot's dims)
        -> robot actions `[..., horizon, action_dim_robot]` in robot units, float32.

        Keeps the robot's dims, unnormalizes them, with a `delta_action_mask` adds back the robot's raw (unnormalized)
        `state` (`[state_dim]`, or `[B, state_dim]` for a batch) like openpi's `AbsoluteActions`, and with a
        `value_conversion` converts the result to the robot's units. numpy in -> numpy out; torch in -> torch out
        on the same device.
        """
        is_torch = is_torch_tensor(actions)
        if not (is_torch or isinstance(actions, np.ndarray)):
            raise ValueError(f"actions: expected a numpy array or torch tensor, got {type(actions).__name__}")
        if actions.ndim not in (2, 3) or actions.shape[-1] < self.action_dim_robot:
            raise ValueError(
                f"actions: expected [horizon, D] or [B, horizon, D] with D >= action_dim_robot="
                f"{self.action_dim_robot}, got shape {tuple(actions.shape)}"
            )
        if not (actions.is_floating_point() if is_torch else np.issubdtype(actions.dtype, np.floating)):
            raise ValueError(f"actions: expected a float array, got dtype {actions.dtype}")
        robot = actions[..., : self.action_dim_robot]
        robot = robot.float() if is_torch else robot.astype(np.float32)
        if self._action_stats is not None:
            robot = unnormalize(robot, self._action_stats, self.norm_mode, self.min_norm_scale)
        if self.delta_action_mask is not None:
            if state is None:
                raise ValueError("state: required to undo delta actions (this processor has a delta_action_mask)")
            raw_state = _as_numeric(state, "state")
            expected = (*actions.shape[:-2], self.state_dim)
            if raw_state.shape != expected:
                raise ValueError(
                    f"state: expected shape {list(expected)} for actions of shape {tuple(actions.shape)}, "
                    f"got {list(raw_state.shape)}"
                )
            state_values = self._model_space_state(raw_state).astype(np.float32)
            if is_torch:
                import torch

                state_values = torch.as_tensor(state_values, device=robot.device)
            robot = apply_delta(robot, state_values, self.delta_action_mask, inverse=True)
        if self._conversion is not None:
            converted = self._conversion.actions_to_robot(robot.cpu().numpy() if is_torch else robot)
            if is_torch:
                import torch

                converted = torch.as_tensor(converted, device=robot.device)
            robot = converted
        return robot.float() if is_torch else robot.astype(np.float32)


def config_settings(config: PI0BaseConfig) -> dict[str, Any]:
    """The processor settings a model config fixes, for every family member: its cameras, image size, prompt length
    and the shape of its action chunks."""
    return dict(camera_names=config.camera_names, image_size=config.image_size, max_token_len=config.max_token_len,
                model_action_dim=config.action_dim, action_horizon=config.action_horizon)


def processor_settings(processor_class: type[PI0Processor]) -> tuple[str, ...]:
    """The settings a processor class saves in `processor_config.json`: its constructors' named arguments, along the
    class hierarchy (a subclass passes the base's settings on through `**settings`)."""
    names: dict[str, None] = {}
    for klass in processor_class.__mro__:
        if isinstance(klass, type) and issubclass(klass, PI0Processor) and "__init__" in vars(klass):
            for name, parameter in inspect.signature(klass.__init__).parameters.items():
                if name not in ("self", "tokenizer") and parameter.kind not in (parameter.VAR_KEYWORD, parameter.VAR_POSITIONAL):
                    names[name] = None
    return tuple(names)


PROCESSOR_SETTINGS = processor_settings(PI0Processor)


def _read_processor_config(path: Path, known: Sequence[str] = PROCESSOR_SETTINGS) -> dict[str, Any]:
    """`processor_config.json` as a dict of `known` settings plus `tokenizer_kind`; `ValueError` naming the file."""
    settings = read_json_file(path)
    if not isinstance(settings, dict):
        raise ValueError(f"{path} must hold a JSON object of settings, got a JSON {type(settings).__name__}")
    if not isinstance(settings.get("tokenizer_kind"), str):
        raise ValueError(f"{path} lacks 'tokenizer_kind' ('sentencepiece' or 'transformers')")
    unknown = sorted(set(settings) - set(known) - {"tokenizer_kind"})
    if unknown:
        raise ValueError(f"{path} has unknown settings {unknown}; known settings: {', '.join(known)}")
    return settings


def _download_processor(repo_id: str, hub_options: dict[str, Any]) -> Path:
    """The processor files of hub repository `repo_id` (config, norm stats, tokenizer), in the local hub cache."""
    from huggingface_hub import snapshot_download

    options = {name: hub_options[name] for name in ("cache_dir", "force_download", "local_files_only", "revision", "token")
               if hub_options.get(name) is not None}
    patterns = [PROCESSOR_CONFIG_FILE, NORM_STATS_FILE, "tokenizer*", "special_tokens_map.json", "added_tokens.json"]
    with hub_errors(repo_id, "processor"):
        return Path(snapshot_download(repo_id, allow_patterns=patterns, **options))


def _as_numeric(value: Any, name: str) -> np.ndarray:
    """A float64 numpy copy of a numeric array-like (numpy, torch, lists); `ValueError` for other dtypes."""
    if is_torch_tensor(value):
        import torch

        if value.dtype == torch.bool or value.is_complex():
            raise ValueError(f"{name}: expected real numbers, got dtype {value.dtype}")
        return value.detach().to("cpu", torch.float64).numpy()
    try:
        array = np.asarray(value)
    except (ValueError, TypeError) as error:
        raise ValueError(f"{name}: expected an array of numbers, got {type(value).__name__} ({error})") from None
    real = np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)
    if array.dtype == np.bool_ or not real:
        raise ValueError(f"{name}: expected real numbers, got dtype {array.dtype}")
    return array.astype(np.float64)


