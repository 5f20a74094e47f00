"""The benchmark adapters (`pi0_torch.envs.aloha`, `pi0_torch.envs.libero`) and our serving path against openpi's
preprocessing, which this file re-implements from openpi's code:

- client side: `examples/aloha_sim/env.py` (`_convert_observation`), `examples/libero/main.py` (180 degree rotation,
  `_quat2axisangle`, the message keys), `openpi_client/image_tools.py` (`resize_with_pad`, `convert_to_uint8`);
- server side: `policies/aloha_policy.py` (`AlohaInputs`: `adapt_to_pi`, cameras, image masks),
  `policies/libero_policy.py` (`LiberoInputs`: the padding camera, masked for π0 only), `transforms.py`
  (`Normalize`: z-score for π0, quantiles for the others; `ResizeImages`; `TokenizePrompt`; `PadStatesAndActions`;
  `InjectDefaultPrompt`), `models/tokenizer.py` (`PaligemmaTokenizer.tokenize`), `models/model.py`
  (`Observation.from_dict`: uint8 -> [-1, 1]), `policies/policy.py` (the batch goes through `jax.tree.map`, which
  orders each dict's keys, so the cameras reach the model sorted by name), `training/config.py` (the settings of
  `pi0_aloha_sim`, `pi0_libero`, `pi05_libero`).

Our path is the adapter's observation -> `ObservationFormat.from_preset(...).to_default` -> `PI0Processor` of a small
config with the settings a converted checkpoint has (`PUBLISHED_CHECKPOINTS`). Images must agree bit for bit, tokens
exactly, the state to 1e-6.

Raw observations:
- ALOHA: recorded from the real gym-aloha 0.1.5 env, `tests/fixtures/benchmarks/aloha_transfer_cube.npz`: `top`
  [2, 480, 640, 3] uint8 and `agent_pos` [2, 14] float64, the observation of `reset(seed=0)` of
  `gym_aloha/AlohaTransferCube-v0` (obs_type `pixels_agent_pos`, MUJOCO_GL=osmesa) and the one after a step holding
  that state. Recorded with:

      env = gymnasium.make("gym_aloha/AlohaTransferCube-v0", obs_type="pixels_agent_pos")
      first, _ = env.reset(seed=0)
      second, *_ = env.step(np.asarray(first["agent_pos"], np.float32))
      np.savez_compressed(path, top=np.stack([first["pixels"]["top"], second["pixels"]["top"]]),
                          agent_pos=np.stack([first["agent_pos"], second["agent_pos"]]))

- LIBERO: synthetic, because LIBERO's scene assets cannot be downloaded here: LIBERO's exact keys, shapes and dtypes
  (`agentview_image` / `robot0_eye_in_hand_image` 256x256x3 uint8 with image-like content, `robot0_eef_pos` (3,),
  `robot0_eef_quat` (4,) unit xyzw, `robot0_gripper_qpos` (2,)), seeded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pi0_torch import PI0Config, PI0Processor
from pi0_torch.conversion.download import PUBLISHED_CHECKPOINTS
from pi0_torch.envs.aloha import AlohaSimEnv, aloha_observation
from pi0_torch.envs.libero import libero_observation, quat_to_axis_angle
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.runtime.observation_formats import ObservationFormat

ALOHA_FIXTURE = Path(__file__).parent / "fixtures" / "benchmarks" / "aloha_transfer_cube.npz"
LIBERO_PROMPT = "pick up the black bowl between the plate and the ramekin and place it on the plate"


# ------------------------------------------------------------------------------------------------------------------
# openpi's preprocessing, re-implemented from its code
# ------------------------------------------------------------------------------------------------------------------


def openpi_resize_with_pad(images: np.ndarray, height: int, width: int) -> np.ndarray:
    """openpi_client.image_tools.resize_with_pad (PIL bilinear, pasted on a black canvas)."""
    if images.shape[-3:-1] == (height, width):
        return images
    out = []
    for image in images.reshape(-1, *images.shape[-3:]):
        pil = Image.fromarray(image)
        cur_width, cur_height = pil.size
        ratio = max(cur_width / width, cur_height / height)
        resized_height, resized_width = int(cur_height / ratio), int(cur_width / ratio)
        resized = pil.resize((resized_width, resized_height), resample=Image.BILINEAR)
        canvas = Image.new(resized.mode, (width, height), 0)
        canvas.paste(resized, (max(0, int((width - resized_width) / 2)), max(0, int((height - resized_height) / 2))))
        out.append(np.asarray(canvas))
    return np.stack(out).reshape(*images.shape[:-3], height, width, images.shape[-1])


def openpi_convert_to_uint8(image: np.ndarray) -> np.ndarray:
    if np.issubdtype(image.dtype, np.floating):
        image = (255 * np.clip(image, 0.0, 1.0)).astype(np.uint8)
    return image


def openpi_quat2axisangle(quat: np.ndarray) -> np.ndarray:
    quat = np.array(quat, np.float64)  # (openpi clips the caller's array in place)
    quat[3] = min(max(quat[3], -1.0), 1.0)
    den = np.sqrt(1.0 - quat[3] * quat[3])
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return (quat[:3] * 2.0 * math.acos(quat[3])) / den


def openpi_aloha_client(gym_obs: dict) -> dict:
    image = openpi_convert_to_uint8(openpi_resize_with_pad(gym_obs["pixels"]["top"], 224, 224))
    return {"state": gym_obs["agent_pos"], "images": {"cam_high": np.transpose(image, (2, 0, 1))}}


def openpi_libero_client(obs: dict, task_description: str) -> dict:
    image = np.ascontiguousarray(obs["agentview_image"][::-1, ::-1])
    wrist = np.ascontiguousarray(obs["robot0_eye_in_hand_image"][::-1, ::-1])
    return {
        "observation/image": openpi_convert_to_uint8(openpi_resize_with_pad(image, 224, 224)),
        "observation/wrist_image": openpi_convert_to_uint8(openpi_resize_with_pad(wrist, 224, 224)),
        "observation/state": np.concatenate(
            (obs["robot0_eef_pos"], openpi_quat2axisangle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"])),
        "prompt": str(task_description),
    }


def _gripper_to_angular(value: np.ndarray) -> np.ndarray:
    value = value * (0.05800 - 0.01844) + 0.01844
    arm_length, horn_radius = 0.036, 0.022
    value = np.arcsin(np.clip((horn_radius**2 + value**2 - arm_length**2) / (2 * horn_radius * value), -1.0, 1.0))
    return (value - 0.5476) / (1.6296 - 0.5476)


def openpi_aloha_inputs(data: dict, adapt_to_pi: bool = True) -> dict:
    """AlohaInputs (the same for every model type)."""
    state = np.asarray(data["state"])
    if adapt_to_pi:
        state = np.array([1, -1, -1, 1, 1, 1, 1, 1, -1, -1, 1, 1, 1, 1]) * state
        state[[6, 13]] = _gripper_to_angular(state[[6, 13]])
    frames = {name: np.transpose(np.asarray(image), (1, 2, 0)) for name, image in data["images"].items()}
    base = frames["cam_high"]
    images, masks = {"base_0_rgb": base}, {"base_0_rgb": True}
    for dest, source in (("left_wrist_0_rgb", "cam_left_wrist"), ("right_wrist_0_rgb", "cam_right_wrist")):
        images[dest] = frames.get(source, np.zeros_like(base))
        masks[dest] = source in frames
    inputs = {"image": images, "image_mask": masks, "state": state}
    if "prompt" in data:
        inputs["prompt"] = data["prompt"]
    return inputs


def openpi_libero_inputs(data: dict, fast: bool = False) -> dict:
    """LiberoInputs: the right wrist is a zero image, masked for π0 / π0.5 but not for π0-FAST."""
    base, wrist = np.asarray(data["observation/image"]), np.asarray(data["observation/wrist_image"])
    return {
        "state": data["observation/state"],
        "image": {"base_0_rgb": base, "left_wrist_0_rgb": wrist, "right_wrist_0_rgb": np.zeros_like(base)},
        "image_mask": {"base_0_rgb": True, "left_wrist_0_rgb": True, "right_wrist_0_rgb": fast},
        "prompt": data["prompt"],
    }


def openpi_tokenize(sentencepiece, prompt: str, state: np.ndarray | None, max_len: int) -> tuple[np.ndarray, np.ndarray]:
    """PaligemmaTokenizer.tokenize."""
    text = prompt.strip().replace("_", " ").replace("\n", " ")
    if state is not None:
        bins = np.digitize(state, bins=np.linspace(-1, 1, 256 + 1)[:-1]) - 1
        tokens = sentencepiece.encode(f"Task: {text}, State: {' '.join(map(str, bins))};\nAction: ", add_bos=True)
    else:
        tokens = sentencepiece.encode(text, add_bos=True) + sentencepiece.encode("\n")
    mask = [True] * min(len(tokens), max_len) + [False] * (max_len - len(tokens))
    tokens = (tokens + [0] * (max_len - len(tokens)))[:max_len]
    return np.asarray(tokens), np.asarray(mask)


def openpi_model_inputs(inputs: dict, stats: dict[str, NormStats], *, quantile: bool, discrete_state: bool,
                        sentencepiece, max_len: int = 48, action_dim: int = 32, default_prompt: str | None = None) -> dict:
    """Normalize -> InjectDefaultPrompt -> ResizeImages(224) -> TokenizePrompt -> PadStatesAndActions -> batch
    (jax.tree.map: cameras in sorted order) -> Observation.from_dict."""
    state, norm = np.asarray(inputs["state"]), stats["state"]
    dims = state.shape[-1]
    if quantile:
        state = (state - norm.q01[:dims]) / (norm.q99[:dims] - norm.q01[:dims] + 1e-6) * 2.0 - 1.0
    else:
        state = (state - norm.mean[:dims]) / (norm.std[:dims] + 1e-6)
    prompt = inputs.get("prompt", default_prompt)
    images = {name: openpi_resize_with_pad(image, 224, 224) for name, image in inputs["image"].items()}
    tokens, token_mask = openpi_tokenize(sentencepiece, prompt, state if discrete_state else None, max_len)
    padded = np.pad(state, (0, action_dim - dims))
    names = sorted(images)
    return {
        "camera_names": names,
        "pixel_values": np.stack([images[n].astype(np.float32) / 255.0 * 2.0 - 1.0 for n in names]),  # [C, H, W, 3]
        "image_masks": np.asarray([inputs["image_mask"][n] for n in names]),
        "input_ids": tokens,
        "attention_mask": token_mask,
        "state": padded.astype(np.float32),
    }


# ------------------------------------------------------------------------------------------------------------------
# our path
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tokenizer():
    return build_test_tokenizer(extra_sentences=[LIBERO_PROMPT, "Transfer cube"])


def norm_stats(state_dim: int, action_dim: int, seed: int) -> dict[str, NormStats]:
    rng = np.random.default_rng(seed)

    def one(dim: int) -> NormStats:
        mean, std = rng.normal(0.0, 0.3, dim), rng.uniform(0.2, 1.0, dim)
        return NormStats(mean=mean, std=std, q01=mean - 2.2 * std, q99=mean + 2.1 * std)

    return {"state": one(state_dim), "actions": one(action_dim)}


def converted_processor(checkpoint: str, preset: str, tokenizer, stats, **extra) -> PI0Processor:
    """A processor with the settings `pi0-torch convert --checkpoint <checkpoint>` gives, on a small config."""
    published = PUBLISHED_CHECKPOINTS[checkpoint]
    config = PI0Config.from_preset(preset, **published.config_overrides())
    return PI0Processor.from_config(config, tokenizer, norm_stats=stats, **published.processor_options(), **extra)


def our_model_inputs(message: dict, obs_format: str, processor: PI0Processor) -> dict:
    observation = ObservationFormat.from_preset(obs_format).to_default(message)
    inputs = processor(images=observation["images"], prompt=observation["prompt"], state=observation["state"],
                       return_tensors="np")
    return {key: value[0] for key, value in inputs.items()}


def assert_same_model_inputs(ours: dict, reference: dict, processor: PI0Processor) -> None:
    assert processor.camera_names == reference["camera_names"]
    np.testing.assert_array_equal(ours["pixel_values"], reference["pixel_values"].transpose(0, 3, 1, 2))
    np.testing.assert_array_equal(ours["image_masks"], reference["image_masks"])
    np.testing.assert_array_equal(ours["input_ids"], reference["input_ids"])
    np.testing.assert_array_equal(ours["attention_mask"], reference["attention_mask"])
    np.testing.assert_allclose(ours["state"], reference["state"], rtol=0, atol=1e-6)


def aloha_recordings() -> list[dict]:
    recorded = np.load(ALOHA_FIXTURE)
    return [{"pixels": {"top": top}, "agent_pos": state} for top, state in zip(recorded["top"], recorded["agent_pos"])]


def libero_raw(seed: int) -> dict:
    """A LIBERO observation with LIBERO's keys, shapes and dtypes: smooth gradients with noise (so that resizing
    has something to average), an unnormalized-then-normalized xyzw quaternion."""
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0, 255, 256)
    def frame() -> np.ndarray:
        base = (ramp[:, None, None] * rng.uniform(0.2, 1.0, 3) + ramp[None, :, None] * rng.uniform(0, 0.5, 3)) / 1.5
        return np.clip(base + rng.normal(0, 12, (256, 256, 3)), 0, 255).astype(np.uint8)

    quat = rng.normal(size=4)
    return {
        "agentview_image": frame(),
        "robot0_eye_in_hand_image": frame(),
        "robot0_eef_pos": rng.normal(0.0, 0.3, 3),
        "robot0_eef_quat": quat / np.linalg.norm(quat),
        "robot0_gripper_qpos": np.array([0.039, -0.039]) * rng.uniform(0.1, 1.0),
    }


# ------------------------------------------------------------------------------------------------------------------
# tests
# ------------------------------------------------------------------------------------------------------------------


def test_aloha_fixture_is_a_real_recording() -> None:
    recorded = np.load(ALOHA_FIXTURE)
    assert recorded["top"].shape == (2, 480, 640, 3) and recorded["top"].dtype == np.uint8
    assert recorded["agent_pos"].shape == (2, 14) and recorded["agent_pos"].dtype == np.float64
    assert len({int(v) for v in np.unique(recorded["top"][0])}) > 50  # a rendered scene, not a flat test pattern


@pytest.mark.parametrize("index", [0, 1])
def test_aloha_adapter_sends_openpi_client_message(index: int) -> None:
    raw = aloha_recordings()[index]
    ours, reference = aloha_observation(raw), openpi_aloha_client(raw)
    assert sorted(ours) == sorted(reference) == ["images", "state"]  # no prompt: the server injects its default
    assert list(ours["images"]) == ["cam_high"]
    np.testing.assert_array_equal(ours["images"]["cam_high"], reference["images"]["cam_high"])
    assert ours["images"]["cam_high"].dtype == np.uint8 and ours["images"]["cam_high"].shape == (3, 224, 224)
    np.testing.assert_array_equal(ours["state"], reference["state"])


@pytest.mark.parametrize("index", [0, 1])
def test_aloha_model_inputs_match_openpi_pi0_aloha_sim(index: int, tokenizer) -> None:
    """pi0_aloha_sim: π0, AlohaInputs(adapt_to_pi=True), z-score, default prompt "Transfer cube", no delta actions;
    cam_high is the base camera, both wrists are zero images with their masks off."""
    raw = aloha_recordings()[index]
    stats = norm_stats(14, 14, seed=index)
    processor = converted_processor("pi0_aloha_sim", "pi0_small", tokenizer, stats)  # (its default prompt included)
    ours = our_model_inputs(aloha_observation(raw), "aloha", processor)
    reference = openpi_model_inputs(openpi_aloha_inputs(openpi_aloha_client(raw)), stats, quantile=False,
                                    discrete_state=False, sentencepiece=tokenizer.backend, default_prompt="Transfer cube")
    assert_same_model_inputs(ours, reference, processor)
    assert reference["image_masks"].tolist() == [True, False, False]


def test_converted_pi0_aloha_sim_has_openpi_default_prompt(tokenizer) -> None:
    processor = converted_processor("pi0_aloha_sim", "pi0_small", tokenizer, norm_stats(14, 14, seed=0))
    assert processor.default_prompt == "Transfer cube"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_libero_adapter_sends_openpi_client_message(seed: int) -> None:
    raw = libero_raw(seed)
    ours, reference = libero_observation(raw, LIBERO_PROMPT), openpi_libero_client(raw, LIBERO_PROMPT)
    assert sorted(ours) == sorted(reference)
    for key in ("observation/image", "observation/wrist_image"):
        assert ours[key].dtype == np.uint8 and ours[key].shape == (224, 224, 3)
        np.testing.assert_array_equal(ours[key], reference[key])
    np.testing.assert_allclose(ours["observation/state"], reference["observation/state"], rtol=0, atol=1e-12)
    assert ours["prompt"] == reference["prompt"]


def test_libero_frames_are_rotated_half_a_turn() -> None:
    raw = libero_raw(0)
    raw["agentview_image"] = np.zeros((256, 256, 3), np.uint8)
    raw["agentview_image"][:128, :128] = 255  # the top-left quarter of the camera frame ...
    image = libero_observation(raw, "x")["observation/image"]
    assert image[-50, -50].tolist() == [255] * 3 and image[50, 50].tolist() == [0] * 3  # ... is the bottom right


@pytest.mark.parametrize(("checkpoint", "preset", "quantile"), [("pi0_libero", "pi0_small", False),
                                                                ("pi05_libero", "pi05_small", True)])
def test_libero_model_inputs_match_openpi(checkpoint: str, preset: str, quantile: bool, tokenizer) -> None:
    """pi0_libero (π0: z-score) and pi05_libero (π0.5: quantiles, `discrete_state_input=False`, so π0's prompt and
    the state to the action expert); the padding right-wrist camera is masked."""
    raw = libero_raw(3)
    stats = norm_stats(8, 7, seed=3)
    processor = converted_processor(checkpoint, preset, tokenizer, stats)
    ours = our_model_inputs(libero_observation(raw, LIBERO_PROMPT), "libero", processor)
    reference = openpi_model_inputs(openpi_libero_inputs(openpi_libero_client(raw, LIBERO_PROMPT)), stats,
                                    quantile=quantile, discrete_state=False, sentencepiece=tokenizer.backend,
                                    max_len=processor.max_token_len)
    assert_same_model_inputs(ours, reference, processor)
    assert reference["image_masks"].tolist() == [True, True, False]


def test_libero_pi05_discrete_state_prompt_matches_openpi(tokenizer) -> None:
    """A π0.5 with openpi's default `discrete_state_input=True`: the normalized state, in 256 bins, is in the prompt."""
    raw = libero_raw(4)
    stats = norm_stats(8, 7, seed=4)
    processor = PI0Processor.from_config(PI0Config.from_preset("pi05_small"), tokenizer, norm_stats=stats)
    ours = our_model_inputs(libero_observation(raw, LIBERO_PROMPT), "libero", processor)
    reference = openpi_model_inputs(openpi_libero_inputs(openpi_libero_client(raw, LIBERO_PROMPT)), stats,
                                    quantile=True, discrete_state=True, sentencepiece=tokenizer.backend, max_len=200)
    assert_same_model_inputs(ours, reference, processor)
    assert "State: " in tokenizer.decode(ours["input_ids"][ours["attention_mask"]])


def test_libero_fast_camera_order_matches_openpi() -> None:
    from pi0_torch.models.configuration_pi0_fast import FAST_CAMERA_NAMES

    message = libero_observation(libero_raw(5), LIBERO_PROMPT)
    frames = ObservationFormat.from_preset("libero_fast").to_default(message)["images"]
    in_model_order = [frames.get(camera) for camera in FAST_CAMERA_NAMES]  # None: the black padding frame
    reference = openpi_libero_inputs(openpi_libero_client(libero_raw(5), LIBERO_PROMPT), fast=True)
    expected = [reference["image"][name] for name in sorted(reference["image"])]
    assert in_model_order[2] is None and np.array_equal(in_model_order[1], expected[1])


def test_libero_observation_refuses_bad_input_by_name() -> None:
    raw = libero_raw(0)
    with pytest.raises(ValueError, match="robot0_eef_quat"):
        libero_observation({**raw, "robot0_eef_quat": np.zeros(3)}, "x")
    with pytest.raises(ValueError, match="agentview_image.*uint8"):
        libero_observation({**raw, "agentview_image": raw["agentview_image"] / 255.0}, "x")
    with pytest.raises(ValueError, match="missing 'robot0_gripper_qpos'"):
        libero_observation({k: v for k, v in raw.items() if k != "robot0_gripper_qpos"}, "x")


def test_quat_to_axis_angle_matches_scipy_and_openpi() -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    quats = rng.normal(size=(200, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    tiny = np.array([1e-7, 1e-4])[:, None] * np.array([[0.6, 0.0, 0.8]])  # rotations of 2e-7 and 2e-4 rad
    near_identity = np.concatenate([np.concatenate([tiny, np.sqrt(1 - (tiny**2).sum(1, keepdims=True))], 1),
                                    np.concatenate([tiny, -np.sqrt(1 - (tiny**2).sum(1, keepdims=True))], 1)])
    for quat in [*quats, *near_identity]:
        ours = quat_to_axis_angle(quat)
        np.testing.assert_allclose(ours, openpi_quat2axisangle(quat), rtol=0, atol=1e-12)
        rotation = Rotation.from_quat(quat)  # scipy: scalar-last (x, y, z, w), as robosuite
        if quat[3] >= 0:  # scipy folds the angle to [0, pi]; openpi's 2 acos(w) exceeds pi when w < 0
            np.testing.assert_allclose(ours, rotation.as_rotvec(), rtol=0, atol=1e-6)
        elif quat[3] > -0.999:  # (near w = -1, 1 - w^2 cancels: openpi's vector is off by up to 1% there, kept)
            assert (Rotation.from_rotvec(ours) * rotation.inv()).magnitude() < 1e-6  # the same rotation
            assert np.linalg.norm(ours) == pytest.approx(2 * math.acos(quat[3]), abs=1e-9)
    for identity in ([0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -1.0], [0.0, 0.0, 0.0, 1.0 + 1e-9]):
        np.testing.assert_array_equal(quat_to_axis_angle(np.array(identity)), np.zeros(3))
    quat = np.array([0.0, 0.0, 0.0, 1.5])
    quat_to_axis_angle(quat)
    assert quat[3] == 1.5  # the caller's array is left alone


@pytest.mark.parametrize("max_steps", [12, pytest.param(None, marks=pytest.mark.slow)])  # (None: gym-aloha's 300)
def test_aloha_episode_runs_through_evaluate(max_steps: int | None) -> None:
    """A real ALOHA sim episode through `pi0-torch eval`'s loop: a random tiny π0 with the `aloha` preset's cameras,
    the adapter's replan steps (10) and hold action, the task's name; 12 steps in `make test`, the whole episode of
    300 steps in `make test-slow` (about 2 minutes of software rendering)."""
    from pi0_torch.envs.rendering import RenderingError, check_mujoco_rendering

    try:  # (before gym_aloha is imported: it imports MuJoCo, which fails to import where its GL library is missing)
        check_mujoco_rendering()
    except RenderingError as error:
        pytest.skip(f"MuJoCo cannot render here: {error}")
    pytest.importorskip("gym_aloha")
    import torch

    from pi0_torch import PI0ForActionGeneration
    from pi0_torch.runtime.policy import PI0Policy
    from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, evaluate

    torch.manual_seed(0)
    config = PI0Config.from_preset("pi0_small", image_size=28, max_token_len=16, action_horizon=12, action_dim=16,
                                   vision_num_layers=1, num_hidden_layers=2, vocab_size=512)
    stats = {key: NormStats(mean=np.zeros(14), std=np.ones(14)) for key in ("state", "actions")}
    processor = PI0Processor.from_config(config, build_test_tokenizer(), norm_stats=stats, value_conversion="aloha",
                                         default_prompt="Transfer cube")
    policy = LocalPolicy(PI0Policy(PI0ForActionGeneration(config), processor, num_steps=2, seed=0))
    # (`pi0-torch eval` takes the replan steps from the env when none are given; `evaluate` takes them as set)
    settings = EvalSettings(env="aloha/AlohaTransferCube-v0", episodes=1, num_envs=1, seed=0, max_steps=max_steps,
                            replan_steps=AlohaSimEnv.replan_steps, inference_delay=2)  # (2 steps of hold_action)
    result = evaluate(policy, settings)
    assert result.complete and result.episodes == 1 and result.replan_steps == 10
    assert result.episodes_detail[0]["steps"] == (max_steps or 300)  # (a random policy does not transfer the cube)
    assert result.per_task["AlohaTransferCube-v0"]["episodes"] == 1
