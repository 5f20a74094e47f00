"""What every configuration of the π0 family shares: [`PI0BaseConfig`], the base of [`PI0Config`] (π0 / π0.5) and
[`PI0FastConfig`] (π0-FAST).

Both models read images with the same SigLIP tower into a Gemma with the same attention geometry, predict chunks of
`action_horizon` actions of `action_dim` values, and take a prompt of `max_token_len` tokens and one image per
camera slot. The base holds the checks of those settings, the size of every setting (`SIZE_LIMITS`), the token
counts they imply, and the loading of a `config.json`; each member adds its own settings and their checks.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from transformers import PretrainedConfig

from pi0_torch.models import auto_registration
from pi0_torch.utils.limits import SIZE_LIMITS
from pi0_torch.utils.validation import check_float, check_int, check_pretrained_location, hub_errors, read_json_file

PALIGEMMA_VOCAB_SIZE = 257_152

# The sizes and counts every member has: each a positive integer within `SIZE_LIMITS`.
SHARED_SIZES = (
    "image_size", "patch_size", "vision_hidden_size", "vision_intermediate_size", "vision_num_layers", "vision_num_heads",
    "num_hidden_layers", "num_attention_heads", "num_key_value_heads", "head_dim", "vocab_size", "action_dim",
    "action_horizon", "max_token_len",
)


class PI0BaseConfig(PretrainedConfig):
    """The settings every π0-family config holds and how they are checked, loaded and counted.

    A member's `__init__` sets its own settings (every one of them: its signature is its schema), then calls this
    one with the rest, transformers' settings: it checks a `dtype` among them, hands them to `PretrainedConfig`,
    checks every setting ([`_check`]) and lets `AutoModel` know the member's model class
    (`pi0_torch.models.auto_registration`).
    """

    own_sizes: ClassVar[tuple[str, ...]] = ()  # the member's sizes and counts besides `SHARED_SIZES`

    def __init__(self, **kwargs: Any) -> None:
        check_dtype_setting(kwargs)
        super().__init__(**kwargs)
        self._check()
        auto_registration.register_models()  # AutoModel maps a config to its model class once one exists

    def _check(self) -> None:
        """Types and ranges of the shared settings (presets, `from_pretrained`, `from_dict` and overrides all come
        here); a member extends it with its own."""
        for name in (*SHARED_SIZES, *self.own_sizes):
            check_int(name, getattr(self, name), minimum=1, maximum=SIZE_LIMITS[name])
        for name in ("rms_norm_eps", "rope_theta"):
            check_float(name, getattr(self, name), minimum=0.0, exclusive_minimum=True)
        if self.vision_hidden_size % self.vision_num_heads:
            raise ValueError(f"vision_hidden_size ({self.vision_hidden_size}) must be a multiple of vision_num_heads "
                             f"({self.vision_num_heads})")
        if self.num_attention_heads % self.num_key_value_heads:
            raise ValueError(
                f"num_attention_heads ({self.num_attention_heads}) must be a multiple of "
                f"num_key_value_heads ({self.num_key_value_heads})"
            )
        if self.head_dim % 2:
            raise ValueError(f"head_dim must be even for RoPE, got {self.head_dim}")
        if self.image_size % self.patch_size:
            raise ValueError(f"image_size ({self.image_size}) must be a multiple of patch_size ({self.patch_size})")
        if (not self.camera_names or len(set(self.camera_names)) != len(self.camera_names)
                or not all(isinstance(name, str) and name for name in self.camera_names)):
            raise ValueError(f"camera_names must be non-empty, unique strings, got {self.camera_names}")

    @property
    def num_cameras(self) -> int:
        return len(self.camera_names)

    @property
    def tokens_per_image(self) -> int:
        return (self.image_size // self.patch_size) ** 2

    @property
    def prefix_len(self) -> int:
        """Tokens of the prefix: every camera's image tokens, then the prompt's tokens."""
        return self.num_cameras * self.tokens_per_image + self.max_token_len

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: str | os.PathLike[str], **kwargs: Any) -> Any:
        """`PretrainedConfig.from_pretrained`, refusing at once a path that is neither a folder with `config.json`
        nor a hub id (see `pi0_torch.utils.validation.is_hub_id`)."""
        config_file = f"{kwargs['subfolder']}/config.json" if kwargs.get("subfolder") else "config.json"
        check_pretrained_location(pretrained_model_name_or_path, config_file, "model")
        with hub_errors(pretrained_model_name_or_path, "model"):
            return super().from_pretrained(pretrained_model_name_or_path, **kwargs)

    @classmethod
    def _dict_from_json_file(cls, json_file: str | os.PathLike[str]) -> dict[str, Any]:
        config_dict = read_json_file(json_file)  # (transformers' own reader raises the parser's errors, naming no file)
        if not isinstance(config_dict, Mapping):
            raise ValueError(f"{json_file} must hold a JSON object of settings, got a JSON {type(config_dict).__name__}")
        return dict(config_dict)


def camera_list(camera_names: Sequence[str]) -> list[str]:
    """The `camera_names` setting as a list; a single string (a likely slip for a list of one) is refused."""
    if isinstance(camera_names, str) or not isinstance(camera_names, Sequence):
        raise ValueError(f"camera_names must be a list of camera names, got {camera_names!r}")
    return list(camera_names)


def check_dtype_setting(settings: Mapping[str, Any]) -> None:
    """A `dtype` (or `torch_dtype`) among a config's settings (what transformers loads the weights as) must name a
    torch floating-point dtype: `"float7"` would otherwise fail inside transformers with an `AttributeError`."""
    import torch

    dtype = settings.get("dtype", settings.get("torch_dtype"))
    if isinstance(dtype, str) and dtype != "auto":
        resolved = getattr(torch, dtype, None)
        if not isinstance(resolved, torch.dtype) or not resolved.is_floating_point:
            raise ValueError(f"dtype must name a torch floating-point dtype (float32, bfloat16, float16) or 'auto', "
                             f"got {dtype!r:.60}")


def vision_parameters(image_size: int, patch_size: int, width: int, intermediate: int, layers: int) -> int:
    """SigLIP's parameter count (patch embedding, position table, and per layer attention and MLP)."""
    tokens = (image_size // patch_size) ** 2
    return 3 * patch_size**2 * width + tokens * width + layers * (4 * width * width + 2 * width * intermediate)
