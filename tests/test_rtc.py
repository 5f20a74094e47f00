"""Real-time chunking in the model: the chunk prefix, guided sampling (inference-time RTC) and committed-prefix
conditioning (training-time RTC), against independent reference computations."""

from __future__ import annotations

import pytest
import torch
from test_modeling import small_batch

from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.inference.conditioning import euler_times
from pi0_torch.inference.rtc import chunk_prefix, guidance_weight

HORIZON, ACTION_DIM = 16, 8
SMALL = dict(image_size=28, max_token_len=12, action_horizon=HORIZON, action_dim=ACTION_DIM)


@pytest.fixture(scope="module", params=["pi0_small", "pi05_small"])
def model(request: pytest.FixtureRequest) -> PI0ForActionGeneration:
    torch.manual_seed(0)
    return PI0ForActionGeneration(PI0Config.from_preset(request.param, rtc_max_delay=8, **SMALL)).eval()


def noise(seed: int, batch: int = 2) -> torch.Tensor:
    return torch.randn(batch, HORIZON, ACTION_DIM, generator=torch.Generator().manual_seed(seed))


def test_chunk_prefix_per_sample_delays_and_errors() -> None:
    previous = torch.arange(100, dtype=torch.float32).view(2, 50, 1)
    prefix = chunk_prefix(previous, inference_delay=torch.tensor([0, 3]), execution_horizon=torch.tensor([10, 40]))
    assert prefix.target[0, :40, 0].tolist() == list(range(10, 50)) and prefix.target[0, 40:].abs().sum() == 0
    assert prefix.target[1, :10, 0].tolist() == list(range(90, 100)) and prefix.target[1, 10:].abs().sum() == 0
    assert prefix.committed.sum(dim=1).tolist() == [0, 3]
    assert prefix.weights[1, :3].tolist() == [1.0, 1.0, 1.0] and prefix.weights[1, 10:].abs().sum() == 0
    assert bool((prefix.weights[0, 1:40] <= prefix.weights[0, :39]).all())  # decays over the overlap
    with pytest.raises(ValueError, match=r"inference_delay must lie in \[0, H - execution_horizon\]"):
        chunk_prefix(previous, inference_delay=11, execution_horizon=40)
    with pytest.raises(ValueError, match=r"execution_horizon must lie in \[0, 49\]"):
        chunk_prefix(previous, inference_delay=0, execution_horizon=50)
    with pytest.raises(ValueError, match="inference_delay must be an int or an integer tensor"):
        chunk_prefix(previous, inference_delay=1.5, execution_horizon=4)
    with pytest.raises(ValueError, match="rtc_schedule must be one of"):
        chunk_prefix(previous, inference_delay=1, execution_horizon=4, schedule="cosine")
    assert guidance_weight(1.0, 5.0) == 5.0 and guidance_weight(0.5, 5.0) == 2.0


def test_zero_guidance_is_plain_sampling(model: PI0ForActionGeneration) -> None:
    batch = small_batch(model.config)
    plain = model.generate_actions(**batch, noise=noise(1), num_steps=3)
    rtc = model.generate_actions(**batch, noise=noise(1), num_steps=3, previous_actions=noise(2), inference_delay=4,
                                 execution_horizon=10, rtc_max_guidance=0.0)
    assert torch.equal(plain, rtc)


def test_guided_sampling_equals_an_autograd_reference(model: PI0ForActionGeneration) -> None:
    """Every Euler step uses `v + w * grad_x 0.5 * sum(W * (Y - x0(x))^2)` with `x0 = x - t * v(x)`: the same
    correction computed with plain autograd through a fresh forward (no cache tricks, no torch.func)."""
    batch, steps, delay, executed = small_batch(model.config), 3, 4, 10
    previous = model.generate_actions(**batch, noise=noise(2), num_steps=steps)
    prefix = chunk_prefix(previous, delay, executed)
    x_t = noise(1)
    for time in euler_times(steps):
        time_batch = torch.full((2,), time)

        with torch.enable_grad():
            x = x_t.clone().requires_grad_(True)
            estimate = x - time * model(**batch, noise=x, time=time_batch).velocity
            objective = 0.5 * (prefix.weights[..., None] * (prefix.target - estimate) ** 2).sum()
            (gradient,) = torch.autograd.grad(objective, x)
            velocity = (x - estimate).detach() / time
        x_t = x_t - (velocity + guidance_weight(time, 5.0) * gradient) / steps
    guided = model.generate_actions(**batch, noise=noise(1), num_steps=steps, previous_actions=previous,
                                    inference_delay=delay, execution_horizon=executed)
    torch.testing.assert_close(guided, x_t, rtol=1e-4, atol=1e-4)


def test_guidance_works_in_inference_mode(model: PI0ForActionGeneration, monkeypatch: pytest.MonkeyPatch) -> None:
    """A policy and a server call the model in inference mode, with inputs made there. Before torch 2.12,
    `torch.func.vjp` in inference mode recorded nothing and returned zeros (pytorch#177318): guided chunks came out
    plain, silently (the GPU image's torch 2.11; its captured guidance graph replayed exactly that). Guided sampling
    therefore differentiates outside inference mode: the same chunk as under no_grad, bit for bit."""
    batch, previous = small_batch(model.config), noise(2)
    rtc = dict(num_steps=3, previous_actions=previous, inference_delay=4, execution_horizon=10)
    expected = model.generate_actions(**batch, noise=noise(1), **rtc)
    seen = []
    step = model.denoise_step
    monkeypatch.setattr(model, "denoise_step", lambda *a, **k: seen.append(torch.is_inference_mode_enabled()) or step(*a, **k))
    with torch.inference_mode():
        made_there = {name: value.clone() for name, value in batch.items()}
        guided = model.generate_actions(**made_there, noise=noise(1).clone(), **{**rtc, "previous_actions": previous.clone()})
    assert torch.equal(guided, expected) and seen and not any(seen)
    assert not torch.equal(guided, model.generate_actions(**batch, noise=noise(1), num_steps=3))


def test_guidance_pulls_the_new_chunk_onto_the_previous_one(model: PI0ForActionGeneration) -> None:
    batch, delay, executed = small_batch(model.config), 5, 10
    previous = model.generate_actions(**batch, noise=noise(2), num_steps=5)
    target = previous[:, executed : executed + delay]
    plain = model.generate_actions(**batch, noise=noise(1), num_steps=5)
    guided = model.generate_actions(**batch, noise=noise(1), num_steps=5, previous_actions=previous,
                                    inference_delay=delay, execution_horizon=executed)
    plain_gap = (plain[:, :delay] - target).abs().mean()
    guided_gap = (guided[:, :delay] - target).abs().mean()
    assert guided_gap < 0.5 * plain_gap, (float(guided_gap), float(plain_gap))


def test_conditioning_keeps_the_committed_actions_and_refuses_longer_delays(model: PI0ForActionGeneration) -> None:
    batch, executed = small_batch(model.config), 10
    previous = noise(2)
    delays = torch.tensor([3, 6])
    actions = model.generate_actions(**batch, noise=noise(1), num_steps=3, previous_actions=previous,
                                     inference_delay=delays, execution_horizon=executed, rtc_method="conditioning")
    for row, delay in enumerate(delays.tolist()):
        assert torch.equal(actions[row, :delay], previous[row, executed : executed + delay])
    plain = model.generate_actions(**batch, noise=noise(1), num_steps=3)
    assert not torch.allclose(actions[:, 6:], plain[:, 6:])  # the free steps see the committed ones
    with pytest.raises(ValueError, match="rtc_max_delay=8"):
        model.generate_actions(**batch, previous_actions=previous, inference_delay=9, execution_horizon=4,
                               rtc_method="conditioning")


def test_training_with_delays(model: PI0ForActionGeneration) -> None:
    """`forward(inference_delay=d)`: committed tokens are clean (x_t = actions, flow time 0), so at time 0 nothing
    changes; zero delays are today's loss; the loss averages over the free steps only."""
    batch = small_batch(model.config)
    actions, draw = noise(3), noise(4)
    zero_time = torch.zeros(2)
    torch.testing.assert_close(
        model(**batch, actions=actions, noise=draw, time=zero_time, inference_delay=torch.tensor([2, 7])).velocity,
        model(**batch, actions=actions, noise=draw, time=zero_time).velocity, rtol=1e-5, atol=1e-5,
    )
    time = torch.tensor([0.3, 0.8])
    plain = model(**batch, actions=actions, noise=draw, time=time)
    assert torch.equal(model(**batch, actions=actions, noise=draw, time=time, inference_delay=0).loss, plain.loss)
    delayed = model(**batch, actions=actions, noise=draw, time=time, inference_delay=torch.tensor([2, 7]))
    target = draw - actions
    free = torch.arange(HORIZON)[None, :] >= torch.tensor([2, 7])[:, None]
    torch.testing.assert_close(delayed.loss, ((delayed.velocity - target) ** 2)[free].mean())
    assert not torch.allclose(delayed.velocity[:, 8:], plain.velocity[:, 8:])
    with pytest.raises(ValueError, match=r"inference_delay must lie in \[0, action_horizon - 1 = 15\]"):
        model(**batch, actions=actions, inference_delay=16)


def test_bad_rtc_arguments_are_named(model: PI0ForActionGeneration) -> None:
    batch = small_batch(model.config)
    with pytest.raises(ValueError, match="execution_horizon is required"):
        model.generate_actions(**batch, previous_actions=noise(2), inference_delay=2)
    with pytest.raises(ValueError, match=r"previous_actions must have shape \(2, 16, 8\)"):
        model.generate_actions(**batch, previous_actions=noise(2)[:, :10], inference_delay=2, execution_horizon=4)
    with pytest.raises(ValueError, match="previous_actions must be finite"):
        model.generate_actions(**batch, previous_actions=noise(2) * float("nan"), inference_delay=2, execution_horizon=4)
    with pytest.raises(ValueError, match="rtc_method must be one of"):
        model.generate_actions(**batch, previous_actions=noise(2), inference_delay=2, execution_horizon=4, rtc_method="x")


@pytest.mark.slow
def test_compiled_guided_sampling_matches_eager() -> None:
    torch.manual_seed(0)
    model = PI0ForActionGeneration(PI0Config.from_preset("pi05_small", **SMALL)).eval()
    batch, previous = small_batch(model.config), noise(2)
    kwargs = dict(noise=noise(1), num_steps=2, previous_actions=previous, inference_delay=3, execution_horizon=5)
    eager = model.generate_actions(**batch, **kwargs)
    model.compile_sampling()
    try:
        compiled = model.generate_actions(**batch, **kwargs)
    finally:
        model.compile_sampling(disable=True)
    torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-4)
