"""Tests of pi0_torch.masks: hand-written grids, openpi's fixture masks, a naive attention loop, FlexAttention."""

from __future__ import annotations

import doctest
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from pi0_torch import masks
from pi0_torch.masks import (
    MASKED_LOGIT,
    block_mask_from_dense,
    broadcast_mask,
    causal_mask,
    causal_mask_mod,
    claw_mask_mod,
    claw_matrix,
    dense_mask_mod,
    flex_attention_available,
    format_mask,
    generate_chunk_data,
    mask_from_mod,
    masked_attention,
    prefix_lm_mask,
    prefix_lm_mask_mod,
    to_additive_mask,
    to_block_mask,
    window_chunk_mask,
    window_chunk_mask_mod,
)

FIXTURES = Path(__file__).parent / "fixtures" / "openpi"
needs_flex = pytest.mark.skipif(not flex_attention_available(), reason="installed torch has no FlexAttention")


def grid(text: str) -> torch.Tensor:
    """Parse a drawn grid ('1' = attend, '.' = masked; spaces ignored) into a bool tensor."""
    rows = [line.replace(" ", "") for line in text.strip().splitlines()]
    return torch.tensor([[char == "1" for char in row] for row in rows])


# ---------------------------------------------------------------------------------------------------------------
# Grids.
# ---------------------------------------------------------------------------------------------------------------

CLAW_8_3 = """
1111....
.1111...
..1111..
...1111.
....1111
.....111
......11
.......1
"""

WINDOW_CHUNK_8_3 = """
11111111...
11111111...
11111111...
11111111...
11111111...
11111111...
11111111...
11111111...
111111111..
1111111111.
11111111111
"""

CAUSAL_5 = """
1....
11...
111..
1111.
11111
"""


def test_claw_matrix_8_3_matches_drawn_grid_and_robovlms_dtype() -> None:
    claw = claw_matrix(8, 3)
    assert claw.shape == (8, 8) and claw.dtype == torch.get_default_dtype()  # RoboVLMs: float 0/1
    assert set(claw.unique().tolist()) == {0.0, 1.0}
    assert torch.equal(claw.bool(), grid(CLAW_8_3))
    assert torch.equal(claw_matrix(8, 3, dtype=torch.bool), grid(CLAW_8_3))


def test_claw_matrix_equals_robovlms_triangle_product() -> None:
    for n, k in [(1, 0), (5, 0), (5, 2), (8, 3), (6, 5), (4, 10), (12, 7)]:
        expected = torch.triu(torch.ones(n, n), diagonal=0) * torch.tril(torch.ones(n, n), diagonal=k)
        assert torch.equal(claw_matrix(n, k), expected), (n, k)


def test_claw_matrix_edge_cases() -> None:
    assert torch.equal(claw_matrix(5, 0, dtype=torch.bool), torch.eye(5, dtype=torch.bool))
    assert torch.equal(claw_matrix(4, 10, dtype=torch.bool), grid("1111\n.111\n..11\n...1"))
    assert claw_matrix(0, 3).shape == (0, 0)
    assert claw_matrix(3, 1, dtype=torch.float64).dtype == torch.float64
    with pytest.raises(ValueError, match="k must be an int >= 0"):
        claw_matrix(4, -1)
    with pytest.raises(ValueError, match="n must be an int >= 0"):
        claw_matrix(-2, 1)


def test_causal_mask_matches_drawn_grid() -> None:
    assert torch.equal(causal_mask(5), grid(CAUSAL_5))
    assert torch.equal(causal_mask(7), torch.ones(7, 7, dtype=torch.bool).tril())


def test_window_chunk_mask_8_3_matches_drawn_grid() -> None:
    mask = window_chunk_mask(8, 3)
    assert mask.shape == (11, 11) and mask.dtype == torch.bool
    assert torch.equal(mask, grid(WINDOW_CHUNK_8_3))
    assert mask[:8, :8].all()  # window block all ones
    assert not mask[:8, 8:].any()  # window rows see nothing of the chunk
    assert torch.equal(mask[8:, 8:], torch.ones(3, 3, dtype=torch.bool).tril())  # chunk causal


def test_window_chunk_mask_definition_and_degenerate_cases() -> None:
    for window, chunk in [(1, 1), (3, 2), (8, 3), (5, 0), (16, 10)]:
        mask = window_chunk_mask(window, chunk)
        n = window + chunk
        for i in range(n):
            visible = list(range(window)) if i < window else list(range(i + 1))
            assert mask[i].nonzero().flatten().tolist() == visible, (window, chunk, i)
    assert torch.equal(window_chunk_mask(0, 6), causal_mask(6))
    assert torch.equal(window_chunk_mask(1, 5), causal_mask(6))
    assert window_chunk_mask(4, 0).all()


def test_format_mask_draws_grid() -> None:
    assert format_mask(claw_matrix(3, 1)) == "1 1 .\n. 1 1\n. . 1"
    with pytest.raises(ValueError, match="2-D"):
        format_mask(torch.ones(2, 2, 2))


def test_mask_from_mod_batched_broadcast() -> None:
    batched = mask_from_mod(causal_mask_mod(), 4, 6, batch_size=3)
    assert batched.shape == (3, 4, 6) and batched.is_contiguous()
    assert torch.equal(batched[2], torch.ones(4, 6, dtype=torch.bool).tril())


# ---------------------------------------------------------------------------------------------------------------
# generate_chunk_data.
# ---------------------------------------------------------------------------------------------------------------


def chunks_by_unfold(data: torch.Tensor, window: int, chunk: int) -> torch.Tensor:
    """Reference: sliding windows of length `chunk` over steps 1.., the first `window` of them."""
    windows = data.unfold(1, chunk, 1)  # [B, window + 1, ..., chunk]
    return windows[:, 1 : window + 1].movedim(-1, 2)


def chunks_by_claw_selection(data: torch.Tensor, window: int, chunk: int) -> torch.Tensor:
    """Reference: RoboVLMs' definition (claw_matrix(S, chunk) without its diagonal, first `window` rows, select)."""
    batch, length = data.shape[:2]
    flat = data.reshape(batch, length, -1)  # [B, S, D]
    selection = claw_matrix(length, chunk, dtype=torch.bool)
    selection.fill_diagonal_(False)
    selection = selection[:window]  # [W, S]
    repeated = flat[:, None].expand(batch, window, length, flat.shape[-1])
    chosen = torch.masked_select(repeated, selection[None, :, :, None].expand_as(repeated))
    return chosen.view(batch, window, chunk, *data.shape[2:])


def make_episode(shape: tuple[int, ...], dtype: torch.dtype, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    if dtype == torch.bool:
        return torch.rand(shape, generator=generator) > 0.5
    if dtype.is_floating_point:
        return torch.randn(shape, generator=generator).to(dtype)
    return torch.randint(0, 100, shape, generator=generator).to(dtype)


@pytest.mark.parametrize("window,chunk", [(1, 1), (2, 1), (8, 3), (5, 7), (16, 10)])
@pytest.mark.parametrize("trailing", [(), (7,), (3, 4, 5)])
def test_generate_chunk_data_equals_unfold_and_claw_selection(
    window: int, chunk: int, trailing: tuple[int, ...]
) -> None:
    data = make_episode((3, window + chunk, *trailing), torch.float32, seed=window * 100 + chunk)
    result = generate_chunk_data(data, window, chunk)
    assert result.shape == (3, window, chunk, *trailing)
    assert result.is_contiguous()
    assert torch.equal(result, chunks_by_unfold(data, window, chunk))
    assert torch.equal(result, chunks_by_claw_selection(data, window, chunk))
    for i in range(window):  # window step i gets steps i+1 .. i+chunk
        assert torch.equal(result[:, i], data[:, i + 1 : i + 1 + chunk])


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16, torch.float16, torch.int64, torch.uint8, torch.bool])
def test_generate_chunk_data_any_dtype(dtype: torch.dtype) -> None:
    data = make_episode((2, 11, 4), dtype, seed=3)
    result = generate_chunk_data(data, 8, 3)
    assert result.dtype == dtype
    assert torch.equal(result, chunks_by_claw_selection(data, 8, 3))


def test_generate_chunk_data_non_contiguous_input_and_gradients() -> None:
    data = make_episode((11, 2, 6), torch.float32, seed=5).transpose(0, 1)  # [2, 11, 6], not contiguous
    assert not data.is_contiguous()
    assert torch.equal(generate_chunk_data(data, 8, 3), chunks_by_unfold(data, 8, 3))

    leaf = data.detach().clone().requires_grad_(True)
    generate_chunk_data(leaf, 8, 3).sum().backward()
    # step s appears once per window row i with i+1 <= s <= i+3, i < 8
    uses = torch.tensor([sum(1 for i in range(8) if i + 1 <= s <= i + 3) for s in range(11)], dtype=torch.float32)
    assert torch.equal(leaf.grad, uses[None, :, None].expand(2, 11, 6))


def test_generate_chunk_data_errors_name_the_argument() -> None:
    data = torch.zeros(2, 10, 7)
    expected = r"window_size \+ chunk_size, \.\.\.\] = \[B, 11, \.\.\.\].*got shape \(2, 10, 7\)"
    with pytest.raises(ValueError, match=expected):
        generate_chunk_data(data, 8, 3)
    with pytest.raises(ValueError, match="window_size must be an int >= 1, got 0"):
        generate_chunk_data(data, 0, 10)
    with pytest.raises(ValueError, match="chunk_size must be an int >= 1, got 0"):
        generate_chunk_data(data, 10, 0)
    with pytest.raises(ValueError, match="chunk_size must be an int >= 1, got 2.0"):
        generate_chunk_data(data, 8, 2.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"got shape \(11,\)"):
        generate_chunk_data(torch.zeros(11), 8, 3)


# ---------------------------------------------------------------------------------------------------------------
# prefix_lm_mask against openpi's fixtures.
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["pi0_small", "pi05_small"])
def openpi_masks(request: pytest.FixtureRequest) -> dict[str, torch.Tensor]:
    with np.load(FIXTURES / request.param / "reference.npz") as reference:
        keys = {
            "prefix_mask": "fp32/loss_path/prefix_mask",
            "suffix_mask": "fp32/loss_path/suffix_mask",
            "prefix_ar_mask": "fp32/loss_path/prefix_ar_mask",
            "suffix_ar_mask": "fp32/loss_path/suffix_ar_mask",
            "attn_mask": "fp32/loss_path/attn_mask",
            "positions": "fp32/loss_path/positions",
            "step0_full_attn_mask": "fp32/sample_path/step0_full_attn_mask",
            "prefix_positions": "fp32/sample_path/prefix_positions",
            "step0_suffix_positions": "fp32/sample_path/step0_suffix_positions",
        }
        return {name: torch.from_numpy(reference[key]) for name, key in keys.items()}


def test_prefix_lm_mask_equals_openpi_loss_path(openpi_masks: dict[str, torch.Tensor]) -> None:
    valid = torch.cat([openpi_masks["prefix_mask"], openpi_masks["suffix_mask"]], dim=1)  # [B, P+S]
    block_flags = torch.cat([openpi_masks["prefix_ar_mask"], openpi_masks["suffix_ar_mask"]])  # [P+S]
    mask, positions = prefix_lm_mask(valid, block_flags)
    assert mask.dtype == torch.bool and positions.dtype == torch.long
    assert not valid.all()  # the fixture has padding and a missing camera, so the valid rule is exercised
    assert torch.equal(mask, openpi_masks["attn_mask"])
    assert torch.equal(positions, openpi_masks["positions"].long())
    # per-sample [B, L] and broadcast [1, L] block flags give the same mask
    assert torch.equal(prefix_lm_mask(valid, block_flags.expand_as(valid))[0], mask)
    assert torch.equal(prefix_lm_mask(valid, block_flags[None])[0], mask)


def test_prefix_lm_mask_rebuilds_openpi_sampling_mask(openpi_masks: dict[str, torch.Tensor]) -> None:
    prefix_valid, suffix_valid = openpi_masks["prefix_mask"], openpi_masks["suffix_mask"]
    prefix_len = prefix_valid.shape[1]
    expected = openpi_masks["step0_full_attn_mask"]  # [B, S, P+S]

    # as the sampler builds it: valid prefix keys, then the suffix's own block mask
    suffix_mask, suffix_positions = prefix_lm_mask(suffix_valid, openpi_masks["suffix_ar_mask"])
    sees_prefix = prefix_valid[:, None, :].expand(-1, suffix_valid.shape[1], -1)
    assert torch.equal(torch.cat([sees_prefix, suffix_mask], dim=2), expected)

    # and as the suffix rows of the joint mask
    valid = torch.cat([prefix_valid, suffix_valid], dim=1)
    block_flags = torch.cat([openpi_masks["prefix_ar_mask"], openpi_masks["suffix_ar_mask"]])
    joint_mask, joint_positions = prefix_lm_mask(valid, block_flags)
    assert torch.equal(joint_mask[:, prefix_len:], expected)

    prefix_positions = prefix_lm_mask(prefix_valid, openpi_masks["prefix_ar_mask"])[1]
    assert torch.equal(prefix_positions, openpi_masks["prefix_positions"].long())
    offset = prefix_valid.sum(dim=1, keepdim=True)
    assert torch.equal(offset + suffix_positions, openpi_masks["step0_suffix_positions"].long())
    assert torch.equal(joint_positions[:, prefix_len:], openpi_masks["step0_suffix_positions"].long())


def test_prefix_lm_mask_shape_errors() -> None:
    with pytest.raises(ValueError, match=r"valid must be \[B, L\]"):
        prefix_lm_mask(torch.ones(5, dtype=torch.bool), torch.zeros(5))
    with pytest.raises(ValueError, match=r"block_flags must be \[L\] or \[B, L\].*got shape \(4,\)"):
        prefix_lm_mask(torch.ones(2, 5, dtype=torch.bool), torch.zeros(4))
    with pytest.raises(ValueError, match=r"got shape \(3, 5\)"):
        prefix_lm_mask(torch.ones(2, 5, dtype=torch.bool), torch.zeros(3, 5))


# ---------------------------------------------------------------------------------------------------------------
# Masked attention against a naive float64 loop.
# ---------------------------------------------------------------------------------------------------------------


def naive_attention(
    query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, mask: torch.Tensor, scale: float
) -> torch.Tensor:
    """softmax(q k^T * scale) v row by row in float64 over the allowed keys; a row with none gets mean(v)."""
    batch, heads, q_len, _ = query.shape
    group = heads // key.shape[1]
    mask = mask if mask.dim() == 3 else mask[:, 0]  # [B, L, S]
    out = torch.zeros(batch, heads, q_len, value.shape[-1], dtype=torch.float64)
    for b in range(batch):
        for n in range(heads):
            keys, values = key[b, n // group].double(), value[b, n // group].double()
            for i in range(q_len):
                allowed = mask[b, i]
                if not allowed.any():
                    out[b, n, i] = values.mean(dim=0)
                    continue
                logits = (keys[allowed] @ query[b, n, i].double()) * scale
                weights = torch.exp(logits - logits.max())
                out[b, n, i] = (weights / weights.sum()) @ values[allowed]
    return out


def attention_masks(batch: int) -> dict[str, torch.Tensor]:
    """Every pattern as a [B, L, S] bool mask with L = S = 11."""
    valid = torch.ones(batch, 11, dtype=torch.bool)
    valid[0, 3:5] = False  # padding inside the prefix: rows 3, 4 are fully masked
    valid[-1, 7] = False
    block_flags = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1, 0, 0, 0])  # prefix, state, 4 actions (π0 layout)
    random = torch.rand(batch, 11, 11, generator=torch.Generator().manual_seed(7)) > 0.6
    random[0, 2] = False  # one fully masked row
    square = {
        "causal": causal_mask(11),
        "claw": claw_matrix(11, 3, dtype=torch.bool),
        "window_chunk": window_chunk_mask(8, 3),
    }
    batched = {name: mask.expand(batch, 11, 11) for name, mask in square.items()}
    return {**batched, "prefix_lm": prefix_lm_mask(valid, block_flags)[0], "random": random}


@pytest.mark.parametrize("pattern", ["causal", "claw", "window_chunk", "prefix_lm", "random"])
@pytest.mark.parametrize("kv_heads", [8, 2, 1])
def test_masked_attention_equals_naive_loop(pattern: str, kv_heads: int) -> None:
    generator = torch.Generator().manual_seed(kv_heads)
    batch, heads, head_dim = 2, 8, 16
    query = torch.randn(batch, heads, 11, head_dim, generator=generator)
    key = torch.randn(batch, kv_heads, 11, head_dim, generator=generator)
    value = torch.randn(batch, kv_heads, 11, head_dim, generator=generator)
    mask = attention_masks(batch)[pattern]
    expected = naive_attention(query, key, value, mask, scale=head_dim**-0.5)

    for layout in (mask, mask[:, None]):  # [B, L, S] and [B, 1, L, S]
        out = masked_attention(query, key, value, layout)
        assert out.shape == (batch, heads, 11, head_dim) and out.dtype == torch.float32
        torch.testing.assert_close(out.double(), expected, atol=1e-5, rtol=1e-5)

    custom = masked_attention(query, key, value, mask, scale=0.3)
    torch.testing.assert_close(custom.double(), naive_attention(query, key, value, mask, 0.3), atol=1e-5, rtol=1e-5)


def test_fully_masked_rows_return_mean_of_values() -> None:
    generator = torch.Generator().manual_seed(0)
    query = torch.randn(1, 4, 5, 8, generator=generator) * 30  # large logits must not leak through
    key = torch.randn(1, 1, 5, 8, generator=generator) * 30
    value = torch.randn(1, 1, 5, 8, generator=generator)
    mask = torch.ones(1, 5, 5, dtype=torch.bool).tril()
    mask[0, 2] = False
    mean = value[0, 0].mean(dim=0)
    out = masked_attention(query, key, value, mask)
    for head in range(4):
        torch.testing.assert_close(out[0, head, 2], mean, atol=1e-6, rtol=0)
    nothing = masked_attention(query, key, value, torch.zeros(1, 5, 5, dtype=torch.bool))
    torch.testing.assert_close(nothing, mean.expand(1, 4, 5, 8), atol=1e-6, rtol=0)

    bf16 = masked_attention(query.bfloat16(), key.bfloat16(), value.bfloat16(), mask)
    assert torch.isfinite(bf16).all()
    bf16_mean = value.bfloat16()[0, 0].float().mean(dim=0)
    torch.testing.assert_close(bf16[0, :, 2].float(), bf16_mean.expand(4, 8), atol=2e-2, rtol=0)
    assert torch.isfinite(masked_attention(query.half(), key.half(), value.half(), mask)).all()


def test_masked_attention_input_errors() -> None:
    query, key = torch.zeros(1, 4, 3, 8), torch.zeros(1, 2, 5, 8)
    with pytest.raises(TypeError, match="mask must be a bool mask"):
        masked_attention(query, key, key, torch.ones(1, 3, 5))
    with pytest.raises(ValueError, match=r"mask must be \[B, L, S\].*L=3, S=5, got shape \(1, 5, 3\)"):
        masked_attention(query, key, key, torch.ones(1, 5, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="multiple of key/value heads"):
        masked_attention(torch.zeros(1, 3, 3, 8), key, key, torch.ones(1, 3, 5, dtype=torch.bool))


# ---------------------------------------------------------------------------------------------------------------
# Conversions.
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16, torch.float64])
def test_to_additive_mask_values(dtype: torch.dtype) -> None:
    mask = window_chunk_mask(3, 2)
    additive = to_additive_mask(mask, dtype)
    assert additive.dtype == dtype and additive.shape == mask.shape
    assert (additive[mask] == 0).all()
    expected = max(MASKED_LOGIT, torch.finfo(dtype).min)
    assert (additive[~mask] == torch.tensor(expected, dtype=dtype)).all()
    assert torch.isfinite(additive).all()
    with pytest.raises(TypeError, match="dtype must be a floating dtype"):
        to_additive_mask(mask, torch.int32)


def test_broadcast_mask_layouts() -> None:
    square = causal_mask(4)
    for mask in (square, square.expand(2, 4, 4), square.expand(2, 1, 4, 4), square.expand(1, 8, 4, 4)):
        expanded = broadcast_mask(mask, batch_size=2, num_heads=8)
        assert expanded.shape == (2, 8, 4, 4)
        assert torch.equal(expanded, square.expand(2, 8, 4, 4))
    with pytest.raises(ValueError, match="cannot broadcast"):
        broadcast_mask(square.expand(3, 4, 4), batch_size=2, num_heads=8)
    with pytest.raises(ValueError, match=r"got shape \(4,\)"):
        broadcast_mask(torch.ones(4, dtype=torch.bool), batch_size=2, num_heads=8)


# ---------------------------------------------------------------------------------------------------------------
# FlexAttention BlockMask.
# ---------------------------------------------------------------------------------------------------------------


def flex_rules(batch: int, length: int) -> dict[str, tuple[masks.MaskMod, int | None]]:
    generator = torch.Generator().manual_seed(11)
    valid = torch.ones(batch, length, dtype=torch.bool)
    valid[0, 50:90] = False  # padding: fully masked rows
    block_flags = torch.zeros(length, dtype=torch.long)
    block_flags[[150, 151]] = 1
    random = torch.rand(batch, length, length, generator=generator) > 0.3
    return {
        "causal": (causal_mask_mod(), None),
        "claw": (claw_mask_mod(40), None),
        "window_chunk": (window_chunk_mask_mod(130), None),
        "prefix_lm": (prefix_lm_mask_mod(valid, block_flags), batch),
        "dense": (dense_mask_mod(random), batch),
    }


@needs_flex
def test_mask_from_mod_equals_flex_create_mask() -> None:
    from torch.nn.attention.flex_attention import create_mask

    for name, (rule, batch) in flex_rules(2, 200).items():
        ours = mask_from_mod(rule, 200, 200, batch_size=batch)
        theirs = create_mask(rule, batch or 1, 1, 200, 200, device="cpu")[:, 0]  # [B, L, S]
        assert torch.equal(ours.expand_as(theirs), theirs), name


@needs_flex
def test_block_mask_skips_exactly_the_empty_tiles() -> None:
    block, length = 64, 200  # 4 x 4 tiles, the last one partial
    tiles = -(-length // block)
    for name, (rule, batch) in flex_rules(2, length).items():
        dense = mask_from_mod(rule, length, length, batch_size=batch).expand(2, length, length)
        padded = torch.zeros(2, tiles * block, tiles * block, dtype=torch.bool)
        padded[:, :length, :length] = dense
        any_in_tile = padded.view(2, tiles, block, tiles, block).any(dim=4).any(dim=2)  # [B, tiles, tiles]
        block_mask = to_block_mask(rule, length, length, batch_size=batch, block_size=block)
        computed = block_mask.to_dense()[:, 0].bool()  # [B or 1, tiles, tiles]
        assert torch.equal(computed.expand_as(any_in_tile), any_in_tile), name


@needs_flex
@pytest.mark.parametrize("pattern", ["causal", "claw", "window_chunk", "prefix_lm", "dense"])
def test_flex_attention_block_mask_equals_dense_sdpa(pattern: str) -> None:
    from torch.nn.attention.flex_attention import flex_attention

    batch, heads, kv_heads, length, head_dim = 2, 4, 2, 200, 16
    generator = torch.Generator().manual_seed(3)
    query = torch.randn(batch, heads, length, head_dim, generator=generator)
    key = torch.randn(batch, kv_heads, length, head_dim, generator=generator)
    value = torch.randn(batch, kv_heads, length, head_dim, generator=generator)
    rule, rule_batch = flex_rules(batch, length)[pattern]
    dense = mask_from_mod(rule, length, length, batch_size=rule_batch).expand(batch, length, length)

    block_mask = to_block_mask(rule, length, length, batch_size=rule_batch, block_size=64)
    if pattern == "dense":
        assert torch.equal(block_mask_from_dense(dense, block_size=64).to_dense(), block_mask.to_dense())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # eager flex_attention warns that it is not fused
        flex_out = flex_attention(query, key, value, block_mask=block_mask, enable_gqa=True)
    sdpa_out = masked_attention(query, key, value, dense)

    seen = dense.any(dim=-1)[:, None, :, None].expand_as(sdpa_out)  # rows with at least one key
    torch.testing.assert_close(flex_out[seen], sdpa_out[seen], atol=1e-5, rtol=1e-5)
    assert (flex_out[~seen] == 0).all()  # FlexAttention: fully masked rows are 0 (masked_attention: mean of v)


def test_to_block_mask_error_without_flex(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(masks, "create_block_mask", None)
    assert not flex_attention_available()
    with pytest.raises(RuntimeError, match="needs torch >= 2.5"):
        to_block_mask(causal_mask_mod(), 8, 8)


# ---------------------------------------------------------------------------------------------------------------
# Docstring examples.
# ---------------------------------------------------------------------------------------------------------------


def test_docstring_examples_run() -> None:
    finder, runner = doctest.DocTestFinder(), doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    examples = [test for test in finder.find(masks) if test.examples]
    if not flex_attention_available():
        examples = [test for test in examples if not test.name.endswith("to_block_mask")]
    assert len(examples) >= 10
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for test in examples:
            runner.run(test)
    assert runner.summarize(verbose=False).failed == 0
