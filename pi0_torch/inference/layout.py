"""How a pass lays out its tokens so that each one attends to a single contiguous range of keys (no mask matrix).

Each sample's valid prefix tokens are moved to the end of the prefix slots, with padding and masked cameras before
them (`compact_prefix`), and the suffix follows. The result equals openpi's prefix-LM mask on the original layout
(tests compare the two with `pi0_torch.masks.prefix_lm_mask`): attention only depends on which tokens are valid and
their order (positions count valid tokens), and no valid token attends to an invalid one.

The layout is decided on the host from the inputs' checks (`InputFacts`, read in the model's one device-to-host copy);
after that nothing waits for the device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from pi0_torch.inference.attention import AttentionPlan, KeyRanges, plan_attention
from pi0_torch.kernels.reference import rope_cos_sin

if TYPE_CHECKING:
    from pi0_torch.models.configuration_pi0 import PI0Config


@dataclass
class StreamPass:
    """How one expert's tokens take part in a pass, the same in every layer: their count per sample, RoPE tables
    `[B or 1, T, 1, H]`, what they attend to, and their k/v slots (`first_slot` on, long `slots` `[T]`)."""

    tokens: int
    cos: torch.Tensor
    sin: torch.Tensor
    attention: AttentionPlan
    first_slot: int
    slots: torch.Tensor


@dataclass(frozen=True)
class PrefixLayout:
    """How a call lays out its prefix, decided on the host from its checked inputs (see `InputFacts.layout`): the
    cameras that go through the vision tower (those some sample shows, in config order) and `length` prefix slots,
    each sample's valid tokens at their end (the longest sample fills them; `padded`: some sample has fewer)."""

    cameras: tuple[int, ...]
    length: int
    padded: bool


@dataclass(frozen=True)
class InputFacts:
    """What the input checks read from the device, in their one read: which cameras each sample shows and how many
    valid text tokens it has."""

    image_masks: tuple[tuple[bool, ...], ...]
    text_counts: tuple[int, ...]
    text_length: int

    def layout(self, tokens_per_image: int, bucket: int = 1) -> PrefixLayout:
        """The prefix layout, `length` rounded up to a multiple of `bucket` (CUDA graphs: fewer distinct layouts)."""
        cameras = tuple(c for c in range(len(self.image_masks[0])) if any(shown[c] for shown in self.image_masks))
        valid = [tokens_per_image * sum(shown[c] for c in cameras) + text for shown, text in zip(self.image_masks, self.text_counts)]
        total = tokens_per_image * len(cameras) + self.text_length
        length = min(total, -(-max(1, *valid) // bucket) * bucket)
        return PrefixLayout(cameras, length, any(count < length for count in valid))


def camera_inputs(pixel_values: torch.Tensor, image_masks: torch.Tensor, layout: PrefixLayout) -> tuple[torch.Tensor, torch.Tensor]:
    """The images and masks of the layout's cameras (all of them, usually: the tensors themselves)."""
    if len(layout.cameras) == pixel_values.shape[1]:
        return pixel_values, image_masks
    if not layout.cameras:
        return pixel_values[:, :0], image_masks[:, :0]
    return (torch.cat([pixel_values[:, c : c + 1] for c in layout.cameras], dim=1),
            torch.cat([image_masks[:, c : c + 1] for c in layout.cameras], dim=1))


def compact_prefix(tokens: torch.Tensor, valid: torch.Tensor, layout: PrefixLayout) -> tuple[torch.Tensor, torch.Tensor]:
    """Move each sample's valid tokens, in order, to the end of `layout.length` slots: `tokens` `[B, P, D]`, `valid`
    `[B, P]` -> tokens `[B * length, D]` (a tensor of its own, not a view: a compiled layer sees the same kind of input
    in every layer) and each sample's first valid slot `[B]` (invalid tokens before it)."""
    first = layout.length - valid.sum(dim=1)
    batch, count = valid.shape
    if count == layout.length and not layout.padded:
        return tokens.flatten(0, 1).clone(), first
    # where a stable sort of `valid` would put each token: the invalid ones first, then the valid ones, each in order
    # (counted with cumsum and placed with a scatter rather than sorted: ONNX has no stable sort)
    flags = valid.long()
    invalid_count = count - flags.sum(dim=1, keepdim=True)
    sorted_slot = torch.where(valid, invalid_count + flags.cumsum(dim=1), (1 - flags).cumsum(dim=1)) - 1
    source = torch.arange(count, device=valid.device).expand(batch, count)
    order = torch.zeros_like(source).scatter_(1, sorted_slot, source)[:, count - layout.length :]  # [B, length]
    rows = order + torch.arange(batch, device=order.device)[:, None] * count
    return tokens.flatten(0, 1).index_select(0, rows.flatten()), first


def rope_tables(config: PI0Config, first: torch.Tensor, slots: int) -> tuple[torch.Tensor, torch.Tensor]:
    """RoPE's `cos`, `sin` `[B, slots, H]` (`rope_cos_sin`) of every slot of a pass: slot s of sample b holds position
    `s - first[b]` (the valid prefix tokens count from 0 at `first[b]`, and the suffix continues after them). One
    table per call; each stream reads its slots' rows."""
    positions = torch.arange(slots, device=first.device)[None, :] - first[:, None]
    return rope_cos_sin(positions, config.head_dim, config.rope_theta)


def prefix_stream(
    config: PI0Config, first: torch.Tensor, layout: PrefixLayout, kernel: str, slots: int, dtype: torch.dtype,
    rope: tuple[torch.Tensor, torch.Tensor],
) -> StreamPass:
    """The prefix in slots `[0, length)`: sample b's valid tokens from `first[b]` at positions 0, 1, ...; they see
    each other (bidirectional) and nothing after. `rope`: the call's `rope_tables`."""
    return suffix_stream(config, first, layout, 0, (layout.length,), kernel, slots, dtype, rope)


def suffix_stream(
    config: PI0Config, first: torch.Tensor, layout: PrefixLayout, first_slot: int, group_rows: tuple[int, ...], kernel: str,
    slots: int, dtype: torch.dtype, rope: tuple[torch.Tensor, torch.Tensor],
) -> StreamPass:
    """Tokens in slots from `first_slot` (the suffix's: after the prefix; the prefix's: `prefix_stream`) at the
    positions of `rope`, the call's `rope_tables`; each group of rows sees the valid prefix and the slots up to its own
    end."""
    tokens = sum(group_rows)
    cos, sin = (table[:, first_slot : first_slot + tokens] for table in rope)
    ends = tuple(first_slot + sum(group_rows[: index + 1]) for index in range(len(group_rows)))
    plan = plan_attention(
        KeyRanges(first, group_rows, ends, padded=layout.padded), config.num_attention_heads,
        config.num_key_value_heads, dtype, kernel, key_slots=slots,
    )
    slot_index = torch.arange(first_slot, first_slot + tokens, device=first.device)
    return StreamPass(tokens, cos[:, :, None], sin[:, :, None], plan, first_slot, slot_index)
