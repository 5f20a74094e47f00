"""π0-FAST in PyTorch, numerically matching openpi (`src/openpi/models/pi0_fast.py`, `gemma_fast.py`).

π0-FAST is PaliGemma decoding FAST action tokens: SigLIP image tokens and the tokenized prompt (task, discretized
state and, in training, `Action: <FAST tokens>|<eos>`) go through one Gemma decoder whose LM head is its token
embedding. The building blocks are π0's (`pi0_torch.models.modeling_pi0`): the SigLIP tower and image head, RMSNorm,
RoPE, the Gemma layer weights (`ExpertLayer`: fused q/k/v, o-projection, GeGLU MLP) and the prefix-LM mask.

Reading order: one decoder layer (a single stream with an optional static k/v buffer), then the model: embedding of
images and prompt, the teacher-forced forward with openpi's loss, and cached decoding (the prefill and one decoded
token; the loop over tokens and what runs it are `pi0_torch.inference.token_decoding.TokenDecoding`'s). Shapes: B batch, C cameras,
P prefix tokens (C * 256 image tokens + L prompt tokens), T decoded tokens, S = P + T k/v slots, N query heads,
K kv heads, H head size, D width, V vocabulary.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import nn
from transformers.modeling_layers import GradientCheckpointingLayer
from transformers.utils import ModelOutput

from pi0_torch.inference.fast_decoding import DecodingLayers, decode_layers_
from pi0_torch.inference.token_decoding import DecodingCache, TokenDecoding
from pi0_torch.kernels.reference import apply_rope, rope_cos_sin
from pi0_torch.masks import aligned_key_count, masked_attention, pad_keys, prefix_lm_mask, to_additive_mask
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.layers import ExpertLayer, RMSNorm
from pi0_torch.models.pretrained import PI0PreTrainedModel
from pi0_torch.models.vision import SiglipImageEmbedding, siglip_vision_tower
from pi0_torch.utils.validation import check_tensor as _check_tensor
from pi0_torch.utils.validation import describe as _describe

if TYPE_CHECKING:
    from pi0_torch.inference.layer_pass import SamplingWeights
    from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor

# ----------------------------------------------------------------------------------------------------------------------
# One Gemma layer
# ----------------------------------------------------------------------------------------------------------------------


class FastDecoderLayer(GradientCheckpointingLayer):
    """One layer of openpi's `gemma_fast` (pre-norms, grouped-query attention with RoPE, GeGLU MLP), with the weights
    of π0's `ExpertLayer`."""

    def __init__(self, config: PI0FastConfig) -> None:
        super().__init__()
        self.block = ExpertLayer(config, config.hidden_size, config.intermediate_size, adaptive=False)
        self.head_dim = config.head_dim

    def forward(
        self,
        x: torch.Tensor,  # [B, T, D]
        cos: torch.Tensor,  # [B, 1, T, H] from `rope_cos_sin`
        sin: torch.Tensor,
        mask: torch.Tensor,  # additive float [B, 1, T, T] (no buffer) or [B, 1, T, S] (with a buffer)
        kv_buffer: tuple[torch.Tensor, torch.Tensor] | None = None,  # [B, K, S, H] each
        kv_slots: torch.Tensor | None = None,  # long [T]: where the new k/v go in the buffer
        last_only: bool = False,
    ) -> torch.Tensor:
        """Returns the layer's output `[B, T, D]` (`[B, 1, D]` for the last token alone with `last_only`).

        With `kv_buffer`, the tokens' post-RoPE k/v are written into the buffer at `kv_slots` and attention reads
        the whole buffer (a static k/v cache; `mask` says which slots each query sees). `last_only` finishes only the
        last token once every token's k/v is written (the prefill's last layer: only the last output is read).
        """
        block = self.block
        batch, length = x.shape[:2]
        q, k, v = (
            y.view(batch, length, -1, self.head_dim).transpose(1, 2)  # [B, heads, T, H]
            for y in block.qkv_proj(block.attn_norm(x)).split([heads * self.head_dim for heads in block.heads], dim=-1)
        )
        q, k = apply_rope(q, cos, sin).to(q.dtype), apply_rope(k, cos, sin).to(k.dtype)
        if kv_buffer is not None:
            key_buffer, value_buffer = kv_buffer
            key_buffer.index_copy_(2, kv_slots, k)
            value_buffer.index_copy_(2, kv_slots, v)
            k, v = key_buffer, value_buffer
        if last_only:
            q, x, mask = q[:, :, -1:], x[:, -1:], mask[:, :, -1:].contiguous()
        attended = masked_attention(q, k, v, mask, scale=q.shape[-1] ** -0.5, additive=True)  # [B, N, T, H]
        x = x + block.o_proj(attended.transpose(1, 2).flatten(2))
        return x + block.down_proj(block.geglu(block.gate_up_proj(block.mlp_norm(x))))


# ----------------------------------------------------------------------------------------------------------------------
# The model
# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class PI0FastOutput(ModelOutput):
    """Output of [`PI0FastForActionGeneration.forward`].

    Attributes:
        loss: scalar, the batch mean of openpi's per-example loss: next-token cross-entropy averaged over the
            targets where `token_loss_mask` is set (present when `token_loss_mask` was given).
        logits: `[B, L - 1, V]` next-token logits at the prompt positions: `logits[:, i]` predicts `input_ids[:, i + 1]`.
    """

    loss: torch.Tensor | None = None
    logits: torch.Tensor | None = None


class PI0FastPreTrainedModel(PI0PreTrainedModel):
    """π0's pre-trained model base (weight init, strict `from_pretrained`) with the π0-FAST config."""

    config_class = PI0FastConfig
    config: PI0FastConfig  # type: ignore[assignment]
    base_model_prefix = "pi0_fast"
    _no_split_modules = ["FastDecoderLayer", "SiglipEncoderLayer"]


class PI0FastForActionGeneration(TokenDecoding, SiglipImageEmbedding, PI0FastPreTrainedModel):
    """π0-FAST: SigLIP vision tower + Gemma decoder (LM head tied to the token embedding) over FAST action tokens.

    ```python
    >>> import torch
    >>> from pi0_torch import PI0FastConfig, PI0FastForActionGeneration
    >>> config = PI0FastConfig.from_preset("pi0_fast_small")
    >>> model = PI0FastForActionGeneration(config).eval()
    >>> length = config.max_token_len
    >>> batch = dict(
    ...     pixel_values=torch.zeros(1, config.num_cameras, 3, 224, 224),
    ...     image_masks=torch.ones(1, config.num_cameras, dtype=torch.bool),
    ...     input_ids=torch.full((1, length), 5),
    ...     attention_mask=torch.ones(1, length, dtype=torch.bool),
    ...     token_ar_mask=torch.arange(length)[None] >= 40,  # prompt: 40 tokens, then the action tokens
    ... )
    >>> model(**batch, token_loss_mask=batch["token_ar_mask"]).logits.shape
    torch.Size([1, 95, 1100])
    >>> model.generate_tokens(**batch, max_new_tokens=4).shape
    torch.Size([1, 4])

    ```
    """

    def __init__(self, config: PI0FastConfig) -> None:
        super().__init__(config)
        self.vision_tower = siglip_vision_tower(config)
        self.image_projection = nn.Linear(config.vision_hidden_size, config.hidden_size)
        self.embed_tokens = nn.Embedding(config.vocab_size, config.hidden_size)
        self.layers = nn.ModuleList(FastDecoderLayer(config) for _ in range(config.num_hidden_layers))
        self.final_norm = RMSNorm(config.hidden_size, config.rms_norm_eps)
        self.post_init()

    # -- inputs: images and prompt -------------------------------------------------------------------------------------

    def embed_inputs(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Tokens `[B, P, D]` (each camera's image tokens, then the prompt embeddings times sqrt(D)), their validity
        `[B, P]` and block flags `[B, P]` (0 on images, `token_ar_mask` on the prompt).

        Every camera goes through SigLIP, masked ones too: openpi's decoding lets generated tokens see a masked
        camera's tokens (see `prepare_decoding`), so they must be what openpi computes.
        """
        image_tokens = self.embed_images(pixel_values)  # [B, C, 256, D]
        text_tokens = self.embed_tokens(input_ids)
        text_tokens = text_tokens * torch.tensor(math.sqrt(text_tokens.shape[-1]), dtype=text_tokens.dtype)
        tokens = torch.cat([image_tokens.flatten(1, 2), text_tokens], dim=1)
        image_valid = image_masks.bool()[:, :, None].expand(-1, -1, image_tokens.shape[2]).flatten(1)
        valid = torch.cat([image_valid, attention_mask.bool()], dim=1)
        flags = torch.cat([torch.zeros_like(image_valid), token_ar_mask.bool()], dim=1)
        return tokens, valid, flags

    def lm_head(self, hidden: torch.Tensor) -> torch.Tensor:
        """Logits `[..., V]` of final-normed hidden states: the token embedding, transposed (tied, as in Gemma)."""
        return F.linear(hidden, self.embed_tokens.weight)

    # -- teacher-forced forward ----------------------------------------------------------------------------------------

    def forward(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
        token_loss_mask: torch.Tensor | None = None,
        **unused: Any,
    ) -> PI0FastOutput:
        """Next-token logits of the prompt positions and (with `token_loss_mask`) openpi's loss.

        As openpi's `compute_loss`: one pass over images and prompt without its last token, under the prefix-LM
        mask of `token_ar_mask` (0 = bidirectional prefix, 1 = causal), with positions `0, 1, ..., P - 2` (in
        training openpi counts every token, masked cameras included).

        Args:
            pixel_values: float `[B, C, 3, H, W]` in [-1, 1], cameras in `config.camera_names` order.
            image_masks: bool `[B, C]`, False for a missing camera.
            input_ids: long `[B, L]` from `PI0FastProcessor` (prompt, state and, in training, the action tokens).
            attention_mask: bool `[B, L]`, False on padding.
            token_ar_mask: `[B, L]`, 1 where a token starts a causal block (the `Action: ...` postfix).
            token_loss_mask: bool `[B, L]`, True on the tokens the loss predicts (the postfix).

        Returns:
            [`PI0FastOutput`] with `logits` `[B, L - 1, V]` and `loss` (scalar, when `token_loss_mask` is given).
        """
        self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, token_ar_mask, token_loss_mask)
        tokens, valid, flags = self.embed_inputs(pixel_values, image_masks, input_ids, attention_mask, token_ar_mask)
        mask, _ = prefix_lm_mask(valid, flags)
        length = tokens.shape[1] - 1  # each token predicts the next one: the last is no input
        positions = torch.arange(length, device=tokens.device).expand(tokens.shape[0], -1)
        cos, sin = (table[:, None] for table in rope_cos_sin(positions, self.config.head_dim, self.config.rope_theta))
        x = tokens[:, :-1]
        additive = to_additive_mask(mask[:, None, :-1, :-1], x.dtype)  # once for all layers
        for layer in self.layers:
            x = layer(x, cos, sin, additive)
        hidden = self.final_norm(x[:, -(input_ids.shape[1] - 1) :])
        logits = self.lm_head(hidden)  # [B, L-1, V]
        loss = None
        if token_loss_mask is not None:
            target_logp = token_log_probs(logits, input_ids[:, 1:])
            loss_mask = token_loss_mask[:, 1:].to(target_logp.dtype)
            per_example = -(target_logp * loss_mask).sum(dim=-1) / loss_mask.sum(dim=-1).clamp(min=1)
            loss = per_example.mean()
        return PI0FastOutput(loss=loss, logits=logits)

    # -- decoding ------------------------------------------------------------------------------------------------------

    def prepare_decoding(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
        max_new_tokens: int,
        fused: Sequence[SamplingWeights] | None = None,
    ) -> tuple[DecodingCache, torch.Tensor]:
        """Prefill: run images and prompt once, keep every layer's k/v, and return the cache with the logits `[B, V]`
        that pick the first token. `fused`: each layer's weights (`layer_pass.decoder_sampling_weights`, as the call's
        plain-weights check made them) where `decode_step` runs the fused kernels (see `decoding_kernels`); None: the
        modules.

        As openpi's `sample_actions`: each row's tokens are rotated so its last valid token is last ("left to right
        alignment"), positions are `cumsum(valid) - 1`, and the k/v buffers have `max_new_tokens` empty (zero) slots
        after the prefix. Decoded token t sits in slot `P + t` at position `n_valid + t + decoding_position_offset`
        (see `PI0FastConfig`) and sees slot `j` iff `P - n_valid <= j <= P + t`. With every camera present that window is exactly the valid prefix and the
        decoded tokens; with a masked camera it is openpi's: it starts `n_valid` slots before the prefix end, so it
        includes the masked camera's tokens and leaves out as many valid ones at its start. Reproduced as is.
        """
        config = self.config
        tokens, valid, flags = self.embed_inputs(pixel_values, image_masks, input_ids, attention_mask, token_ar_mask)
        mask, _ = prefix_lm_mask(valid, flags)
        tokens, valid, mask = left_to_right_align(tokens, valid, mask)
        batch, prefix_len = valid.shape
        slots = self.decoding_slots(pixel_values.shape[1], input_ids.shape[1], max_new_tokens)
        device = tokens.device

        buffer_shape = (batch, config.num_key_value_heads, slots, config.head_dim)
        keys = [tokens.new_zeros(buffer_shape) for _ in self.layers]  # zeros: fully masked rows average them, as openpi
        values = [tokens.new_zeros(buffer_shape) for _ in self.layers]
        prefix_mask = F.pad(mask, (0, max_new_tokens))[:, None]  # [B, 1, P, P + max_new_tokens]
        cos, sin = (table[:, None] for table in rope_cos_sin(torch.cumsum(valid.long(), dim=1) - 1, config.head_dim, config.rope_theta))
        additive = pad_keys(to_additive_mask(prefix_mask, tokens.dtype), slots)  # [B, 1, P, S]
        prefix_slots = torch.arange(prefix_len, device=device)
        x = tokens
        for index, (layer, key_buffer, value_buffer) in enumerate(zip(self.layers, keys, values)):
            last = index == len(self.layers) - 1
            x = layer(x, cos, sin, additive, kv_buffer=(key_buffer, value_buffer), kv_slots=prefix_slots, last_only=last)
        logits = self.lm_head(self.final_norm(x[:, -1]))  # [B, V]

        valid_count = valid.sum(dim=1, keepdim=True)  # [B, 1]
        steps = torch.arange(max_new_tokens, device=device)
        window_start = prefix_len - valid_count  # [B, 1]
        masks = None  # (the fused kernels attend over [first, slot] without one)
        if fused is None:
            slot_index = torch.arange(prefix_len + max_new_tokens, device=device)
            sees = (slot_index[None, None, :] >= window_start[:, :, None]) & (
                slot_index[None, None, :] <= (prefix_len + steps)[None, :, None]
            )  # [B, T, S]
            masks = pad_keys(to_additive_mask(sees[:, None], tokens.dtype), slots)
        decode_positions = valid_count + config.decoding_position_offset + steps[None, :]  # [B, T]
        decode_cos, decode_sin = (table[:, None] for table in rope_cos_sin(decode_positions, config.head_dim, config.rope_theta))
        cache = DecodingCache(
            keys=keys,
            values=values,
            masks=masks,
            cos=decode_cos,
            sin=decode_sin,
            slots=prefix_len + steps,
            first=window_start[:, 0],
            fused=None if fused is None else DecodingLayers.build(fused, self.layers, keys, values),
        )
        return cache, logits

    def decoding_slots(self, cameras: int, text_length: int, max_new_tokens: int) -> int:
        """The slots of `prepare_decoding`'s k/v caches: every camera's image tokens, the prompt, the new tokens,
        rounded up to a multiple of 8 (SDPA's masks cover a multiple of 8 keys; the rest masked)."""
        return aligned_key_count(cameras * self.config.tokens_per_image + text_length + max_new_tokens)

    def decode_step(self, cache: DecodingCache, token: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """Feed the token decoded at `step` (long `[1]`) for every row (`token` long `[B]`): writes its k/v into the
        cache and returns the logits `[B, V]` of the next token. Shapes never change with `step`, so one compiled
        graph serves every step."""
        x = self.embed_tokens(token[:, None])
        x = x * torch.tensor(math.sqrt(x.shape[-1]), dtype=x.dtype)  # [B, 1, D]
        cos, sin = cache.cos.index_select(2, step), cache.sin.index_select(2, step)
        slot = cache.slots.index_select(0, step)
        if cache.fused is not None:  # the fused kernels: attention over the slots [first, slot], no mask
            x = decode_layers_(cache.fused, x[:, 0], cos[:, 0], sin[:, 0], cache.first, slot)
            return self.lm_head(self.final_norm(x))
        mask = cache.masks.index_select(2, step)  # [B, 1, 1, S]
        for layer, key_buffer, value_buffer in zip(self.layers, cache.keys, cache.values):
            x = layer(x, cos, sin, mask, kv_buffer=(key_buffer, value_buffer), kv_slots=slot)
        return self.lm_head(self.final_norm(x[:, -1]))

    @torch.no_grad()
    def generate_actions(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
        *,
        processor: PI0FastProcessor,
        max_new_tokens: int | None = None,
        temperature: float = 0.0,
        generator: torch.Generator | None = None,
        **unused: Any,
    ) -> torch.Tensor:
        """Decode tokens (`generate_tokens`) and turn them into action chunks with `processor.extract_actions`
        (openpi's `extract_actions`: the FAST tokens between `Action: ` and `|`, FAST-decoded; an undecodable
        chunk is zeros, with a warning).

        Returns:
            float32 `[B, action_horizon, action_dim]` actions in normalized model space, on the model's device
            (`processor.postprocess_actions` maps them to robot units).
        """
        tokens = self.generate_tokens(
            pixel_values, image_masks, input_ids, attention_mask, token_ar_mask, max_new_tokens, temperature, generator
        )
        actions = processor.extract_actions(tokens.cpu().numpy())
        return torch.from_numpy(actions).to(pixel_values.device)

    # -- input checks --------------------------------------------------------------------------------------------------

    def _check_inputs(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
        token_loss_mask: torch.Tensor | None = None,
    ) -> None:
        """Validate the model inputs; errors name the argument, the expected and the actual shape / dtype / range."""
        config = self.config
        size = config.image_size
        if not isinstance(pixel_values, torch.Tensor) or pixel_values.dim() != 5:
            raise ValueError(
                f"pixel_values must be a float tensor [B, num_cameras={config.num_cameras}, 3, {size}, {size}], "
                f"got {_describe(pixel_values)}"
            )
        batch = pixel_values.shape[0]
        _check_tensor("pixel_values", pixel_values, (batch, config.num_cameras, 3, size, size), floating=True)
        low, high = pixel_values.aminmax()
        if low < -1.001 or high > 1.001 or not (torch.isfinite(low) and torch.isfinite(high)):
            raise ValueError(
                f"pixel_values must lie in [-1, 1] (uint8 images map to x / 255 * 2 - 1), got range "
                f"[{low.item():.4g}, {high.item():.4g}]"
            )
        _check_tensor("image_masks", image_masks, (batch, config.num_cameras), dtypes=(torch.bool,))
        if not isinstance(input_ids, torch.Tensor) or input_ids.dim() != 2 or input_ids.shape[0] != batch or input_ids.shape[1] < 2:
            raise ValueError(f"input_ids must be [B={batch}, L] with L >= 2, got {_describe(input_ids)}")
        _check_tensor("input_ids", input_ids, tuple(input_ids.shape), dtypes=(torch.long, torch.int32))
        integer_or_bool = (torch.bool, torch.long, torch.int32)
        _check_tensor("attention_mask", attention_mask, tuple(input_ids.shape), dtypes=integer_or_bool)
        _check_tensor("token_ar_mask", token_ar_mask, tuple(input_ids.shape), dtypes=integer_or_bool)
        if token_loss_mask is not None:
            _check_tensor("token_loss_mask", token_loss_mask, tuple(input_ids.shape), dtypes=integer_or_bool)


def left_to_right_align(
    tokens: torch.Tensor, valid: torch.Tensor, mask: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """openpi's `left_to_right_align`: rotate each row so that its last valid token is the last one.

    Row b is rolled left by `n_b` = (index of its last valid token + 1): the trailing padding moves to the front.
    `tokens` `[B, P, D]`, `valid` bool `[B, P]` and `mask` bool `[B, P, P]` (both axes) move together.
    """
    length = valid.shape[1]
    index = torch.arange(length, device=valid.device)
    shift = (valid * index).amax(dim=1, keepdim=True) + 1  # [B, 1]
    order = (index[None, :] + shift) % length  # [B, P]: new position i holds old position order[b, i]
    tokens = tokens.gather(1, order[..., None].expand(-1, -1, tokens.shape[-1]))
    valid = valid.gather(1, order)
    mask = mask.gather(1, order[..., None].expand(-1, -1, length)).gather(2, order[:, None, :].expand(-1, length, -1))
    return tokens, valid, mask


def token_log_probs(logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """float32 log-probability `[...]` of `targets` (long `[...]`) under `logits` `[..., V]` (log-softmax in float32)."""
    logits = logits.float()
    return logits.gather(-1, targets.long()[..., None])[..., 0] - torch.logsumexp(logits, dim=-1)
