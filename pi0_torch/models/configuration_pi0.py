"""Configuration of the π0 / π0.5 vision-language-action model."""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import logging
from collections.abc import Sequence
from typing import Any

from transformers import PretrainedConfig

from pi0_torch.models.configuration_base import (
    PALIGEMMA_VOCAB_SIZE,
    SIZE_LIMITS,
    PI0BaseConfig,
    camera_list,
    vision_parameters,
)
from pi0_torch.models.cameras import DEFAULT_CAMERA_NAMES
from pi0_torch.utils.validation import check_float, check_int

logger = logging.getLogger(__name__)

MAX_ACTION_DIM = SIZE_LIMITS["action_dim"]
MAX_ACTION_HORIZON = SIZE_LIMITS["action_horizon"]
MAX_INFERENCE_STEPS = SIZE_LIMITS["num_inference_steps"]

# Sizes of the vision tower, the VLM Gemma (expert 0) and the action expert (expert 1) for each preset.
# "pi0"/"pi05" are the released sizes (SigLIP So400m/14, Gemma 2B, Gemma 300M); "small" matches the openpi test
# fixtures (deliberately non-square so a transposed weight shows); "medium" is the benchmark size of issue 7.
_SIZES: dict[str, dict[str, Any]] = {
    "full": dict(
        vision_hidden_size=1152, vision_intermediate_size=4304, vision_num_layers=27, vision_num_heads=16,
        vlm_hidden_size=2048, vlm_intermediate_size=16_384,
        expert_hidden_size=1024, expert_intermediate_size=4096,
        num_hidden_layers=18, num_attention_heads=8, num_key_value_heads=1, head_dim=256,
        vocab_size=PALIGEMMA_VOCAB_SIZE,
    ),
    "medium": dict(
        vision_hidden_size=384, vision_intermediate_size=1536, vision_num_layers=6, vision_num_heads=6,
        vlm_hidden_size=512, vlm_intermediate_size=2048,
        expert_hidden_size=256, expert_intermediate_size=1024,
        num_hidden_layers=6, num_attention_heads=8, num_key_value_heads=1, head_dim=64,
        vocab_size=16_384,
    ),
    "small": dict(
        vision_hidden_size=40, vision_intermediate_size=80, vision_num_layers=2, vision_num_heads=4,
        vlm_hidden_size=64, vlm_intermediate_size=128,
        expert_hidden_size=48, expert_intermediate_size=96,
        num_hidden_layers=3, num_attention_heads=4, num_key_value_heads=1, head_dim=32,
        vocab_size=1024,
    ),
}


class PI0Config(PI0BaseConfig):
    """Configuration of [`PI0ForActionGeneration`].

    Holds the dimensions of the SigLIP vision tower, the VLM Gemma ("expert 0", width `vlm_hidden_size`) and the
    action expert ("expert 1", width `expert_hidden_size`), which share depth, head count and head size, plus the
    action/flow-matching settings. `pi05=True` selects π0.5 (adaRMS time conditioning in the action expert, no state
    token). `rtc_max_delay` records the largest inference delay (in action steps) the model was trained to take
    committed actions for (training-time real-time chunking, `pi0-torch train --rtc-max-delay`); 0 = not trained so. Use the presets for the released sizes:

    ```python
    >>> from pi0_torch import PI0Config
    >>> PI0Config.pi0().vlm_hidden_size, PI0Config.pi05().max_token_len
    (2048, 200)
    >>> PI0Config.from_preset("pi05_small").expert_hidden_size
    48

    ```
    """

    model_type = "pi0_torch"
    own_sizes = ("vlm_hidden_size", "vlm_intermediate_size", "expert_hidden_size", "expert_intermediate_size",
                 "num_inference_steps")

    def __init__(
        self,
        pi05: bool = False,
        # SigLIP vision tower
        image_size: int = 224,
        patch_size: int = 14,
        vision_hidden_size: int = 1152,
        vision_intermediate_size: int = 4304,
        vision_num_layers: int = 27,
        vision_num_heads: int = 16,
        # joint two-expert Gemma
        vlm_hidden_size: int = 2048,
        vlm_intermediate_size: int = 16_384,
        expert_hidden_size: int = 1024,
        expert_intermediate_size: int = 4096,
        num_hidden_layers: int = 18,
        num_attention_heads: int = 8,
        num_key_value_heads: int = 1,
        head_dim: int = 256,
        vocab_size: int = PALIGEMMA_VOCAB_SIZE,
        rms_norm_eps: float = 1e-6,
        rope_theta: float = 10_000.0,
        # actions and flow matching
        action_dim: int = 32,
        action_horizon: int = 50,
        max_token_len: int | None = None,
        num_inference_steps: int = 10,
        time_beta_alpha: float = 1.5,
        time_beta_beta: float = 1.0,
        time_scale: float = 0.999,
        time_offset: float = 0.001,
        time_min_period: float = 4e-3,
        time_max_period: float = 4.0,
        camera_names: Sequence[str] = DEFAULT_CAMERA_NAMES,
        rtc_max_delay: int = 0,
        **kwargs: Any,
    ) -> None:
        if pi05 not in (True, False):  # (0 and 1 pass; the string "false" would be truthy)
            raise ValueError(f"pi05 must be true or false, got {pi05!r}")
        self.pi05 = bool(pi05)
        self.image_size = image_size
        self.patch_size = patch_size
        self.vision_hidden_size = vision_hidden_size
        self.vision_intermediate_size = vision_intermediate_size
        self.vision_num_layers = vision_num_layers
        self.vision_num_heads = vision_num_heads
        self.vlm_hidden_size = vlm_hidden_size
        self.vlm_intermediate_size = vlm_intermediate_size
        self.expert_hidden_size = expert_hidden_size
        self.expert_intermediate_size = expert_intermediate_size
        self.num_hidden_layers = num_hidden_layers
        self.num_attention_heads = num_attention_heads
        self.num_key_value_heads = num_key_value_heads
        self.head_dim = head_dim
        self.vocab_size = vocab_size
        self.rms_norm_eps = rms_norm_eps
        self.rope_theta = rope_theta
        self.action_dim = action_dim
        self.action_horizon = action_horizon
        self.max_token_len = max_token_len if max_token_len is not None else (200 if self.pi05 else 48)
        self.num_inference_steps = num_inference_steps
        self.time_beta_alpha = time_beta_alpha
        self.time_beta_beta = time_beta_beta
        self.time_scale = time_scale
        self.time_offset = time_offset
        self.time_min_period = time_min_period
        self.time_max_period = time_max_period
        self.camera_names = camera_list(camera_names)
        self.rtc_max_delay = rtc_max_delay
        unknown = sorted(set(kwargs) - _TRANSFORMERS_KEYS)
        if unknown:  # transformers keeps them as attributes; nothing in pi0-torch reads them
            logger.warning("PI0Config: ignoring unknown settings %s%s", unknown, _suggestions(unknown))
        super().__init__(**kwargs)

    def _check(self) -> None:
        """The shared checks ([`PI0BaseConfig._check`]), then the flow-matching times, the action expert's width and
        the training-time real-time chunking delay."""
        super()._check()
        for name in ("time_beta_alpha", "time_beta_beta", "time_scale", "time_min_period", "time_max_period"):
            check_float(name, getattr(self, name), minimum=0.0, exclusive_minimum=True)
        check_float("time_offset", self.time_offset, minimum=0.0)
        if self.time_scale + self.time_offset > 1.0 + 1e-6:
            raise ValueError(f"time_scale + time_offset must be <= 1 (flow times lie in (0, 1]), got "
                             f"{self.time_scale} + {self.time_offset}")
        if self.expert_hidden_size % 2:
            raise ValueError(f"expert_hidden_size must be even for the sin/cos time embedding, got {self.expert_hidden_size}")
        check_int("rtc_max_delay", self.rtc_max_delay, minimum=0, maximum=self.action_horizon - 1)

    def estimated_parameters(self) -> int:
        """The model's parameter count from its sizes (within a fraction of a percent: norms and biases are left
        out), for a memory estimate before a model is built.

        ```python
        >>> round(PI0Config.pi0().estimated_parameters() / 3_238_048_528, 3)  # the released π0 and π0.5
        1.0
        >>> round(PI0Config.pi05().estimated_parameters() / 3_353_433_872, 3)
        1.0

        ```
        """
        vision = vision_parameters(self.image_size, self.patch_size, self.vision_hidden_size,
                                   self.vision_intermediate_size, self.vision_num_layers)
        attention = self.num_attention_heads * self.head_dim
        key_value = 2 * self.num_key_value_heads * self.head_dim

        def expert(width: int, intermediate: int) -> int:
            return width * (attention + key_value) + attention * width + 3 * width * intermediate

        per_layer = expert(self.vlm_hidden_size, self.vlm_intermediate_size) + expert(
            self.expert_hidden_size, self.expert_intermediate_size)
        heads = 4 * self.action_dim * self.expert_hidden_size + 3 * self.expert_hidden_size**2
        if self.pi05:  # adaRMS: scale, shift and gate of both norms of every expert layer and of its final norm
            per_layer += 6 * self.expert_hidden_size**2
            heads += 3 * self.expert_hidden_size**2
        return (vision + self.vision_hidden_size * self.vlm_hidden_size + self.vocab_size * self.vlm_hidden_size
                + self.num_hidden_layers * per_layer + heads)

    @property
    def suffix_len(self) -> int:
        """Tokens in the suffix: (π0 only) one state token, then one token per action step."""
        return self.action_horizon + (0 if self.pi05 else 1)

    @classmethod
    def from_preset(cls, name: str, **overrides: Any) -> PI0Config:
        """Build a preset: `pi0`, `pi05` (released sizes), `pi0_medium`, `pi05_medium`, `pi0_small`, `pi05_small`.

        `overrides` replace settings of the preset; a name that is not a setting is refused (a typo would otherwise
        be ignored silently).
        """
        variant, _, size = name.partition("_")
        if variant not in ("pi0", "pi05") or (size or "full") not in _SIZES:
            raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(preset_names())}")
        if "pi05" in overrides:
            raise ValueError(f"pi05 is set by the preset name ({variant}_... or the other variant), not by an override")
        unknown = sorted(set(overrides) - set(CONFIG_FIELDS))
        if unknown:
            raise ValueError(f"unknown config settings {unknown}"
                             f"{_suggestions(unknown) or '; settings: ' + ', '.join(CONFIG_FIELDS)}")
        return cls(pi05=variant == "pi05", **{**_SIZES[size or "full"], **overrides})

    @classmethod
    def pi0(cls, **overrides: Any) -> PI0Config:
        """π0 at the released size (3,238,048,528 parameters)."""
        return cls.from_preset("pi0", **overrides)

    @classmethod
    def pi05(cls, **overrides: Any) -> PI0Config:
        """π0.5 at the released size (3,353,433,872 parameters)."""
        return cls.from_preset("pi05", **overrides)


CONFIG_FIELDS: tuple[str, ...] = tuple(
    name for name, parameter in inspect.signature(PI0Config.__init__).parameters.items()
    if name != "self" and parameter.kind is not inspect.Parameter.VAR_KEYWORD
)
# What transformers itself writes into config.json or passes to a config besides the model's own settings.
_TRANSFORMERS_KEYS = {field.name for field in dataclasses.fields(PretrainedConfig)} | {
    "model_type", "transformers_version", "name_or_path", "_name_or_path", "_commit_hash", "torch_dtype",
    "attn_implementation", "experts_implementation", "output_attentions", "num_labels", "auto_map", "use_cache",
    "quantization_config",
}


def _suggestions(names: Sequence[str]) -> str:
    """` (did you mean 'action_horizon'?)` for names close to a setting, else an empty string."""
    close = {name: difflib.get_close_matches(name, CONFIG_FIELDS, n=1) for name in names}
    hints = [f"{match[0]!r} for {name!r}" for name, match in close.items() if match]
    return f" (did you mean {', '.join(hints)}?)" if hints else ""


def preset_names() -> list[str]:
    """Names accepted by [`PI0Config.from_preset`]."""
    return [f"{variant}{'' if size == 'full' else '_' + size}" for variant in ("pi0", "pi05") for size in _SIZES]
