"""Every SDPA call with a mask, in every path of π0, π0.5 and π0-FAST, passes a mask cuDNN cannot break: contiguous,
its key count a multiple of 8 and equal to the keys' (`pi0_torch.masks.sdpa_with_mask`). A sliced, odd-length decoding
mask crashed π0-FAST in cuDNN on an H200 ("misaligned address", the CUDA context lost); the CPU records the calls."""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from pi0_torch import PI0Config, PI0FastConfig, PI0FastForActionGeneration, PI0ForActionGeneration
from pi0_torch.masks import KEY_ALIGNMENT

SMALL = dict(image_size=28, vision_hidden_size=32, vision_intermediate_size=64, vision_num_layers=1, vision_num_heads=2)


@pytest.fixture
def masked_calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[tuple[int, ...], bool, int]]:
    """(mask shape, contiguous, key count) of every SDPA call with a mask, checked as it happens."""
    calls: list[tuple[tuple[int, ...], bool, int]] = []
    sdpa = F.scaled_dot_product_attention

    def recording(query, key, value, attn_mask=None, *args, **kwargs):
        if attn_mask is not None:
            calls.append((tuple(attn_mask.shape), attn_mask.is_contiguous(), key.shape[-2]))
            assert attn_mask.is_contiguous() and attn_mask.shape[-1] % KEY_ALIGNMENT == 0, calls[-1]
            assert attn_mask.shape[-1] == key.shape[-2] == value.shape[-2], calls[-1]
        return sdpa(query, key, value, attn_mask, *args, **kwargs)

    monkeypatch.setattr(F, "scaled_dot_product_attention", recording)
    return calls


def pi0_inputs(config: PI0Config, lengths: list[int], shown: list[bool]) -> dict[str, torch.Tensor]:
    batch = len(lengths)
    generator = torch.Generator().manual_seed(sum(lengths))
    return dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, config.image_size, config.image_size, generator=generator) * 2 - 1,
        image_masks=torch.tensor([shown] * batch),
        input_ids=torch.randint(0, config.vocab_size, (batch, config.max_token_len), generator=generator),
        attention_mask=torch.arange(config.max_token_len)[None] < torch.tensor(lengths)[:, None],
        state=torch.randn(batch, config.action_dim, generator=generator),
        noise=torch.randn(batch, config.action_horizon, config.action_dim, generator=generator),
    )


@pytest.mark.parametrize("preset", ["pi0_small", "pi05_small"])
@pytest.mark.parametrize("lengths, shown", [([1], [True, True, True]), ([5, 12], [True, False, True]), ([3, 7, 9], [True, True, False])])
def test_every_masked_sdpa_call_of_pi0_and_pi05_is_aligned(masked_calls: list, preset: str, lengths: list[int],
                                                          shown: list[bool]) -> None:
    """Training forward, the sampling's prefix and suffix, both real-time chunking methods, the reference loop."""
    config = PI0Config.from_preset(preset, **SMALL, max_token_len=12, action_horizon=6, rtc_max_delay=3)
    model = PI0ForActionGeneration(config).eval()
    model.attention_kernel = "sdpa"
    inputs = pi0_inputs(config, lengths, shown)
    noise = inputs.pop("noise")
    model(**inputs, actions=torch.zeros_like(noise), noise=noise)
    with torch.no_grad():
        model.generate_actions(**inputs, noise=noise, num_steps=2)
        for method in ("guidance", "conditioning"):
            model.generate_actions(**inputs, noise=noise, num_steps=2, previous_actions=torch.randn_like(noise),
                                   inference_delay=2, execution_horizon=3, rtc_method=method)
        model.sample_actions_reference(**inputs, noise=noise, num_steps=2)
    assert len(masked_calls) >= 2 * config.num_hidden_layers, masked_calls  # (unpadded passes need no mask)


@pytest.mark.parametrize("max_new_tokens", [1, 2, 60])
@pytest.mark.parametrize("lengths, shown", [([1], [True, True, True]), ([5, 20], [True, False, True])])
def test_every_masked_sdpa_call_of_pi0_fast_is_aligned(masked_calls: list, max_new_tokens: int, lengths: list[int],
                                                       shown: list[bool]) -> None:
    """The training forward, the prefill (its last layer finishes the last token only) and every decoding step."""
    config = PI0FastConfig.from_preset("pi0_fast_small", **SMALL, max_token_len=24, eos_token_id=None)
    model = PI0FastForActionGeneration(config).eval()
    inputs = pi0_inputs(copy.deepcopy(config), lengths, shown)
    for name in ("state", "noise"):
        inputs.pop(name)
    inputs["token_ar_mask"] = torch.arange(config.max_token_len)[None].expand(len(lengths), -1) >= 4
    model(**inputs, token_loss_mask=inputs["token_ar_mask"])
    tokens = model.generate_tokens(**inputs, max_new_tokens=max_new_tokens)
    assert tokens.shape == (len(lengths), max_new_tokens)
    assert len(masked_calls) >= 2 * config.num_hidden_layers + (max_new_tokens - 1) * config.num_hidden_layers
