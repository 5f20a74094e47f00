"""Attention as the π0 model runs it: one call per layer over the tokens of a pass, grouped-query (one kv head).

Sampling lays its k/v cache out so that every query sees one contiguous range of keys: each sample's valid prefix
tokens are moved to the end of the prefix slots (padding and masked cameras before them), and the suffix follows.
Query rows then come in groups that share where their keys end: the prefix sees `[first, prefix_len)`; π0's state
token `[first, prefix_len + 1)` (the prefix and itself); its action tokens and all of π0.5's suffix
`[first, prefix_len + suffix_len)`. `first[b]` is where sample b's valid prefix starts ([`KeyRanges`]).

Two kernels read those ranges ([`attend`]):

- `"sdpa"`: `scaled_dot_product_attention` with an additive mask built from the ranges once per pass (no mask at all
  when no sample is padded and every row sees every key), shared by every layer; its key count is padded to a
  multiple of 8 (`pi0_torch.masks.sdpa_with_mask`: cuDNN fails on other masks), which the k/v buffers' slots match;
- `"varlen"`: FlashAttention's variable-length kernel (`aten._flash_attention_forward`, the kernel behind
  `torch.nn.attention.varlen.varlen_attn`; CUDA, bf16/fp16), which takes each sample's first key and key count as
  device tensors (`seqused_k`) and needs no mask. torch 2.10 and 2.11 take `seqused_k` there only (`varlen_attn`
  gained it in 2.12), so it is called directly.

With one kv head (every released π0), the query heads are folded into the query length: `[B, T, N, H]` is viewed as
`[B, 1, T * N, H]` (a view, no copy), so no kernel expands the kv head N times.

```python
>>> import torch
>>> ranges = KeyRanges(first=torch.tensor([0, 2]), group_rows=(1, 2), group_ends=(3, 5))
>>> plan = plan_attention(ranges, num_heads=1, kv_heads=1, dtype=torch.float32, kernel="sdpa")
>>> (plan.mask[1, 0] == 0).int()  # sample 1: its prefix starts at key 2; row 0 stops after key 2, rows 1-2 see all
tensor([[0, 0, 1, 0, 0, 0, 0, 0],
        [0, 0, 1, 1, 1, 0, 0, 0],
        [0, 0, 1, 1, 1, 0, 0, 0]], dtype=torch.int32)
>>> plan.mask.shape  # 5 keys, padded to 8 (-inf: never attended)
torch.Size([2, 1, 3, 8])

```
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from pi0_torch.masks import pad_keys, sdpa_with_mask, to_additive_mask

KERNELS = ("auto", "sdpa", "varlen")
_FLASH_FORWARD = getattr(torch.ops.aten, "_flash_attention_forward", None)
# per-sample key counts: torch >= 2.10 (the GPU image's 2.11 included)
VARLEN_AVAILABLE = _FLASH_FORWARD is not None and "seqused_k" in str(_FLASH_FORWARD.default._schema)


def flash_varlen(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, cu_seq_q: torch.Tensor,
                 cu_seq_k: torch.Tensor, max_q: int, max_k: int, seqused_k: torch.Tensor) -> torch.Tensor:
    """FlashAttention's variable-length forward: sequence i's queries are rows `[cu_seq_q[i], cu_seq_q[i + 1])` of
    `query` `[total_q, heads, H]`, its keys the `seqused_k[i]` rows of `key` / `value` `[total_k, kv_heads, H]` from
    `cu_seq_k[i]`; logits scaled by `H ** -0.5`. Returns `[total_q, heads, H]`."""
    return _FLASH_FORWARD(query, key, value, cu_seq_q, cu_seq_k, max_q, max_k, 0.0, False, False, seqused_k=seqused_k)[0]


@dataclass(frozen=True)
class KeyRanges:
    """Which keys the queries of one pass see: sample b's rows of group g see the keys `[first[b], group_ends[g])`.

    `group_rows` are the query rows (tokens) of each group in order; `padded` is False when every `first` is 0
    (known on the host, it lets the "sdpa" kernel run without a mask).
    """

    first: torch.Tensor  # long [B]
    group_rows: tuple[int, ...]
    group_ends: tuple[int, ...]
    padded: bool = True

    @property
    def num_keys(self) -> int:
        return max(self.group_ends)


@dataclass(frozen=True)
class VarlenGroup:
    """One FlashAttention varlen call: query rows `[row_start, row_start + rows)` of every sample."""

    row_start: int
    rows: int
    query_starts: torch.Tensor  # int32 [B + 1]: sample b's folded query rows start at query_starts[b]
    key_starts: torch.Tensor  # int32 [B + 1]: ... and its keys at key_starts[b] of the flattened k/v buffer
    key_counts: torch.Tensor  # int32 [B]: how many keys it reads from there
    max_keys: int


@dataclass(frozen=True)
class AttentionPlan:
    """How one pass attends, built once per pass and shared by every layer ([`plan_attention`])."""

    kernel: str  # "sdpa" or "varlen"
    num_keys: int  # keys the pass reads (the k/v given to `attend` may have more slots after them)
    fold_heads: bool  # one kv head: query heads folded into the query length
    mask: torch.Tensor | None = None  # "sdpa": additive [B, 1, rows, aligned_key_count(num_keys)], rows 1, T or T * N
    varlen: tuple[VarlenGroup, ...] = ()  # "varlen": one call per group of rows


def choose_kernel(kernel: str, device: torch.device, dtype: torch.dtype, kv_heads: int, head_dim: int) -> str:
    """The kernel a pass runs: `kernel` if it is "sdpa" or "varlen", else ("auto") varlen where FlashAttention's
    variable-length kernel applies (CUDA with compute capability >= 8.0, bf16 / fp16, one kv head, head size a
    multiple of 8 up to 256, a torch whose flash kernel takes `seqused_k`), sdpa elsewhere."""
    if kernel not in KERNELS:
        raise ValueError(f"attention kernel must be one of {KERNELS}, got {kernel!r}")
    usable = (
        VARLEN_AVAILABLE
        and device.type == "cuda"
        and dtype in (torch.bfloat16, torch.float16)
        and kv_heads == 1
        and head_dim % 8 == 0
        and head_dim <= 256
        and _compute_capability(device) >= (8, 0)
    )
    if kernel == "varlen" and not usable:
        raise ValueError(
            "attention kernel 'varlen' needs FlashAttention's varlen kernel with seqused_k (torch >= 2.10), a "
            f"CUDA device of compute capability >= 8.0, bf16/fp16, one kv head and head size <= 256; got {device}, "
            f"{dtype}, {kv_heads} kv heads, head size {head_dim}"
        )
    if kernel == "auto":
        return "varlen" if usable else "sdpa"
    return kernel


_compute_capability = functools.lru_cache(maxsize=None)(torch.cuda.get_device_capability)  # (per device, once)


def plan_attention(ranges: KeyRanges, num_heads: int, kv_heads: int, dtype: torch.dtype, kernel: str, key_slots: int | None = None) -> AttentionPlan:
    """Build the attention of a pass with key ranges for `kernel` ("sdpa" or "varlen", see [`choose_kernel`]).

    `key_slots` is the slot count of the k/v buffers `attend` will get (the flattened layout the varlen kernel
    indexes; default `ranges.num_keys`). Everything is computed here once; `attend` only reads it.
    """
    first = ranges.first
    batch, device = first.shape[0], first.device
    fold = kv_heads == 1
    if kernel == "varlen":
        slots = ranges.num_keys if key_slots is None else key_slots
        sample = torch.arange(batch + 1, device=device, dtype=torch.int32)
        key_starts = torch.cat([sample[:-1] * slots + first.int(), sample[-1:] * slots])
        groups, row_start = [], 0
        for rows, end in zip(ranges.group_rows, ranges.group_ends):
            groups.append(VarlenGroup(row_start, rows, sample * (rows * num_heads), key_starts, (end - first).int(), end))
            row_start += rows
        return AttentionPlan("varlen", ranges.num_keys, fold, varlen=tuple(groups))
    if not ranges.padded and len(ranges.group_ends) == 1 and ranges.group_ends[0] == ranges.num_keys:
        return AttentionPlan("sdpa", ranges.num_keys, fold)  # every row sees every key
    keys = torch.arange(ranges.num_keys, device=device)
    visible = keys[None, :] >= first[:, None]  # [B, keys]
    repeat = num_heads if fold else 1  # folded rows: each token's N heads are N rows
    if len(ranges.group_ends) == 1:
        rows_mask = (visible & (keys < ranges.group_ends[0]))[:, None, None, :]  # [B, 1, 1, keys]: every row alike
    else:
        rows_mask = torch.cat(
            [(visible & (keys < end))[:, None, :].expand(-1, rows * repeat, -1) for rows, end in zip(ranges.group_rows, ranges.group_ends)],
            dim=1,
        )[:, None]  # [B, 1, rows, keys]
    return AttentionPlan("sdpa", ranges.num_keys, fold, mask=pad_keys(to_additive_mask(rows_mask, dtype)))


def attend(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, plan: AttentionPlan) -> torch.Tensor:
    """Attention of `query` `[B, T, N, H]` (post-RoPE, unscaled; contiguous) over `key` / `value` `[B, K, slots, H]`
    (the first `plan.num_keys` slots are read; with a mask, its aligned key count, where the caller's buffers have
    that many finite slots), logits scaled by `H ** -0.5`, softmax in float32. Returns `[B * T, N * H]`, the layout of
    the o-projection's input."""
    batch, tokens, heads, head_dim = query.shape
    if plan.kernel == "varlen":
        return _attend_varlen(query, key, value, plan)
    if plan.fold_heads:  # [B, 1, T * N, H] against the one kv head
        query = query.view(batch, 1, tokens * heads, head_dim)
    else:
        query = query.transpose(1, 2)
    if plan.mask is None:
        if key.shape[2] != plan.num_keys:
            key, value = key[:, :, : plan.num_keys], value[:, :, : plan.num_keys]
        attended = F.scaled_dot_product_attention(query, key, value, enable_gqa=not plan.fold_heads)
    else:
        mask = plan.mask if plan.mask.dtype == query.dtype else plan.mask.to(query.dtype)  # (autocast)
        attended = sdpa_with_mask(query, key, value, mask, enable_gqa=not plan.fold_heads)
    if plan.fold_heads:  # (a reshape: a decomposed SDPA, as exported, may return other strides)
        return attended.reshape(batch * tokens, heads * head_dim)
    return attended.transpose(1, 2).reshape(batch * tokens, heads * head_dim)


def _attend_varlen(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, plan: AttentionPlan) -> torch.Tensor:
    """FlashAttention's varlen kernel, one call per group of rows: the folded query rows of sample b read the
    `key_counts[b]` keys from `key_starts[b]` of the flattened (one kv head) buffer."""
    batch, tokens, heads, head_dim = query.shape
    folded = query.view(batch, tokens * heads, 1, head_dim)
    flat_key, flat_value = key.view(-1, 1, head_dim), value.view(-1, 1, head_dim)  # [B * slots, 1, H], views
    outputs = []
    for group in plan.varlen:
        rows = folded[:, group.row_start * heads : (group.row_start + group.rows) * heads].reshape(-1, 1, head_dim)
        outputs.append(flash_varlen(
            rows, flat_key, flat_value, group.query_starts, group.key_starts, group.rows * heads, group.max_keys,
            seqused_k=group.key_counts,
        ).view(batch, group.rows * heads, head_dim))
    attended = outputs[0] if len(outputs) == 1 else torch.cat(outputs, dim=1)
    return attended.view(batch * tokens, heads * head_dim)
