"""Numerical parity with openpi's own JAX outputs at every level of the model (fixtures in tests/fixtures/openpi).

Relative error = max|ours - ref| / max|ref|. Float32 must agree to 1e-4 (measured ~1e-6); bf16 inference to 3e-2.
`python tests/test_parity.py` prints the measured table.
"""

from __future__ import annotations

import numpy as np
import torch

from pi0_torch.masks import prefix_lm_mask
from pi0_torch.models.flow_matching import euler_times, interpolate, sincos_time_embedding
from pi0_torch.inference.layout import compact_prefix
from pi0_torch.inference.sampling import SamplingInputs

from conftest import VARIANTS, OpenpiReference, relative_error

FLOAT32_TOLERANCE = 1e-4
BF16_TOLERANCE = 3e-2


def implied_attention(valid: torch.Tensor, first: torch.Tensor, length: int, suffix_ends: list[int]) -> torch.Tensor:
    """The bool mask `[B, P + S, P + S]` over the original token layout that our key ranges amount to: each sample's
    valid prefix tokens sit, in order, in slots `[first, length)` and see each other; suffix token t (slot
    `length + t`) sees the valid prefix and the suffix slots before `suffix_ends[t]`. Padded rows and columns stay
    False (openpi's mask leaves them False too)."""
    batch, prefix_len = valid.shape
    suffix_len = len(suffix_ends)
    mask = torch.zeros(batch, prefix_len + suffix_len, prefix_len + suffix_len, dtype=torch.bool)
    for b in range(batch):
        prefix = valid[b].nonzero()[:, 0].tolist()
        assert len(prefix) == length - int(first[b])
        mask[b, torch.tensor(prefix)[:, None], torch.tensor(prefix)[None, :]] = True
        for t, end in enumerate(suffix_ends):
            mask[b, prefix_len + t, prefix] = True
            mask[b, prefix_len + t, prefix_len : prefix_len + end - length] = True
    return mask


def suffix_ends(model, length: int) -> list[int]:
    """The end slot of each suffix token's keys (π0: the state token stops after itself)."""
    config = model.config
    if config.pi05:
        return [length + config.action_horizon] * config.action_horizon
    return [length + 1] + [length + config.suffix_len] * config.action_horizon


def layout_of(model, inputs: dict[str, torch.Tensor]):
    """The prefix layout `generate_actions` uses for `inputs` (one host read of the checked inputs)."""
    facts = model._check_inputs(inputs["pixel_values"], inputs["image_masks"], inputs["input_ids"], inputs["attention_mask"], inputs["state"])
    return facts.layout(model.config.tokens_per_image)


@torch.no_grad()
def loss_path_errors(ref: OpenpiReference, dtype: torch.dtype = torch.float32) -> dict[str, float]:
    """Errors of every intermediate of openpi's `compute_loss` pass (`fp32/loss_path/*`)."""
    model, inputs = ref.model(dtype), ref.model_inputs()
    config, mode = model.config, "fp32"
    time, noise, actions = ref.tensor("inputs/loss_time"), ref.tensor("inputs/loss_noise"), ref.tensor("inputs/actions")
    errors: dict[str, float] = {}

    images = inputs["pixel_values"].flatten(0, 1)
    encoded = model.vision_tower(pixel_values=images).last_hidden_state.unflatten(0, inputs["pixel_values"].shape[:2])
    image_tokens = model.embed_images(inputs["pixel_values"])
    for c, camera in enumerate(config.camera_names):
        errors[f"siglip_encoded/{camera}"] = relative_error(encoded[:, c], ref[f"{mode}/loss_path/siglip/{camera}/encoded"])
        errors[f"img_tokens/{camera}"] = relative_error(image_tokens[:, c], ref[f"{mode}/loss_path/img_tokens/{camera}"])

    prefix, prefix_valid = model.embed_prefix(
        inputs["pixel_values"], inputs["image_masks"], inputs["input_ids"], inputs["attention_mask"]
    )
    assert torch.equal(prefix_valid, ref.tensor(f"{mode}/loss_path/prefix_mask"))
    errors["prefix_tokens (valid)"] = relative_error(prefix[prefix_valid], ref[f"{mode}/loss_path/prefix_tokens"][prefix_valid.numpy()])

    errors["time_emb_sincos"] = relative_error(
        sincos_time_embedding(time, config.expert_hidden_size, config.time_min_period, config.time_max_period),
        ref[f"{mode}/loss_path/time_emb_sincos"],
    )
    x_t, target = interpolate(actions, noise, time)
    errors["x_t"] = relative_error(x_t, ref[f"{mode}/loss_path/x_t"])
    errors["u_t"] = relative_error(target, ref[f"{mode}/loss_path/u_t"])
    if config.pi05:
        errors["adarms_cond"] = relative_error(model.time_conditioning(time), ref[f"{mode}/loss_path/adarms_cond"])
    conditioning = model.conditioning(time).per_token(config.action_horizon)
    suffix = model.embed_suffix(inputs["state"], x_t, conditioning.condition)
    batch = x_t.shape[0]
    errors["suffix_tokens"] = relative_error(suffix.view(batch, config.suffix_len, -1), ref[f"{mode}/loss_path/suffix_tokens"])

    # our key ranges over the compacted prefix amount to openpi's prefix-LM mask; positions count valid tokens
    layout = layout_of(model, inputs)
    compacted, first = compact_prefix(prefix, prefix_valid, layout)
    valid = torch.cat([prefix_valid, ref.tensor(f"{mode}/loss_path/suffix_mask")], dim=1)
    flags = torch.cat([ref.tensor(f"{mode}/loss_path/prefix_ar_mask"), ref.tensor(f"{mode}/loss_path/suffix_ar_mask")])
    mask, positions = prefix_lm_mask(valid, flags)
    assert torch.equal(mask, ref.tensor(f"{mode}/loss_path/attn_mask"))
    assert torch.equal(positions, ref.tensor(f"{mode}/loss_path/positions").long())
    ours = implied_attention(prefix_valid, first, layout.length, suffix_ends(model, layout.length))
    pairs = valid[:, :, None] & valid[:, None, :]
    assert torch.equal(ours & pairs, mask & pairs)
    suffix_positions = (layout.length - first)[:, None] + torch.arange(config.suffix_len)
    assert torch.equal(suffix_positions, positions[:, prefix_valid.shape[1] :])

    prefix_out, suffix_out = model.run_layers(compacted, suffix, first, layout, conditioning)
    prefix_out = prefix_out.view(batch, layout.length, -1)
    reference_prefix_out = ref[f"{mode}/loss_path/prefix_out"]  # padded query rows are meaningless: valid tokens only
    errors["prefix_out (valid)"] = max(
        relative_error(prefix_out[b, int(first[b]) :], reference_prefix_out[b, prefix_valid[b].numpy()]) for b in range(batch)
    )
    errors["suffix_out"] = relative_error(suffix_out.view(batch, config.suffix_len, -1), ref[f"{mode}/loss_path/suffix_out"])

    output = model(**inputs, actions=actions, noise=noise, time=time)
    errors["v_t"] = relative_error(output.velocity, ref[f"{mode}/loss_path/v_t"])
    per_step_loss = ((output.velocity - target) ** 2).mean(dim=-1)  # openpi's compute_loss: [B, horizon]
    errors["loss"] = relative_error(per_step_loss, ref[f"{mode}/loss"])
    errors["loss (scalar mean)"] = relative_error(output.loss, ref[f"{mode}/loss"].mean())
    return errors


@torch.no_grad()
def sample_path_errors(ref: OpenpiReference) -> dict[str, float]:
    """Errors of openpi's `sample_actions`: the prefix k/v cache, the first step, every Euler step, the actions."""
    model, inputs = ref.model(), ref.model_inputs()
    config = model.config
    errors: dict[str, float] = {}
    times = euler_times(int(ref["inputs/num_steps"]))
    np.testing.assert_array_equal(np.array(times, dtype=np.float32), ref["fp32/sample_path/traj_time"])
    layout = layout_of(model, inputs)
    sampling = SamplingInputs(
        inputs["pixel_values"], inputs["image_masks"], inputs["input_ids"], inputs["attention_mask"], inputs["state"],
        ref.tensor("inputs/sample_noise"), torch.tensor(times),
    )
    cache = model.cache_prefix(sampling, layout)
    # openpi: [layers, B, P, K, H] over the original layout; ours: per layer [B, K, slots, H], each sample's valid
    # prefix tokens in order in slots [first, length): compare them with openpi's cache at its valid positions
    ref_valid = ref["fp32/loss_path/prefix_mask"]  # same inputs
    for name, ours in (("k", cache.keys), ("v", cache.values)):
        reference = ref[f"fp32/sample_path/kv_cache_{name}"]
        errors[f"kv_cache_{name} (valid)"] = max(
            relative_error(torch.stack([layer[b, :, int(cache.first[b]) : layout.length].transpose(0, 1) for layer in ours]),
                           reference[:, b, ref_valid[b]])
            for b in range(ref_valid.shape[0])
        )
    ours = implied_attention(torch.from_numpy(ref_valid), cache.first, layout.length, suffix_ends(model, layout.length))
    full_mask = ref.tensor("fp32/sample_path/step0_full_attn_mask")  # [B, S, P + S]
    rows = ours[:, ref_valid.shape[1] :]
    keys = torch.cat([torch.from_numpy(ref_valid), torch.ones(ref_valid.shape[0], config.suffix_len, dtype=torch.bool)], 1)
    assert torch.equal(rows & keys[:, None], full_mask & keys[:, None])
    suffix_positions = (layout.length - cache.first)[:, None] + torch.arange(config.suffix_len)
    assert torch.equal(suffix_positions, ref.tensor("fp32/sample_path/step0_suffix_positions").long())

    x_t = sampling.noise
    steps = model.conditioning(sampling.times).steps()
    step0_tokens = model.embed_suffix(inputs["state"], x_t, steps[0].condition)
    errors["step0_suffix_tokens"] = relative_error(
        step0_tokens.view(x_t.shape[0], config.suffix_len, -1), ref["fp32/sample_path/step0_suffix_tokens"]
    )
    actions_pass = model.action_pass(cache)
    velocity_errors, state_errors = [], []
    for step, conditioning in enumerate(steps):
        velocity = model.denoise_step(actions_pass, x_t, conditioning)
        x_t = x_t + (-1.0 / len(times)) * velocity
        velocity_errors.append(relative_error(velocity, ref["fp32/sample_path/traj_v"][step]))
        state_errors.append(relative_error(x_t, ref["fp32/sample_path/traj_x"][step]))
    errors["traj_v (worst step)"] = max(velocity_errors)
    errors["traj_x (worst step)"] = max(state_errors)

    actions = model.generate_actions(**inputs, noise=ref.tensor("inputs/sample_noise"))
    errors["actions"] = relative_error(actions, ref["fp32/actions"])

    # the plain reference loop (openpi's layout and mask, the state token recomputed every step), as openpi
    plain, plain_cache = model.sample_actions_reference(**inputs, noise=ref.tensor("inputs/sample_noise"), return_cache=True)
    errors["actions (reference loop)"] = relative_error(plain, ref["fp32/actions"])
    prefix_len = ref_valid.shape[1]
    for index, name in enumerate(("k", "v")):
        reference = ref[f"fp32/sample_path/kv_cache_{name}"]  # [layers, B, P, K, H]
        ours = torch.stack([layer[index][:, :, :prefix_len].transpose(1, 2) for layer in plain_cache])  # [layers, B, P, K, H]
        errors[f"kv_cache_{name} (reference loop, valid)"] = max(
            relative_error(ours[:, b, ref_valid[b]], reference[:, b, ref_valid[b]]) for b in range(ref_valid.shape[0]))
    return errors


@torch.no_grad()
def bf16_errors(ref: OpenpiReference) -> dict[str, float]:
    """bf16 inference (weights and residual stream bf16, float32 islands) against openpi's `bf16_infer` outputs."""
    model, inputs = ref.model(torch.bfloat16), ref.model_inputs()
    actions = model.generate_actions(**inputs, noise=ref.tensor("inputs/sample_noise"))
    time, noise, target_actions = ref.tensor("inputs/loss_time"), ref.tensor("inputs/loss_noise"), ref.tensor("inputs/actions")
    velocity = model(**inputs, actions=target_actions, noise=noise, time=time).velocity
    per_step_loss = ((velocity - (noise - target_actions)) ** 2).mean(dim=-1)
    return {"bf16 actions": relative_error(actions, ref["bf16_infer/actions"]), "bf16 loss": relative_error(per_step_loss, ref["bf16_infer/loss"])}


def test_loss_path_float32(reference: OpenpiReference) -> None:
    errors = loss_path_errors(reference)
    assert max(errors.values()) <= FLOAT32_TOLERANCE, errors


def test_sample_path_float32(reference: OpenpiReference) -> None:
    errors = sample_path_errors(reference)
    assert max(errors.values()) <= FLOAT32_TOLERANCE, errors


def test_bf16_inference(reference: OpenpiReference) -> None:
    errors = bf16_errors(reference)
    assert max(errors.values()) <= BF16_TOLERANCE, errors
    assert all(np.isfinite(v) for v in errors.values())


def test_batch_elements_are_independent(reference: OpenpiReference) -> None:
    """Each batch element sampled alone gives the same actions as in the batch (masks/positions are per element)."""
    model, inputs = reference.model(), reference.model_inputs()
    noise = reference.tensor("inputs/sample_noise")
    batched = model.generate_actions(**inputs, noise=noise)
    for b in range(noise.shape[0]):
        single = model.generate_actions(**{k: v[b : b + 1] for k, v in inputs.items()}, noise=noise[b : b + 1])
        torch.testing.assert_close(single[0], batched[b], rtol=1e-5, atol=1e-5)


def test_shorter_token_padding_changes_nothing(reference: OpenpiReference) -> None:
    """Padding does not advance positions, so trimming trailing padding leaves the actions unchanged."""
    model, inputs = reference.model(), reference.model_inputs()
    noise = reference.tensor("inputs/sample_noise")
    longest = int(inputs["attention_mask"].sum(1).max())
    trimmed = dict(inputs, input_ids=inputs["input_ids"][:, :longest], attention_mask=inputs["attention_mask"][:, :longest])
    torch.testing.assert_close(
        model.generate_actions(**trimmed, noise=noise), model.generate_actions(**inputs, noise=noise), rtol=1e-5, atol=1e-5
    )


if __name__ == "__main__":
    torch.set_num_threads(2)
    for variant in VARIANTS:
        ref = OpenpiReference(variant)
        print(f"\n{variant}: relative error max|ours-ref|/max|ref|")
        for name, value in {**loss_path_errors(ref), **sample_path_errors(ref), **bf16_errors(ref)}.items():
            print(f"  {name:32s} {value:.2e}")
