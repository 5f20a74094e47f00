"""The exportable core of `generate_actions` (`pi0_torch.inference.program`): for a static plan it returns what
`generate_actions` returns for the same noise, `torch.export` traces it (non-strict), and the exported program replays
it, for π0 and π0.5 at batch 1 and 3, with cameras and prompt tokens masked or not."""

from __future__ import annotations

import pytest
import torch

from pi0_torch import PI0Config, PI0ForActionGeneration


def relative(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got - want).abs().max() / want.abs().max())


@pytest.fixture(scope="module", params=["pi0_small", "pi05_small"])
def model(request: pytest.FixtureRequest) -> PI0ForActionGeneration:
    torch.manual_seed(0)
    return PI0ForActionGeneration(PI0Config.from_preset(request.param, num_inference_steps=3)).eval()


@pytest.mark.parametrize("batch, masked", [(1, False), (1, True), (3, False), (3, True)])
def test_program_equals_generate_actions_and_exports(model: PI0ForActionGeneration, batch: int, masked: bool) -> None:
    program = model.sampling_program(batch_size=batch)
    inputs = list(program.example_inputs(seed=batch))
    if masked:  # a camera and some prompt tokens left out (sample 0 keeps all when batch > 1)
        inputs[1][-1, 0] = False
        inputs[3][-1, 9:] = False
    pixel_values, image_masks, input_ids, attention_mask, state, noise = inputs
    actions = program(*inputs)
    expected = model.generate_actions(pixel_values, image_masks, input_ids, attention_mask, state, noise=noise)
    if batch > 1 and masked:  # sample 0 fills every slot, another does not: generate_actions lays the batch out the same
        assert torch.equal(actions, expected)
    else:  # (unpadded, or without the masked camera's and tokens' slots: the same numbers to rounding)
        assert relative(actions, expected) <= 1e-5
    assert relative(actions, model.sample_actions_reference(*inputs[:5], noise=noise)) <= 1e-5

    exported = torch.export.export(program, tuple(inputs), strict=False)
    assert relative(exported.module()(*inputs), actions) <= 1e-6
    other = [tensor.clone() for tensor in inputs]  # the exported program follows its inputs (masks included)
    other[1][0, 0] = False
    other[5] = torch.randn_like(noise)
    assert relative(exported.module()(*other), program(*other)) <= 1e-6


def test_program_checks_its_sizes(model: PI0ForActionGeneration) -> None:
    with pytest.raises(ValueError, match="batch_size"):
        model.sampling_program(batch_size=0)
    with pytest.raises(ValueError, match=r"text_length must be an integer in \[1, 48\]|text_length must be an integer in \[1, 200\]"):
        model.sampling_program(text_length=10_000)
    program = model.sampling_program(batch_size=2, num_steps=5, text_length=7)
    assert len(program.plan.times) == 5 and program.example_inputs()[2].shape == (2, 7)
