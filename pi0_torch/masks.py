"""Attention masks and masked attention through `scaled_dot_product_attention`.

Convention: a boolean mask is True where a query (row) may attend to a key (column). Shapes: `[L, S]` for one
pattern, `[B, L, S]` (one mask per batch element, shared by all heads) or `[B, 1, L, S]` / `[B, heads, L, S]` (the
layouts SDPA broadcasts).

Every pattern is written once, as a FlexAttention-style *mask rule* `mask_mod(b, h, q_idx, kv_idx) -> bool` built
from elementwise index arithmetic. The same rule gives

- a dense bool mask (`mask_from_mod`, evaluated on broadcast index grids), fed to SDPA by `masked_attention`;
- a block-sparse FlexAttention `BlockMask` (`to_block_mask`), where whole 128x128 tiles that the rule masks are
  skipped.

The module reads top to bottom: mask rules -> dense masks (causal, RoboVLMs' claw, window+chunk, openpi's prefix-LM)
-> RoboVLMs' chunk selection of training targets -> conversions (additive, broadcast, BlockMask) -> attention.

Compute: a dense mask given to SDPA saves nothing: every score is still computed, then hidden, so it costs what no
mask costs (or a little more, for reading the mask). Only a block-sparse FlexAttention kernel skips work, and only
for tiles (128 tokens a side by default) that are masked entirely.
See `docs/masks.md` and `benchmarks/bench_masks.py`.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

try:  # FlexAttention appeared in torch 2.5
    from torch.nn.attention.flex_attention import BlockMask, create_block_mask
except ImportError:  # pragma: no cover - depends on the installed torch
    BlockMask = None  # type: ignore[assignment,misc]
    create_block_mask = None  # type: ignore[assignment]

# openpi's masked-logit value (gemma/modules.py): large and finite, so that a query row with every key masked
# gets a uniform softmax (the mean of the values) instead of NaN.
MASKED_LOGIT = -2.3819763e38

# FlexAttention's tile size: block sparsity skips work only in whole BLOCK_SIZE x BLOCK_SIZE tiles.
BLOCK_SIZE = 128

# Every mask given to SDPA is contiguous with its key count a multiple of this (keys padded to match, masked out):
# cuDNN's attention reads the mask in 16-byte vectors and fails on a sliced or odd-length one ("misaligned address",
# and a CUDA context lost; seen with π0-FAST's decoding masks on an H200). See `sdpa_with_mask`.
KEY_ALIGNMENT = 8

# mask_mod(b, h, q_idx, kv_idx) -> bool tensor; the arguments are integer index tensors that broadcast together.
MaskMod = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def _check_count(name: str, value: int, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")


def _as_4d(mask: torch.Tensor, name: str) -> torch.Tensor:
    """`[L, S]` -> `[1, 1, L, S]`, `[B, L, S]` -> `[B, 1, L, S]`, `[B, heads, L, S]` unchanged (views)."""
    if mask.dim() == 2:
        return mask[None, None]
    if mask.dim() == 3:
        return mask[:, None]
    if mask.dim() == 4:
        return mask
    raise ValueError(f"{name} must be [L, S], [B, L, S] or [B, heads, L, S], got shape {tuple(mask.shape)}")


def _require_bool(mask: torch.Tensor, name: str) -> None:
    if mask.dtype != torch.bool:
        raise TypeError(
            f"{name} must be a bool mask (True = attend), got dtype {mask.dtype}; convert a 0/1 mask with "
            f"`.bool()` (an additive 0/-inf mask would be inverted by that, so build the bool mask instead)"
        )


# ----------------------------------------------------------------------------------------------------------------
# Mask rules. Each returns a FlexAttention mask_mod; the arithmetic is elementwise, so the rule works on scalar
# indices (FlexAttention vmaps it) and on broadcast index grids (`mask_from_mod`).
# ----------------------------------------------------------------------------------------------------------------


def causal_mask_mod() -> MaskMod:
    """Rule of the standard causal mask: query i sees keys j <= i."""

    def causal(b: torch.Tensor, h: torch.Tensor, q_idx: torch.Tensor, kv_idx: torch.Tensor) -> torch.Tensor:
        return kv_idx <= q_idx

    return causal


def claw_mask_mod(k: int) -> MaskMod:
    """Rule of RoboVLMs' claw matrix: row i has ones at columns i..i+k (a forward band of width k+1)."""
    _check_count("k", k, 0)

    def claw(b: torch.Tensor, h: torch.Tensor, q_idx: torch.Tensor, kv_idx: torch.Tensor) -> torch.Tensor:
        return (kv_idx >= q_idx) & (kv_idx <= q_idx + k)

    return claw


def window_chunk_mask_mod(window: int) -> MaskMod:
    """Rule of the window+chunk pattern: key j is visible from query i iff j <= i or j < window.

    For a window row (i < window) that is "every window key, no chunk key"; for a chunk row (i >= window) it is
    "keys 0..i" (the whole window, then causal inside the chunk).
    """
    _check_count("window", window, 0)

    def window_chunk(b: torch.Tensor, h: torch.Tensor, q_idx: torch.Tensor, kv_idx: torch.Tensor) -> torch.Tensor:
        return (kv_idx <= q_idx) | (kv_idx < window)

    return window_chunk


def prefix_lm_mask_mod(valid: torch.Tensor, block_flags: torch.Tensor) -> MaskMod:
    """Rule of openpi's block-causal ("prefix-LM") mask; see `prefix_lm_mask` for the arguments.

    With `c = cumsum(block_flags)` per batch element, query i sees key j iff `c[j] <= c[i]` and both are valid.
    The rule reads two `[B, L]` vectors, never an `[L, L]` table.
    """
    if valid.dim() != 2:
        raise ValueError(f"valid must be [B, L], got shape {tuple(valid.shape)}")
    batch_size, length = valid.shape
    if (
        block_flags.dim() not in (1, 2)
        or block_flags.shape[-1] != length
        or (block_flags.dim() == 2 and block_flags.shape[0] not in (1, batch_size))
    ):
        raise ValueError(
            f"block_flags must be [L] or [B, L] = [{length}] or [{batch_size}, {length}] to match valid, "
            f"got shape {tuple(block_flags.shape)}"
        )
    valid = valid.bool()
    block_index = torch.cumsum(block_flags.to(valid.device).long().expand_as(valid), dim=1)  # [B, L]

    def prefix_lm(b: torch.Tensor, h: torch.Tensor, q_idx: torch.Tensor, kv_idx: torch.Tensor) -> torch.Tensor:
        same_or_earlier_block = block_index[b, kv_idx] <= block_index[b, q_idx]
        return same_or_earlier_block & valid[b, q_idx] & valid[b, kv_idx]

    return prefix_lm


def dense_mask_mod(mask: torch.Tensor) -> MaskMod:
    """Rule that looks up an arbitrary bool mask `[L, S]`, `[B, L, S]` or `[B, heads, L, S]` (B, heads may be 1).

    Use it only for masks with no index formula; an analytic rule lets FlexAttention skip the table entirely.
    """
    _require_bool(mask, "mask")
    table = _as_4d(mask, "mask")  # [B, heads, L, S]
    per_batch, per_head = table.shape[0] > 1, table.shape[1] > 1  # a size-1 dim serves every batch / head

    def lookup(b: torch.Tensor, h: torch.Tensor, q_idx: torch.Tensor, kv_idx: torch.Tensor) -> torch.Tensor:
        # (a size-1 dim is indexed by a zero tensor, not 0: torch 2.10's vmap in `create_mask` refuses a Python int
        # beside tensor indices, "calling .item() on a Tensor")
        return table[b if per_batch else b * 0, h if per_head else h * 0, q_idx, kv_idx]

    return lookup


# ----------------------------------------------------------------------------------------------------------------
# Dense masks.
# ----------------------------------------------------------------------------------------------------------------


def mask_from_mod(
    mask_mod: MaskMod,
    q_len: int,
    kv_len: int,
    batch_size: int | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Evaluate a mask rule on index grids: bool `[q_len, kv_len]`, or `[batch_size, q_len, kv_len]`.

    Head index 0 is used (the rules here do not depend on the head). Equals FlexAttention's `create_mask`
    without needing FlexAttention or vmap.

    >>> print(format_mask(mask_from_mod(claw_mask_mod(1), 3, 4)))
    1 1 . .
    . 1 1 .
    . . 1 1
    """
    _check_count("q_len", q_len, 0)
    _check_count("kv_len", kv_len, 0)
    q_idx = torch.arange(q_len, device=device)[:, None]  # [L, 1]
    kv_idx = torch.arange(kv_len, device=device)[None, :]  # [1, S]
    head = torch.zeros((), dtype=torch.long, device=device)
    if batch_size is None:
        batch, shape = head, (q_len, kv_len)
    else:
        _check_count("batch_size", batch_size, 1)
        batch, shape = torch.arange(batch_size, device=device)[:, None, None], (batch_size, q_len, kv_len)
    mask = mask_mod(batch, head, q_idx, kv_idx).bool()
    return mask if mask.shape == shape else mask.expand(shape).contiguous()


def causal_mask(n: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Standard causal mask, bool `[n, n]`: query i sees keys 0..i.

    >>> print(format_mask(causal_mask(4)))
    1 . . .
    1 1 . .
    1 1 1 .
    1 1 1 1
    """
    _check_count("n", n, 0)
    return mask_from_mod(causal_mask_mod(), n, n, device=device)


def claw_matrix(
    n: int, k: int, device: torch.device | str | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """RoboVLMs' `claw_matrix(n, k)`: `[n, n]` with ones where `i <= j <= i + k`, zeros elsewhere.

    Like RoboVLMs (`triu(ones) * tril(ones, diagonal=k)`) the result is a 0/1 float tensor of the default dtype;
    pass `dtype=torch.bool` for a mask. In RoboVLMs it is a data-selection mask (see `generate_chunk_data`);
    used as an attention mask, query i sees itself and the k keys after it.

    >>> print(format_mask(claw_matrix(5, 2)))
    1 1 1 . .
    . 1 1 1 .
    . . 1 1 1
    . . . 1 1
    . . . . 1
    >>> claw_matrix(3, 1)
    tensor([[1., 1., 0.],
            [0., 1., 1.],
            [0., 0., 1.]])
    """
    _check_count("n", n, 0)
    mask = mask_from_mod(claw_mask_mod(k), n, n, device=device)
    return mask.to(torch.get_default_dtype() if dtype is None else dtype)


def window_chunk_mask(window: int, chunk: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Window fully connected + chunk causal, bool `[window + chunk, window + chunk]`.

    Window rows (0..window-1) see the whole window and nothing of the chunk; chunk row i (global index,
    window <= i < window + chunk) sees keys 0..i: the whole window plus the chunk causally. Some write-ups call
    this pattern a "claw"; it is not RoboVLMs' `claw_matrix`. `window_chunk_mask(0, n)` is `causal_mask(n)`.

    >>> print(format_mask(window_chunk_mask(3, 2)))
    1 1 1 . .
    1 1 1 . .
    1 1 1 . .
    1 1 1 1 .
    1 1 1 1 1
    """
    _check_count("chunk", chunk, 0)
    return mask_from_mod(window_chunk_mask_mod(window), window + chunk, window + chunk, device=device)


def prefix_lm_mask(valid: torch.Tensor, block_flags: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """openpi's block-causal ("prefix-LM") mask and the matching RoPE positions.

    A token whose block flag is set starts a new block; tokens see their own block and every earlier block:
    with `c = cumsum(block_flags)`, query i attends key j iff `c[j] <= c[i]` and both tokens are valid.

    Args:
        valid: bool `[B, L]`, False for padding and masked cameras.
        block_flags: bool or int `[L]` or `[B, L]`.

    Returns:
        `(mask, positions)`: bool `[B, L, L]` and long `[B, L]` with `positions = cumsum(valid) - 1` (padding does
        not advance the position).

    Example: two prefix tokens (the second is padding), then a state token and two action tokens (π0's layout):

    >>> valid = torch.tensor([[True, False, True, True, True]])
    >>> mask, positions = prefix_lm_mask(valid, torch.tensor([0, 0, 1, 1, 0]))
    >>> print(format_mask(mask[0]))
    1 . . . .
    . . . . .
    1 . 1 . .
    1 . 1 1 1
    1 . 1 1 1
    >>> positions
    tensor([[0, 0, 1, 2, 3]])
    """
    mask_mod = prefix_lm_mask_mod(valid, block_flags)  # checks the shapes
    batch_size, length = valid.shape
    mask = mask_from_mod(mask_mod, length, length, batch_size, valid.device)
    positions = torch.cumsum(valid.long(), dim=1) - 1
    return mask, positions


def format_mask(mask: torch.Tensor) -> str:
    """Draw a 2-D mask as text: `1` where set (nonzero), `.` where masked, one row per line.

    >>> print(format_mask(torch.tensor([[True, False], [True, True]])))
    1 .
    1 1
    """
    if mask.dim() != 2:
        raise ValueError(f"mask must be 2-D [L, S] to draw, got shape {tuple(mask.shape)}")
    return "\n".join(" ".join("1" if bit else "." for bit in row) for row in mask.bool().tolist())


# ----------------------------------------------------------------------------------------------------------------
# RoboVLMs' chunk selection of training targets.
# ----------------------------------------------------------------------------------------------------------------


def generate_chunk_data(data: torch.Tensor, window_size: int, chunk_size: int) -> torch.Tensor:
    """Action-chunk targets from an episode slice: `[B, window + chunk, ...]` -> `[B, window, chunk, ...]`.

    Window step i gets the chunk of steps i+1 .. i+chunk. This is RoboVLMs' `generate_chunck_data`: it selects with
    `claw_matrix(window + chunk, chunk)` minus its diagonal, first `window` rows. Here the same selection is one
    gather with index `i + 1 + c`, so no `[B, window, window + chunk, ...]` intermediate is built. Any trailing
    shape and dtype; the result is a new contiguous tensor (not a view of `data`) and gradients flow through it.

    >>> episode = torch.arange(6).view(1, 6)  # window 4 + chunk 2
    >>> generate_chunk_data(episode, window_size=4, chunk_size=2)
    tensor([[[1, 2],
             [2, 3],
             [3, 4],
             [4, 5]]])
    """
    _check_count("window_size", window_size, 1)
    _check_count("chunk_size", chunk_size, 1)
    if data.dim() < 2 or data.shape[1] != window_size + chunk_size:
        raise ValueError(
            f"data must be [B, window_size + chunk_size, ...] = [B, {window_size + chunk_size}, ...] "
            f"(window_size={window_size}, chunk_size={chunk_size}), got shape {tuple(data.shape)}"
        )
    steps = torch.arange(window_size, device=data.device)[:, None]  # [W, 1]
    offsets = torch.arange(1, chunk_size + 1, device=data.device)[None, :]  # [1, C]
    return data[:, steps + offsets]  # [B, W, C, ...]


# ----------------------------------------------------------------------------------------------------------------
# Conversions.
# ----------------------------------------------------------------------------------------------------------------


def to_additive_mask(mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Bool mask -> additive float mask for SDPA: 0 where allowed, a large finite negative where masked.

    The negative is openpi's -2.3819763e38 clipped to what `dtype` can hold (float16: -65504), so a fully masked
    row stays finite. In float32 and bfloat16 it swamps every real logit and such a row averages the values; in
    float16 the row is finite but keeps the logits' differences.

    >>> to_additive_mask(torch.tensor([True, False]), torch.float32)
    tensor([ 0.0000e+00, -2.3820e+38])
    >>> to_additive_mask(torch.tensor([True, False]), torch.float16)
    tensor([     0., -65504.], dtype=torch.float16)
    """
    _require_bool(mask, "mask")
    if not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating dtype, got {dtype}")
    masked_value = max(MASKED_LOGIT, torch.finfo(dtype).min)
    additive = torch.zeros(mask.shape, dtype=dtype, device=mask.device)
    return additive.masked_fill_(~mask, masked_value)


def broadcast_mask(mask: torch.Tensor, batch_size: int, num_heads: int) -> torch.Tensor:
    """Expand `[L, S]`, `[B, L, S]` or `[B or 1, heads or 1, L, S]` to `[batch_size, num_heads, L, S]` (a view).

    >>> broadcast_mask(causal_mask(4), batch_size=2, num_heads=8).shape
    torch.Size([2, 8, 4, 4])
    """
    _check_count("batch_size", batch_size, 1)
    _check_count("num_heads", num_heads, 1)
    mask4 = _as_4d(mask, "mask")
    if mask4.shape[0] not in (1, batch_size) or mask4.shape[1] not in (1, num_heads):
        raise ValueError(
            f"mask of shape {tuple(mask.shape)} cannot broadcast to [batch_size={batch_size}, "
            f"num_heads={num_heads}, L, S]: its batch must be 1 or {batch_size} and its heads 1 or {num_heads}"
        )
    return mask4.expand(batch_size, num_heads, *mask4.shape[2:])


def flex_attention_available() -> bool:
    """True when the installed torch has FlexAttention (`torch.nn.attention.flex_attention`, torch >= 2.5)."""
    return create_block_mask is not None


def to_block_mask(
    mask_mod: MaskMod,
    q_len: int,
    kv_len: int,
    batch_size: int | None = None,
    num_heads: int | None = None,
    device: torch.device | str | None = None,
    block_size: int = BLOCK_SIZE,
) -> BlockMask:
    """Block-sparse FlexAttention `BlockMask` of a mask rule (for `flex_attention(..., block_mask=...)`).

    `batch_size`/`num_heads` None broadcast over batch/heads (give `batch_size` for per-sample rules such as
    `prefix_lm_mask_mod`). Tiles of `block_size` x `block_size` that the rule masks entirely are skipped by the
    kernel; partially masked tiles run the rule per element. Note: FlexAttention returns 0 for a query row with
    every key masked (`masked_attention` returns the mean of the values there, as openpi).

    >>> block_mask = to_block_mask(claw_mask_mod(255), 1024, 1024)  # 8 x 8 tiles, 21 of them computed
    >>> block_mask.sparsity()  # % of tiles skipped
    67.1875
    """
    if create_block_mask is None:
        raise RuntimeError(
            f"FlexAttention BlockMask needs torch >= 2.5 (torch.nn.attention.flex_attention); "
            f"installed torch is {torch.__version__}"
        )
    _check_count("block_size", block_size, 1)
    device = torch.get_default_device() if device is None else device
    return create_block_mask(mask_mod, batch_size, num_heads, q_len, kv_len, device=device, BLOCK_SIZE=block_size)


def block_mask_from_dense(mask: torch.Tensor, block_size: int = BLOCK_SIZE) -> BlockMask:
    """`BlockMask` of an arbitrary bool mask `[L, S]`, `[B, L, S]` or `[B, heads, L, S]` (lookup rule).

    Prefer `to_block_mask` with an analytic rule when the pattern has one.
    """
    _require_bool(mask, "mask")
    mask4 = _as_4d(mask, "mask")
    batch_size, num_heads, q_len, kv_len = mask4.shape
    return to_block_mask(
        dense_mask_mod(mask4),
        q_len,
        kv_len,
        batch_size=batch_size,
        num_heads=num_heads,
        device=mask.device,
        block_size=block_size,
    )


# ----------------------------------------------------------------------------------------------------------------
# Attention.
# ----------------------------------------------------------------------------------------------------------------


def aligned_key_count(keys: int) -> int:
    """`keys` rounded up to a multiple of `KEY_ALIGNMENT` (the key count of every mask given to SDPA)."""
    return -(-keys // KEY_ALIGNMENT) * KEY_ALIGNMENT


def pad_keys(mask: torch.Tensor, keys: int | None = None) -> torch.Tensor:
    """An additive mask `[..., L, S]` with its key axis padded to `keys` (default `aligned_key_count(S)`) by -inf
    columns: keys no row attends to, not even a row with every real key masked, which still averages the real keys'
    values (as openpi, see `to_additive_mask`)."""
    keys = aligned_key_count(mask.shape[-1]) if keys is None else keys
    return F.pad(mask, (0, keys - mask.shape[-1]), value=float("-inf")) if keys != mask.shape[-1] else mask


def sdpa_with_mask(
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    mask: torch.Tensor,
    scale: float | None = None,
    enable_gqa: bool = False,
) -> torch.Tensor:
    """`scaled_dot_product_attention` with an additive `mask` `[..., L, S']`, the one way this package calls it with
    a mask. The mask SDPA gets is contiguous and its key count is a multiple of `KEY_ALIGNMENT`: callers that can
    build it so (`pad_keys`; k/v buffers with as many slots, finite) pay nothing here; otherwise the mask is padded
    by `pad_keys` and key / value `[..., S, H]` with zeros, copies that a hot path should avoid.

    >>> q = k = v = torch.ones(1, 1, 2, 4)
    >>> mask = torch.zeros(1, 1, 2, 2)  # two keys: padded to 8, six of them masked out
    >>> sdpa_with_mask(q, k, v, mask).shape
    torch.Size([1, 1, 2, 4])
    """
    mask = pad_keys(mask)
    keys = mask.shape[-1]
    if key.shape[-2] < keys:
        key, value = (F.pad(tensor, (0, 0, 0, keys - tensor.shape[-2])) for tensor in (key, value))
    elif key.shape[-2] > keys:
        key, value = key[..., :keys, :], value[..., :keys, :]
    return F.scaled_dot_product_attention(query, key, value, attn_mask=mask.contiguous(), scale=scale, enable_gqa=enable_gqa)


def masked_attention(
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    mask: torch.Tensor,
    scale: float | None = None,
    *,
    additive: bool = False,
) -> torch.Tensor:
    """Grouped-query attention with a mask through `scaled_dot_product_attention` (by `sdpa_with_mask`: a contiguous
    mask whose key count is a multiple of `KEY_ALIGNMENT`).

    Args:
        query: `[B, N, L, H]`; key, value: `[B, K, S, H]` with N a multiple of K (query head n uses kv head
            n // (N / K); k/v are not materialised N/K times).
        mask: bool `[B, L, S]` or `[B, 1, L, S]`, True = attend.
        scale: logit scale, default `H ** -0.5`.
        additive: `mask` is already additive (`to_additive_mask`; convert once when many layers share one mask);
            it is cast to the query's dtype.

    Returns:
        `[B, N, L, H]`. A query row with every key masked returns the mean of the values (finite), as openpi
        (float32/bfloat16; see `to_additive_mask` for float16). SDPA given the bool mask itself gives 0 there
        (recent torch) or NaN (older torch), and FlexAttention gives 0.

    >>> q = k = v = torch.arange(4.0).view(1, 1, 2, 2)  # tokens (0, 1) and (2, 3)
    >>> mask = torch.tensor([[[False, False], [True, False]]])  # token 0 sees nothing, token 1 sees token 0
    >>> masked_attention(q, k, v, mask)
    tensor([[[[1., 2.],
              [0., 1.]]]])
    """
    if not additive:
        _require_bool(mask, "mask")
    elif not mask.is_floating_point():
        raise TypeError(f"an additive mask must be floating point (from `to_additive_mask`), got {mask.dtype}")
    if query.dim() != 4 or key.dim() != 4 or value.dim() != 4 or value.shape[:3] != key.shape[:3]:
        raise ValueError(
            f"query must be [B, N, L, H] and key, value [B, K, S, H]; got query {tuple(query.shape)}, "
            f"key {tuple(key.shape)}, value {tuple(value.shape)}"
        )
    if query.shape[1] % key.shape[1]:
        raise ValueError(f"query heads ({query.shape[1]}) must be a multiple of key/value heads ({key.shape[1]})")
    mask4 = mask[:, None] if mask.dim() == 3 else mask  # [B, 1, L, S]
    if mask4.dim() != 4 or mask4.shape[1] != 1 or mask4.shape[2:] != (query.shape[2], key.shape[2]):
        raise ValueError(
            f"mask must be [B, L, S] or [B, 1, L, S] with L={query.shape[2]}, S={key.shape[2]}, "
            f"got shape {tuple(mask.shape)}"
        )
    # an additive mask built in the residual stream's dtype meets bf16 queries under autocast: cast it (no-op otherwise)
    attn_mask = mask4.to(query.dtype) if additive else to_additive_mask(mask4, query.dtype)
    return sdpa_with_mask(query, key, value, attn_mask, scale=scale, enable_gqa=query.shape[1] != key.shape[1])
