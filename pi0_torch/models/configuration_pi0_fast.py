"""Configuration of π0-FAST: PaliGemma (SigLIP + Gemma 2B) decoding FAST action tokens autoregressively."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pi0_torch.models.cameras import FAST_CAMERA_NAMES
from pi0_torch.models.configuration_base import PALIGEMMA_VOCAB_SIZE, PI0BaseConfig, camera_list, vision_parameters
from pi0_torch.utils.validation import check_int

PALIGEMMA_EOS_TOKEN = 1

# Sizes of the vision tower and the Gemma decoder. "full" is openpi's `gemma_2b` with SigLIP So400m/14 (the released
# pi0_fast checkpoints); "small" matches the openpi test fixture `pi0_fast_small`; "medium" is a benchmark size.
_SIZES: dict[str, dict[str, Any]] = {
    "full": dict(
        vision_hidden_size=1152, vision_intermediate_size=4304, vision_num_layers=27, vision_num_heads=16,
        hidden_size=2048, intermediate_size=16_384, num_hidden_layers=18,
        num_attention_heads=8, num_key_value_heads=1, head_dim=256, vocab_size=PALIGEMMA_VOCAB_SIZE,
    ),
    "medium": dict(
        vision_hidden_size=384, vision_intermediate_size=1536, vision_num_layers=6, vision_num_heads=6,
        hidden_size=512, intermediate_size=2048, num_hidden_layers=6,
        num_attention_heads=8, num_key_value_heads=1, head_dim=64, vocab_size=16_384,
    ),
    "small": dict(
        vision_hidden_size=40, vision_intermediate_size=72, vision_num_layers=2, vision_num_heads=4,
        hidden_size=64, intermediate_size=96, num_hidden_layers=2,
        num_attention_heads=2, num_key_value_heads=1, head_dim=32, vocab_size=1100,
    ),
}
# What openpi's released configs set beyond the sizes (`Pi0FASTConfig` defaults: action_dim 32, horizon 32, 250 tokens).
_TASKS: dict[str, dict[str, Any]] = {
    "": dict(action_dim=32, action_horizon=32, max_token_len=250),
    "droid": dict(action_dim=8, action_horizon=10, max_token_len=250),
    "libero": dict(action_dim=7, action_horizon=10, max_token_len=180),
}
_PRESETS: dict[str, tuple[str, str]] = {
    "pi0_fast": ("full", ""),
    "pi0_fast_droid": ("full", "droid"),
    "pi0_fast_libero": ("full", "libero"),
    "pi0_fast_medium": ("medium", "droid"),
    "pi0_fast_small": ("small", ""),
}
_SMALL_TASK = dict(action_dim=8, action_horizon=10, max_token_len=96, max_decoding_steps=12)


class PI0FastConfig(PI0BaseConfig):
    """Configuration of [`PI0FastForActionGeneration`].

    Holds the SigLIP vision tower's dims (same names as [`PI0Config`]), the Gemma decoder's (one expert: width
    `hidden_size`, LM head tied to the token embedding), and the FAST action settings: `action_dim` and
    `action_horizon` are the shape of the chunk the FAST tokens decode to, `max_token_len` the length of the
    tokenized prompt (prompt, state and, in training, the action tokens), `max_decoding_steps` the default
    number of tokens `generate_tokens` decodes, `fast_skip_tokens` the special tokens at the end of the
    vocabulary that FAST ids skip (FAST id `i` is token `vocab_size - 1 - fast_skip_tokens - i`).

    `decoding_position_offset`: the token decoded at step t is fed at RoPE position `n_valid + t + offset`, where
    `n_valid` counts the valid prefix tokens. openpi at commit 15a9616a (the version the parity fixtures come from)
    uses 1, one past the position training gives that token; later openpi uses 0. Default 1, openpi's behaviour
    the parity tests check.

    ```python
    >>> from pi0_torch import PI0FastConfig
    >>> config = PI0FastConfig.from_preset("pi0_fast_droid")
    >>> config.hidden_size, config.action_dim, config.action_horizon, config.camera_names
    (2048, 8, 10, ['base_0_rgb', 'base_1_rgb', 'wrist_0_rgb'])

    ```
    """

    model_type = "pi0_fast_torch"
    own_sizes = ("hidden_size", "intermediate_size", "max_decoding_steps")

    def __init__(
        self,
        # SigLIP vision tower
        image_size: int = 224,
        patch_size: int = 14,
        vision_hidden_size: int = 1152,
        vision_intermediate_size: int = 4304,
        vision_num_layers: int = 27,
        vision_num_heads: int = 16,
        # Gemma decoder
        hidden_size: int = 2048,
        intermediate_size: int = 16_384,
        num_hidden_layers: int = 18,
        num_attention_heads: int = 8,
        num_key_value_heads: int = 1,
        head_dim: int = 256,
        vocab_size: int = PALIGEMMA_VOCAB_SIZE,
        rms_norm_eps: float = 1e-6,
        rope_theta: float = 10_000.0,
        # FAST actions and decoding
        action_dim: int = 32,
        action_horizon: int = 32,
        max_token_len: int = 250,
        max_decoding_steps: int = 256,
        fast_skip_tokens: int = 128,
        decoding_position_offset: int = 1,
        camera_names: Sequence[str] = FAST_CAMERA_NAMES,
        eos_token_id: int = PALIGEMMA_EOS_TOKEN,
        **kwargs: Any,
    ) -> None:
        self.image_size = image_size
        self.patch_size = patch_size
        self.vision_hidden_size = vision_hidden_size
        self.vision_intermediate_size = vision_intermediate_size
        self.vision_num_layers = vision_num_layers
        self.vision_num_heads = vision_num_heads
        self.hidden_size = hidden_size
        self.intermediate_size = intermediate_size
        self.num_hidden_layers = num_hidden_layers
        self.num_attention_heads = num_attention_heads
        self.num_key_value_heads = num_key_value_heads
        self.head_dim = head_dim
        self.vocab_size = vocab_size
        self.rms_norm_eps = rms_norm_eps
        self.rope_theta = rope_theta
        self.action_dim = action_dim
        self.action_horizon = action_horizon
        self.max_token_len = max_token_len
        self.max_decoding_steps = max_decoding_steps
        self.fast_skip_tokens = fast_skip_tokens
        self.decoding_position_offset = decoding_position_offset
        self.camera_names = camera_list(camera_names)
        super().__init__(eos_token_id=eos_token_id, **kwargs)

    def _check(self) -> None:
        """The shared checks ([`PI0BaseConfig._check`]), then the FAST token ids and the decoding positions."""
        super()._check()
        check_int("fast_skip_tokens", self.fast_skip_tokens, minimum=0, maximum=self.vocab_size - 1)
        check_int("decoding_position_offset", self.decoding_position_offset, minimum=0, maximum=1)

    def estimated_parameters(self) -> int:
        """The model's parameter count from its sizes (norms left out), for a memory estimate before a model is
        built (see `PI0Config.estimated_parameters`)."""
        vision = vision_parameters(self.image_size, self.patch_size, self.vision_hidden_size,
                                   self.vision_intermediate_size, self.vision_num_layers)
        attention = self.num_attention_heads * self.head_dim
        layer = (self.hidden_size * (attention + 2 * self.num_key_value_heads * self.head_dim)
                 + attention * self.hidden_size + 3 * self.hidden_size * self.intermediate_size)
        return (vision + self.vision_hidden_size * self.hidden_size + self.vocab_size * self.hidden_size
                + self.num_hidden_layers * layer)

    @classmethod
    def from_preset(cls, name: str, **overrides: Any) -> PI0FastConfig:
        """Build a preset: `pi0_fast` (openpi's `pi0_fast_base`), `pi0_fast_droid`, `pi0_fast_libero` (released
        size), `pi0_fast_medium` (benchmark size), `pi0_fast_small` (the openpi test fixture's dims)."""
        if name not in _PRESETS:
            raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(_PRESETS)}")
        size, task = _PRESETS[name]
        settings = {**_SIZES[size], **(_SMALL_TASK if size == "small" else _TASKS[task])}
        return cls(**{**settings, **overrides})


def fast_preset_names() -> list[str]:
    """Names accepted by [`PI0FastConfig.from_preset`]."""
    return list(_PRESETS)
