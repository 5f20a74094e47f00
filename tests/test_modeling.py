"""PI0ForActionGeneration behaviour: loading and saving, gradients, checkpointing, reproducibility, input errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file
from transformers import AutoConfig, AutoModel

from pi0_torch import PI0Config, PI0ForActionGeneration

from conftest import OpenpiReference, enable_checkpointing


def small_batch(config: PI0Config, batch: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    size, length = config.image_size, config.max_token_len
    attention_mask = torch.arange(length)[None, :] < torch.tensor([length // 2, length // 3])[:batch, None]
    return dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        image_masks=torch.tensor([[True, True, True], [True, False, True]])[:batch],
        input_ids=torch.randint(1, config.vocab_size, (batch, length), generator=generator),
        attention_mask=attention_mask,
        state=torch.randn(batch, config.action_dim, generator=generator),
    )


@pytest.fixture(scope="module")
def tiny_pi0() -> PI0ForActionGeneration:
    torch.manual_seed(0)
    return PI0ForActionGeneration(PI0Config.from_preset("pi0_small")).eval()


# -- presets and sizes ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset, expected", [("pi0", 3_238_048_528), ("pi05", 3_353_433_872)])
def test_released_parameter_counts_equal_openpi(preset: str, expected: int) -> None:
    with torch.device("meta"):  # no 13 GB allocation
        model = PI0ForActionGeneration(PI0Config.from_preset(preset))
    assert sum(p.numel() for p in model.parameters()) == expected
    names = [name for name, _ in model.named_parameters()]
    assert not any("lm_head" in n for n in names)
    assert sum("embed" in n and "vision" not in n for n in names) == 1  # one text embedding table, none for the expert


def test_model_type_is_not_transformers_pi0() -> None:
    assert PI0Config.model_type == "pi0_torch"
    with pytest.raises(ValueError, match="unknown preset"):
        PI0Config.from_preset("pi1")


def test_patch_positions_of_a_new_model_start_as_2d_sine_cosine(tiny_pi0: PI0ForActionGeneration) -> None:
    table = tiny_pi0.vision_tower.embeddings.position_embedding.weight.detach()  # [16 * 16 patches, 40]
    grid, quarter = 16, table.shape[1] // 4
    omega = [10_000.0 ** (-k / (quarter - 1)) for k in range(quarter)]  # 1 down to 1e-4
    row, column = 5, 11
    expected = [math.sin(column * w) for w in omega] + [math.cos(column * w) for w in omega]
    expected += [math.sin(row * w) for w in omega] + [math.cos(row * w) for w in omega]
    torch.testing.assert_close(table[row * grid + column], torch.tensor(expected), rtol=0, atol=1e-6)
    assert tiny_pi0.vision_tower.embeddings.position_embedding.weight.requires_grad  # still a learned table


# -- save / load -----------------------------------------------------------------------------------------------------------


def test_save_and_load_round_trip_is_bit_exact(tiny_pi0: PI0ForActionGeneration, tmp_path: Path) -> None:
    tiny_pi0.save_pretrained(tmp_path)
    assert (tmp_path / "model.safetensors").exists()
    assert json.loads((tmp_path / "config.json").read_text())["model_type"] == "pi0_torch"
    for loader in (PI0ForActionGeneration.from_pretrained, AutoModel.from_pretrained):
        loaded = loader(tmp_path)
        assert isinstance(loaded, PI0ForActionGeneration)
        original, reloaded = tiny_pi0.state_dict(), loaded.state_dict()
        assert original.keys() == reloaded.keys()
        assert all(torch.equal(original[k], reloaded[k]) for k in original)
    assert isinstance(AutoConfig.from_pretrained(tmp_path), PI0Config)


def _corrupt(tmp_path: Path, model: PI0ForActionGeneration, change: str) -> Path:
    model.save_pretrained(tmp_path)
    weights = load_file(tmp_path / "model.safetensors")
    if change == "missing":
        del weights["layers.1.expert.qkv_proj.weight"]
    elif change == "unexpected":
        weights["lm_head.weight"] = torch.zeros(3, 3)
    elif change == "mis-shaped":
        weights["action_out_proj.weight"] = torch.zeros(31, model.config.expert_hidden_size)
    save_file(weights, tmp_path / "model.safetensors", metadata={"format": "pt"})
    return tmp_path


@pytest.mark.parametrize("change, named", [
    ("missing", "layers.1.expert.qkv_proj.weight"),
    ("unexpected", "lm_head.weight"),
    ("mis-shaped", "action_out_proj.weight"),
])
def test_mismatched_checkpoint_refuses_to_load(tiny_pi0: PI0ForActionGeneration, tmp_path: Path, change: str, named: str) -> None:
    folder = _corrupt(tmp_path, tiny_pi0, change)
    with pytest.raises(ValueError, match=rf"{change}.*{named.replace('.', '[.]')}"):
        PI0ForActionGeneration.from_pretrained(folder)


@pytest.mark.parametrize("dtype, stored", [(torch.int32, "I32"), (torch.int64, "I64"), (torch.bool, "BOOL"),
                                           (torch.float8_e4m3fn, "F8_E4M3")])
def test_weights_stored_as_another_kind_refuse_to_load(tiny_pi0: PI0ForActionGeneration, tmp_path: Path,
                                                      dtype: torch.dtype, stored: str) -> None:
    """Issue 38.7: the demo policy saved as int32 loaded silently (560 of 272,947 parameters non-zero) and served
    normal-looking actions. A floating parameter stored as integers, booleans or 8-bit floats is refused, named."""
    tiny_pi0.save_pretrained(tmp_path)
    weights = load_file(tmp_path / "model.safetensors")
    weights["action_out_proj.weight"] = weights["action_out_proj.weight"].to(dtype)
    save_file(weights, tmp_path / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(ValueError, match=rf"not floating-point: action_out_proj[.]weight \({stored}\)$"):
        PI0ForActionGeneration.from_pretrained(tmp_path)
    tiny_pi0.to(torch.bfloat16).save_pretrained(tmp_path)  # (BF16 is floating: it loads)
    tiny_pi0.float()
    assert PI0ForActionGeneration.from_pretrained(tmp_path).dtype == torch.bfloat16


@pytest.mark.parametrize("time", [2.0, 1.0001, -0.5])
def test_flow_times_outside_zero_to_one_are_refused(tiny_pi0: PI0ForActionGeneration, time: float) -> None:
    """Issue 38.15: `forward(time=2.0)` extrapolated silently; a flow time lies in [0, 1] (1 noise, 0 the actions:
    training-time real-time chunking gives its committed steps at 0)."""
    batch = small_batch(tiny_pi0.config)
    with pytest.raises(ValueError, match=r"^time: flow times must lie in \[0, 1\]"):
        tiny_pi0(**batch, time=torch.full((2,), time))
    assert torch.isfinite(tiny_pi0(**batch, time=torch.tensor([0.0, 1.0])).velocity).all()


def test_pi0_checkpoint_does_not_load_as_pi05(tiny_pi0: PI0ForActionGeneration, tmp_path: Path) -> None:
    tiny_pi0.save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    (tmp_path / "config.json").write_text(json.dumps({**config, "pi05": True}))
    with pytest.raises(ValueError, match="missing.*unexpected"):
        PI0ForActionGeneration.from_pretrained(tmp_path)


# -- training ---------------------------------------------------------------------------------------------------------------


def _unused_by_loss(model: PI0ForActionGeneration) -> set[str]:
    """Parameters the flow loss cannot depend on: the suffix reads the prefix only through the k/v of each layer,
    so the VLM's final norm and the last layer's VLM post-attention weights never reach the velocity."""
    last = f"layers.{model.config.num_hidden_layers - 1}.vlm"
    return {"vlm_final_norm.weight", f"{last}.o_proj.weight", f"{last}.mlp_norm.weight", f"{last}.gate_up_proj.weight", f"{last}.down_proj.weight"}


def test_every_parameter_that_influences_the_loss_gets_a_gradient(references: dict[str, OpenpiReference]) -> None:
    for ref in references.values():
        model = ref.model().train()
        output = model(**ref.model_inputs(), actions=ref.tensor("inputs/actions"))
        assert output.loss.dim() == 0 and output.loss.requires_grad
        output.loss.backward()
        unused = _unused_by_loss(model)
        for name, parameter in model.named_parameters():
            if name in unused:
                assert parameter.grad is None or not parameter.grad.any(), name
            else:
                assert parameter.grad is not None and torch.isfinite(parameter.grad).all() and parameter.grad.any(), name


def test_gradient_checkpointing_gives_the_same_gradients(references: dict[str, OpenpiReference]) -> None:
    ref = references["pi05_small"]
    inputs = dict(ref.model_inputs(), actions=ref.tensor("inputs/actions"), noise=ref.tensor("inputs/loss_noise"), time=ref.tensor("inputs/loss_time"))
    gradients = []
    for checkpointing in (False, True):
        model = ref.model().train()
        if checkpointing:
            enable_checkpointing(model)
            assert all(layer.gradient_checkpointing for layer in model.layers)
            assert all(layer.gradient_checkpointing for layer in model.vision_tower.encoder.layers)
        model(**inputs).loss.backward()
        gradients.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    assert gradients[0].keys() == gradients[1].keys()
    for name in gradients[0]:
        torch.testing.assert_close(gradients[1][name], gradients[0][name], rtol=1e-5, atol=1e-7, msg=name)


def test_forward_without_actions_returns_velocity_only(tiny_pi0: PI0ForActionGeneration) -> None:
    output = tiny_pi0(**small_batch(tiny_pi0.config))
    assert output.loss is None and output.velocity.shape == (2, 50, 32)


def test_random_time_and_noise_are_drawn_in_training(tiny_pi0: PI0ForActionGeneration) -> None:
    batch = small_batch(tiny_pi0.config)
    actions = torch.randn(2, 50, 32)
    torch.manual_seed(1)
    first = tiny_pi0(**batch, actions=actions).loss
    second = tiny_pi0(**batch, actions=actions).loss
    torch.manual_seed(1)
    again = tiny_pi0(**batch, actions=actions).loss
    assert torch.isfinite(first) and first != second and first == again


# -- sampling -----------------------------------------------------------------------------------------------------------------


def test_generator_makes_sampling_reproducible(tiny_pi0: PI0ForActionGeneration) -> None:
    batch = small_batch(tiny_pi0.config)
    sample = lambda seed: tiny_pi0.generate_actions(**batch, generator=torch.Generator().manual_seed(seed), num_steps=3)
    assert torch.equal(sample(7), sample(7))
    assert not torch.equal(sample(7), sample(8))


def test_pi05_ignores_state(references: dict[str, OpenpiReference]) -> None:
    ref = references["pi05_small"]
    model, inputs = ref.model(), ref.model_inputs()
    noise = ref.tensor("inputs/sample_noise")
    with_state = model.generate_actions(**inputs, noise=noise, num_steps=2)
    without_state = model.generate_actions(**{k: v for k, v in inputs.items() if k != "state"}, noise=noise, num_steps=2)
    assert torch.equal(with_state, without_state)


def test_fully_masked_rows_stay_finite_in_bf16(tiny_pi0: PI0ForActionGeneration) -> None:
    model = PI0ForActionGeneration(tiny_pi0.config).eval().to(torch.bfloat16)
    batch = small_batch(model.config)
    batch["image_masks"][:, 1:] = False  # two cameras' image tokens masked: many fully masked query rows
    assert torch.isfinite(model.generate_actions(**batch, num_steps=2)).all()
    assert torch.isfinite(model.sample_actions_reference(**batch, num_steps=2)).all()  # (openpi's mask: the rows kept)


# -- input errors --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("field, bad_value, message", [
    ("pixel_values", lambda b: b["pixel_values"][:, :2], r"pixel_values must have shape \(2, 3, 3, 224, 224\)"),
    ("pixel_values", lambda b: b["pixel_values"].permute(0, 1, 3, 4, 2), r"pixel_values must have shape"),
    ("pixel_values", lambda b: (b["pixel_values"] + 1) * 127.5, r"pixel_values must lie in \[-1, 1\]"),
    ("pixel_values", lambda b: b["pixel_values"].to(torch.uint8), r"pixel_values must be a floating-point"),
    ("pixel_values", lambda b: b["pixel_values"][0], r"pixel_values must be a float tensor \[B, num_cameras=3"),
    ("image_masks", lambda b: b["image_masks"].long(), r"image_masks must have dtype"),
    ("input_ids", lambda b: torch.ones(2, 49, dtype=torch.long), r"max_token_len=48"),
    ("input_ids", lambda b: b["input_ids"].float(), r"input_ids must have dtype"),
    ("attention_mask", lambda b: b["attention_mask"][:, :10], r"attention_mask must have shape \(2, 48\)"),
    ("state", lambda b: None, r"state is required by pi0"),
    ("state", lambda b: b["state"][:, :7], r"state must have shape \(2, 32\)"),
])
def test_bad_inputs_raise_clear_errors(tiny_pi0: PI0ForActionGeneration, field: str, bad_value, message: str) -> None:
    batch = small_batch(tiny_pi0.config)
    batch[field] = bad_value(batch)
    with pytest.raises(ValueError, match=message):
        tiny_pi0.generate_actions(**batch)
    with pytest.raises(ValueError, match=message):
        tiny_pi0(**batch)


@pytest.mark.parametrize("field", ["image_masks", "attention_mask"])
def test_a_sample_with_no_camera_or_no_token_is_refused(tiny_pi0: PI0ForActionGeneration, field: str) -> None:
    """Issue 63, round 5 item 10: every `image_masks` or `attention_mask` entry of a sample False gave actions from
    nothing; refused by name (the other sample is fine)."""
    batch = small_batch(tiny_pi0.config)
    batch[field] = batch[field].clone()
    batch[field][1] = False
    with pytest.raises(ValueError, match=rf"^{field}: every entry of sample 1 is False, so the model would act on no "):
        tiny_pi0.generate_actions(**batch)


def test_bad_noise_and_actions_raise_clear_errors(tiny_pi0: PI0ForActionGeneration) -> None:
    batch = small_batch(tiny_pi0.config)
    with pytest.raises(ValueError, match=r"noise: values in \[1e\+30, 1e\+30\], beyond ±1000"):  # (returned actions of 1e30)
        tiny_pi0.generate_actions(**batch, noise=torch.full((2, 50, 32), 1e30))
    with pytest.raises(ValueError, match=r"noise must have shape \(2, 50, 32\)"):
        tiny_pi0.generate_actions(**batch, noise=torch.zeros(2, 50, 7))
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 50, 32\)"):
        tiny_pi0(**batch, actions=torch.zeros(2, 10, 32))
    with pytest.raises(ValueError, match=r"num_steps must be an integer in \[1, "):
        tiny_pi0.generate_actions(**batch, num_steps=0)


@pytest.mark.slow
def test_compiled_sampling_matches_eager(references: dict[str, OpenpiReference]) -> None:
    """`compile_sampling` (regional: each repeated layer compiled once) keeps the numbers on both fixtures."""
    for ref in references.values():
        model, inputs = ref.model(), ref.model_inputs()
        noise = ref.tensor("inputs/sample_noise")
        eager = model.generate_actions(**inputs, noise=noise)
        model.compile_sampling()
        compiled = model.generate_actions(**inputs, noise=noise)
        model.compile_sampling(disable=True)
        torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-5)
