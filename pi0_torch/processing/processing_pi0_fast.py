"""`PI0FastProcessor`: raw robot observations -> `PI0FastForActionGeneration` inputs, and generated tokens -> robot
actions.

It is `PI0Processor` (same images, state/action normalization, delta actions, value conversions, batching and
checks) with openpi's π0-FAST prompt (`FASTTokenizer.tokenize`) and, on the way out, openpi's `extract_actions`:

- prompt: `<bos> "Task: {prompt lowercased, stripped, _ -> space}, State: {bins};\\n"` with the normalized state
  (the robot's dims) in 256 bins over [-1, 1] (`np.digitize(s, linspace(-1, 1, 257)[:-1]) - 1`), block flag 0,
  no loss;
- in training, then `"Action: "`, the FAST ids of the normalized action chunk (padded to the model's action dim)
  mapped into the end of the vocabulary (`vocab - 1 - fast_skip_tokens - id`), and `"|" <eos>`, block flag 1
  (causal), with loss;
- padded with 0 (mask, flags and loss False) to `max_token_len`, or truncated (warning, or an error with
  `truncation="error"`);
- out: the generated tokens are decoded to text, the text between `"Action: "` and `"|"` is encoded again, the ids
  mapped back to FAST ids and FAST-decoded to `[action_horizon, action_dim]` (zeros, with a warning, when that
  fails; NaN with `mark_undecodable`, as `PI0FastPolicy` asks, so that the chunk is withheld), then unnormalized like
  π0's actions (`postprocess_actions`).

Normalization defaults to quantile (openpi normalizes every model but π0 by quantiles), and an absent camera is a
black frame with its mask on (openpi's π0-FAST input transforms do not mask padding images). The FAST tokenizer is
saved in the `fast_tokenizer/` subfolder of the model folder.

```python
>>> import numpy as np
>>> from pi0_torch import PI0FastConfig
>>> from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
>>> from pi0_torch.processing.normalization import NormStats
>>> from pi0_torch.processing.tokenization import build_test_tokenizer
>>> rng = np.random.default_rng(0)
>>> fast = FASTActionTokenizer.fit([np.cumsum(rng.normal(0, .1, (10, 8)), 0) for _ in range(100)], vocab_size=256)
>>> stats = NormStats(mean=np.zeros(8), std=np.ones(8), q01=-np.ones(8), q99=np.ones(8))
>>> config = PI0FastConfig.from_preset("pi0_fast_small")
>>> processor = PI0FastProcessor.from_config(config, build_test_tokenizer(1024), fast, {"state": stats, "actions": stats})
>>> inputs = processor(images={"base_0_rgb": np.zeros((224, 224, 3), np.uint8)}, prompt="Pick up the fork",
...                    state=np.zeros(8), actions=np.zeros((10, 8)))
>>> sorted(inputs)
['attention_mask', 'image_masks', 'input_ids', 'pixel_values', 'token_ar_mask', 'token_loss_mask']
>>> processor.tokenizer.decode(inputs["input_ids"][0][~inputs["token_ar_mask"][0]])
'Task: pick up the fork, State: 127 127 127 127 127 127 127 127;\\n'
>>> processor.extract_actions(inputs["input_ids"][0][inputs["token_ar_mask"][0]].numpy()).shape
(1, 10, 8)

```
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from transformers import AutoProcessor

from pi0_torch.models.cameras import FAST_CAMERA_NAMES
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor, config_settings
from pi0_torch.processing.tokenization import TokenizerSource, discretize_state

FAST_TOKENIZER_DIR = "fast_tokenizer"
ACTION_START = "Action: "
ACTION_END = "|"

logger = logging.getLogger(__name__)


def clean_fast_prompt(prompt: str) -> str:
    """openpi's π0-FAST cleaning: lowercase, strip, `_` -> space (newlines are kept, unlike π0's)."""
    return prompt.lower().strip().replace("_", " ")


def format_fast_prefix(prompt: str, normalized_state: Any) -> str:
    """`"Task: {clean prompt}, State: {bins};\\n"`, the part of a π0-FAST prompt every token attends to."""
    bins = " ".join(str(int(b)) for b in discretize_state(normalized_state))
    return f"Task: {clean_fast_prompt(prompt)}, State: {bins};\n"


class PI0FastProcessor(PI0Processor):
    """Camera frames + instruction + robot state (+ actions in training) -> π0-FAST model inputs; generated tokens ->
    robot actions.

    Args:
        tokenizer: the prompt tokenizer (PaliGemma's SentencePiece model), as for [`PI0Processor`].
        action_tokenizer: a [`FASTActionTokenizer`] or a folder holding one (the `physical-intelligence/fast`
            layout).
        fast_skip_tokens: special tokens at the end of the prompt vocabulary that FAST ids skip (128 for PaliGemma).
        mask_missing_cameras: False (openpi's π0-FAST input transforms, "we don't mask out padding images for FAST
            models"): an absent camera is a black frame the model sees; True: it is masked out, as π0 does.
        camera_names, max_token_len, norm_mode, ...: as for [`PI0Processor`] (defaults: openpi's π0-FAST cameras,
            250 tokens, quantile normalization).
    """

    def __init__(
        self,
        tokenizer: TokenizerSource,
        action_tokenizer: FASTActionTokenizer | str | Path,
        *,
        camera_names: Sequence[str] = FAST_CAMERA_NAMES,
        max_token_len: int = 250,
        norm_mode: str | None = "quantile",
        fast_skip_tokens: int = 128,
        mask_missing_cameras: bool = False,
        **settings: Any,
    ) -> None:
        super().__init__(tokenizer, camera_names=camera_names, max_token_len=max_token_len, norm_mode=norm_mode, **settings)
        self.mask_missing_cameras = bool(mask_missing_cameras)
        if self.pi05:
            raise ValueError("pi05=True is a π0.5 setting; PI0FastProcessor writes π0-FAST prompts")
        if not isinstance(action_tokenizer, FASTActionTokenizer):
            action_tokenizer = FASTActionTokenizer.from_pretrained(action_tokenizer)
        self.action_tokenizer = action_tokenizer
        self.fast_skip_tokens = int(fast_skip_tokens)
        lowest = self.tokenizer.vocab_size - 1 - self.fast_skip_tokens - (action_tokenizer.vocab_size - 1)
        if lowest < 0 or self.fast_skip_tokens < 0:
            raise ValueError(
                f"FAST ids 0..{action_tokenizer.vocab_size - 1} do not fit below the last {self.fast_skip_tokens} of "
                f"the prompt tokenizer's {self.tokenizer.vocab_size} tokens"
            )
        if self.tokenizer.eos_id is None:
            raise ValueError("the prompt tokenizer has no end-of-sequence token; π0-FAST's action postfix ends with one")

    @classmethod
    def from_config(  # type: ignore[override]
        cls,
        config: PI0FastConfig,
        tokenizer: TokenizerSource,
        action_tokenizer: FASTActionTokenizer | str | Path,
        norm_stats: Mapping[str, NormStats] | str | Path | None = None,
        **kwargs: Any,
    ) -> PI0FastProcessor:
        """A processor matching `config` (cameras, image size, prompt length, action chunk shape, skipped tokens).

        Raises `ValueError` when the prompt tokenizer's vocabulary is larger than the model's.
        """
        settings = {**config_settings(config), "fast_skip_tokens": config.fast_skip_tokens, **kwargs}
        processor = cls(tokenizer, action_tokenizer, norm_stats=norm_stats, **settings)
        processor._check_vocab_size(config)
        return processor

    def to_dict(self) -> dict[str, Any]:
        settings = super().to_dict()
        settings.pop("pi05")
        settings["fast_skip_tokens"] = self.fast_skip_tokens
        settings["mask_missing_cameras"] = self.mask_missing_cameras
        return settings

    def save_pretrained(self, save_directory: str | Path, **unused: Any) -> list[str]:
        """As [`PI0Processor.save_pretrained`], plus the FAST tokenizer in `fast_tokenizer/`."""
        written = super().save_pretrained(save_directory)
        written.append(str(self.action_tokenizer.save_pretrained(Path(save_directory) / FAST_TOKENIZER_DIR)))
        return written

    @classmethod
    def from_pretrained(cls, pretrained_path: str | Path, **overrides: Any) -> PI0FastProcessor:
        """Load what [`save_pretrained`] wrote (the FAST tokenizer from `fast_tokenizer/` unless
        `action_tokenizer=` is given); `overrides` replace saved settings."""
        if overrides.get("action_tokenizer") is None:
            overrides["action_tokenizer"] = FASTActionTokenizer.from_pretrained(Path(pretrained_path) / FAST_TOKENIZER_DIR)
        return super().from_pretrained(pretrained_path, **overrides)  # type: ignore[return-value]

    # ------------------------------------------------------------------------------------------- inputs

    def tokenize(self, prompt: str, state: Any, actions: Any = None) -> dict[str, np.ndarray]:
        """openpi's `FASTTokenizer.tokenize` on an already normalized `state` `[D]` and (training) `actions` `[H, A]`.

        Returns `input_ids` int64, `attention_mask`, `token_ar_mask` and `token_loss_mask` bool, each `[max_token_len]`.
        """
        if not isinstance(prompt, str):
            raise ValueError(f"prompt: expected a string, got {type(prompt).__name__}")
        if not clean_fast_prompt(prompt).strip():
            raise ValueError(f"prompt: empty after cleaning (got {prompt!r}); give the task instruction")
        prefix = self.tokenizer.encode(format_fast_prefix(prompt, state), add_bos=True)
        postfix: list[int] = []
        if actions is not None:
            fast_ids = np.asarray(self.action_tokenizer(actions)[0], dtype=np.int64)
            postfix = (
                self.tokenizer.encode(ACTION_START)
                + self._fast_to_vocab(fast_ids).tolist()
                + self.tokenizer.encode(ACTION_END)
                + [self.tokenizer.eos_id]
            )
        ids = prefix + postfix
        causal = [False] * len(prefix) + [True] * len(postfix)
        if len(ids) > self.max_token_len:
            message = f"prompt: {len(ids)} tokens exceed max_token_len {self.max_token_len} ({clean_fast_prompt(prompt)[:60]!r})"
            if self.truncation == "error":
                raise ValueError(message + "; shorten it or raise max_token_len")
            warnings.warn(message + "; truncating (the model sees only the first max_token_len tokens)", stacklevel=3)
            ids, causal = ids[: self.max_token_len], causal[: self.max_token_len]
        length = self.max_token_len
        input_ids = np.zeros(length, np.int64)
        input_ids[: len(ids)] = ids
        attention_mask = np.arange(length) < len(ids)
        token_ar_mask = np.zeros(length, bool)
        token_ar_mask[: len(causal)] = causal
        return {
            "input_ids": input_ids,
            "attention_mask": attention_mask,
            "token_ar_mask": token_ar_mask,
            "token_loss_mask": token_ar_mask.copy(),  # the loss is on the postfix, the causal part
        }

    def _encode_images(self, images: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
        """As π0's; an absent camera is a black frame whose mask stays on unless `mask_missing_cameras`."""
        pixel_values, image_masks = super()._encode_images(images, where)
        return pixel_values, image_masks if self.mask_missing_cameras else np.ones_like(image_masks)

    def _encode(self, sample: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
        """One observation -> unbatched model arrays; `where` prefixes error messages (e.g. `"[3] "`)."""
        state = self._model_space_state(self._check_vector(sample.get("state"), where + "state", self.state_dim))
        pixel_values, image_masks = self._encode_images(sample.get("images"), where)
        normalized_state = self._normalized_state(state, where)
        prompt = self._prompt(sample, where)
        actions = None
        if sample.get("actions") is not None:
            actions = self._encode_actions(sample["actions"], state, where)  # normalized, padded to model_action_dim
        try:
            tokens = self.tokenize(prompt, normalized_state, actions)
        except ValueError as error:
            raise ValueError(f"{where}{error}") from None
        if actions is None:
            tokens.pop("token_loss_mask")
        return {"pixel_values": pixel_values, "image_masks": image_masks, **tokens}

    # ------------------------------------------------------------------------------------------- outputs

    def _fast_to_vocab(self, ids: np.ndarray) -> np.ndarray:
        """FAST ids <-> prompt-vocabulary ids (the map is its own inverse)."""
        return self.tokenizer.vocab_size - 1 - self.fast_skip_tokens - ids

    def extract_actions(self, tokens: Any, mark_undecodable: bool = False) -> np.ndarray:
        """openpi's `extract_actions`: generated tokens `[T]` or `[B, T]` -> float32 `[B, action_horizon,
        model_action_dim]` normalized actions.

        The tokens are decoded to text; the text between `"Action: "` and `"|"`, stripped, is encoded again and its
        ids mapped back to FAST ids, which the FAST tokenizer decodes. No `"Action: "`, or FAST ids that do not
        decode to a whole chunk, give a chunk of zeros (openpi's behaviour) and a logged warning; with
        `mark_undecodable`, a chunk of NaN, which tells it from a decoded chunk (a policy withholds it).
        """
        rows = tokens.detach().cpu().numpy() if isinstance(tokens, torch.Tensor) else np.asarray(tokens)
        if rows.ndim == 1:
            rows = rows[None]
        if rows.ndim != 2 or rows.dtype.kind not in "iu":
            raise ValueError(f"tokens: expected integer ids [T] or [B, T], got shape {rows.shape} dtype {rows.dtype}")
        horizon, dim = self.action_horizon, self.model_action_dim
        if horizon is None:
            raise ValueError("extract_actions needs the processor's action_horizon (build it with from_config)")
        chunks = np.full((len(rows), horizon, dim), np.nan if mark_undecodable else 0.0, np.float32)
        for index, row in enumerate(rows):
            text = self.tokenizer.decode(row.tolist())
            if ACTION_START not in text:
                logger.warning("generated tokens hold no %r: returning a chunk of %s (text: %r)", ACTION_START,
                               "NaN (undecodable)" if mark_undecodable else "zeros", text[:80])
                continue
            action_text = text.split(ACTION_START, 1)[1].split(ACTION_END)[0].strip()
            fast_ids = self._fast_to_vocab(np.asarray(self.tokenizer.encode(action_text), dtype=np.int64))
            chunks[index] = self.action_tokenizer.decode([fast_ids.tolist()], time_horizon=horizon, action_dim=dim,
                                                         mark_undecodable=mark_undecodable)[0]
        return chunks

    def decode_actions(self, tokens: Any, state: Any = None) -> np.ndarray:
        """Generated tokens `[T]` / `[B, T]` -> robot actions `[B, action_horizon, action_dim_robot]` in robot units
        (`extract_actions`, then `postprocess_actions`; `state` is the raw state, needed with delta actions)."""
        return self.postprocess_actions(self.extract_actions(tokens), state=state)  # type: ignore[return-value]


AutoProcessor.register(PI0FastConfig, PI0FastProcessor, exist_ok=True)
