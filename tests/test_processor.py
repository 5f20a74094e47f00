"""PI0Processor: observations -> model inputs -> actions, save/load, bad inputs, end to end with the fixture models."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from PIL import Image
from transformers import AutoProcessor

from pi0_torch import PI0Config
from pi0_torch.processing.images import to_model_image
from pi0_torch.processing.normalization import NormStats, load_openpi_norm_stats, normalize
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.tokenization import PromptTokenizer, build_test_tokenizer, format_pi05_prompt

from conftest import FIXTURES, OpenpiReference

STATS_DIR = FIXTURES / "pi0_small" / "ckpt" / "0"
CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
MODEL_KEYS = ["pixel_values", "image_masks", "input_ids", "attention_mask", "state"]


@pytest.fixture(scope="module")
def tokenizer() -> PromptTokenizer:
    return build_test_tokenizer()


@pytest.fixture(scope="module")
def stats() -> dict[str, NormStats]:
    return load_openpi_norm_stats(STATS_DIR)  # dim 8


def make_processor(tokenizer: PromptTokenizer, stats, preset: str = "pi0_small", **kwargs) -> PI0Processor:
    return PI0Processor.from_config(PI0Config.from_preset(preset), tokenizer=tokenizer, norm_stats=stats, **kwargs)


def observation(seed: int = 0, cameras=("base_0_rgb", "left_wrist_0_rgb"), horizon: int | None = None) -> dict:
    rng = np.random.default_rng(seed)
    obs = {
        "images": {name: rng.integers(0, 256, size=(120 + 10 * i, 160, 3), dtype=np.uint8) for i, name in enumerate(cameras)},
        "prompt": f"pick_up the fork number {seed}",
        "state": rng.normal(size=8),
    }
    if horizon is not None:
        obs["actions"] = rng.normal(size=(horizon, 8))
    return obs


def test_single_observation_outputs(tokenizer, stats) -> None:
    processor = make_processor(tokenizer, stats)
    obs = observation()
    out = processor(images=obs["images"], prompt=obs["prompt"], state=obs["state"])
    assert list(out) == MODEL_KEYS
    shapes = {k: (tuple(v.shape), v.dtype) for k, v in out.items()}
    assert shapes == {
        "pixel_values": ((1, 3, 3, 224, 224), torch.float32),
        "image_masks": ((1, 3), torch.bool),
        "input_ids": ((1, 48), torch.int64),
        "attention_mask": ((1, 48), torch.bool),
        "state": ((1, 32), torch.float32),
    }
    assert out["image_masks"].tolist() == [[True, True, False]]  # camera order from the config
    assert torch.all(out["pixel_values"][0, 2] == -1)  # the absent camera: black, masked
    np.testing.assert_array_equal(out["pixel_values"][0, 1].numpy(), to_model_image(obs["images"]["left_wrist_0_rgb"], 224))
    expected_state = (obs["state"] - stats["state"].mean) / (stats["state"].std + 1e-6)
    np.testing.assert_allclose(out["state"][0, :8].numpy(), expected_state, rtol=1e-6)
    assert torch.all(out["state"][0, 8:] == 0)
    ids, mask = tokenizer.tokenize(obs["prompt"], 48)
    assert out["input_ids"][0].tolist() == ids.tolist() and out["attention_mask"][0].tolist() == mask.tolist()
    as_numpy = processor(images=obs["images"], prompt=obs["prompt"], state=obs["state"], return_tensors="np")
    assert all(isinstance(v, np.ndarray) for v in as_numpy.values())
    np.testing.assert_array_equal(as_numpy["pixel_values"], out["pixel_values"].numpy())


def test_images_match_openpi_resize_reference(tokenizer, stats) -> None:
    with np.load(FIXTURES / "pi0_small" / "reference.npz") as reference:
        frame, expected = reference["preproc/resize_in_uint8"][0], reference["preproc/resize_out_uint8_pil"][0]
    out = make_processor(tokenizer, stats)(images={"base_0_rgb": frame}, prompt="x", state=np.zeros(8))
    openpi = np.moveaxis(expected.astype(np.float32) / 255.0 * 2.0 - 1.0, -1, 0)  # openpi: uint8 -> x/255*2-1
    assert np.abs(out["pixel_values"][0, 0].numpy() - openpi).max() <= 2 / 255 + 1e-6


def test_pi05_prompt_carries_discretized_normalized_state(tokenizer, stats) -> None:
    processor = make_processor(tokenizer, stats, preset="pi05_small")
    assert processor.norm_mode == "quantile" and processor.max_token_len == 200
    obs = observation(3)
    out = processor(obs)
    s = stats["state"]
    normalized = (obs["state"] - s.q01) / (s.q99 - s.q01 + 1e-6) * 2.0 - 1.0
    np.testing.assert_allclose(out["state"][0, :8].numpy(), normalized, rtol=1e-6)
    text = format_pi05_prompt(obs["prompt"], normalized)
    assert text.startswith("Task: pick up the fork number 3, State: ") and text.endswith(";\nAction: ")
    ids, mask = tokenizer.tokenize(obs["prompt"], 200, normalized_state=normalized)
    assert out["input_ids"][0].tolist() == ids.tolist() and out["attention_mask"][0].tolist() == mask.tolist()
    assert tokenizer.decode(ids[mask][1:]) == text


def test_batch_forms_agree(tokenizer, stats) -> None:
    processor = make_processor(tokenizer, stats)
    observations = [observation(i, horizon=50) for i in range(3)]
    observations[1]["images"].pop("left_wrist_0_rgb")
    from_dicts = processor(observations)
    singles = [processor(obs) for obs in observations]
    from_arrays = processor(
        images={
            "base_0_rgb": [o["images"]["base_0_rgb"] for o in observations],
            "left_wrist_0_rgb": [o["images"].get("left_wrist_0_rgb") for o in observations],
        },
        prompt=[o["prompt"] for o in observations],
        state=np.stack([o["state"] for o in observations]),
        actions=torch.from_numpy(np.stack([o["actions"] for o in observations])),
    )
    assert list(from_dicts) == [*MODEL_KEYS, "actions"]
    assert from_dicts["image_masks"].tolist() == [[True, True, False], [True, False, False], [True, True, False]]
    for key in from_dicts:
        assert torch.equal(from_dicts[key], from_arrays[key]), key
        assert torch.equal(from_dicts[key], torch.cat([s[key] for s in singles])), key
    # one array per camera with a batch axis, one prompt for all
    same_size = [observation(i) for i in range(2)]
    stacked = processor(
        images={"base_0_rgb": np.stack([o["images"]["base_0_rgb"] for o in same_size])},
        prompt="pick up the fork",
        state=torch.from_numpy(np.stack([o["state"] for o in same_size])),
    )
    assert stacked["pixel_values"].shape == (2, 3, 3, 224, 224)
    assert torch.equal(stacked["input_ids"][0], stacked["input_ids"][1])


def test_training_actions_and_postprocess_roundtrip(tokenizer, stats) -> None:
    for preset in ("pi0_small", "pi05_small"):
        processor = make_processor(tokenizer, stats, preset=preset)
        obs = observation(5, horizon=50)
        out = processor(obs)
        assert out["actions"].shape == (1, 50, 32) and out["actions"].dtype == torch.float32
        expected = normalize(obs["actions"], stats["actions"], processor.norm_mode)
        np.testing.assert_allclose(out["actions"][0, :, :8].numpy(), expected, rtol=1e-5, atol=1e-6)
        assert torch.all(out["actions"][..., 8:] == 0)
        back = processor.postprocess_actions(out["actions"])
        assert isinstance(back, torch.Tensor) and back.shape == (1, 50, 8) and back.dtype == torch.float32
        np.testing.assert_allclose(back[0].numpy(), obs["actions"], atol=1e-5)
        back_np = processor.postprocess_actions(out["actions"][0].numpy())
        assert isinstance(back_np, np.ndarray) and back_np.shape == (50, 8) and back_np.dtype == np.float32
        np.testing.assert_allclose(back_np, obs["actions"], atol=1e-5)


def test_delta_actions(tokenizer, stats) -> None:
    mask = [True] * 7 + [False]  # joints relative to the state, gripper absolute (openpi's make_bool_mask(7, -1))
    processor = make_processor(tokenizer, stats, delta_action_mask=mask)
    obs = observation(7, horizon=50)
    out = processor(obs)
    deltas = obs["actions"].copy()
    deltas[:, :7] -= obs["state"][:7]
    expected = (deltas - stats["actions"].mean) / (stats["actions"].std + 1e-6)
    np.testing.assert_allclose(out["actions"][0, :, :8].numpy(), expected, rtol=1e-5, atol=1e-6)
    back = processor.postprocess_actions(out["actions"], state=obs["state"][None])
    np.testing.assert_allclose(back[0].numpy(), obs["actions"], atol=1e-5)
    back_np = processor.postprocess_actions(out["actions"][0].numpy(), state=obs["state"])
    np.testing.assert_allclose(back_np, obs["actions"], atol=1e-5)
    with pytest.raises(ValueError, match="state: required to undo delta actions"):
        processor.postprocess_actions(out["actions"])
    with pytest.raises(ValueError, match=r"state: expected shape \[1, 8\] for actions of shape \(1, 50, 32\), got \[8\]"):
        processor.postprocess_actions(out["actions"], state=obs["state"])


def test_save_and_load_roundtrip(tokenizer, stats, tmp_path) -> None:
    processor = make_processor(
        tokenizer, stats, preset="pi05_small", delta_action_mask=[True, False], default_prompt="fold the towel"
    )
    processor.save_pretrained(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["norm_stats.json", "processor_config.json", "tokenizer.model"]
    raw = json.loads((tmp_path / "norm_stats.json").read_text())
    assert set(raw["norm_stats"]) == {"state", "actions"} and len(raw["norm_stats"]["state"]["q01"]) == 8
    loaded = PI0Processor.from_pretrained(tmp_path)
    assert loaded.to_dict() == processor.to_dict()
    PI0Config.from_preset("pi05_small").save_pretrained(tmp_path)  # a model folder: AutoProcessor goes by its config
    auto = AutoProcessor.from_pretrained(str(tmp_path))
    assert isinstance(auto, PI0Processor) and auto.to_dict() == processor.to_dict()
    obs = observation(2, horizon=50)
    obs.pop("prompt")  # the default prompt is used
    for other in (loaded, auto):
        a, b = processor(obs), other(obs)
        assert all(torch.equal(a[k], b[k]) for k in a)
        actions = torch.randn(1, 50, 32, generator=torch.Generator().manual_seed(0))
        state = obs["state"][None]
        assert torch.equal(processor.postprocess_actions(actions, state), other.postprocess_actions(actions, state))
    overridden = PI0Processor.from_pretrained(tmp_path, truncation="error")
    assert overridden.truncation == "error"


def test_norm_mode_none_and_explicit_dims(tokenizer) -> None:
    processor = PI0Processor(
        tokenizer, camera_names=["front"], image_size=56, max_token_len=16, norm_mode="none",
        state_dim=3, action_dim_robot=2, model_action_dim=4,
    )
    red = Image.new("RGB", (80, 40), (255, 0, 0))
    out = processor(images={"front": red}, prompt="go", state=[1.0, 2.0, 3.0], actions=np.ones((5, 2)))
    assert out["pixel_values"].shape == (1, 1, 3, 56, 56)
    assert out["state"].tolist() == [[1.0, 2.0, 3.0, 0.0]] and torch.all(out["actions"][..., :2] == 1)
    assert processor.postprocess_actions(np.full((5, 4), 0.5)).tolist() == [[0.5, 0.5]] * 5


def test_construction_errors(tokenizer, stats) -> None:
    with pytest.raises(ValueError, match="tokenizer has .* tokens but the model's vocab_size is 100"):
        PI0Processor.from_config(PI0Config.from_preset("pi0_small", vocab_size=100), tokenizer=tokenizer, norm_stats=stats)
    with pytest.raises(ValueError, match="needs norm_stats"):
        PI0Processor(tokenizer, state_dim=8, action_dim_robot=8)
    with pytest.raises(ValueError, match=r"norm_stats lacks \['actions'\]"):
        PI0Processor(tokenizer, norm_stats={"state": stats["state"]})
    with pytest.raises(ValueError, match="state_dim is 9 but the 'state' norm stats have only 8 dims"):
        PI0Processor(tokenizer, norm_stats=stats, state_dim=9)
    with pytest.raises(ValueError, match="quantile' needs q01/q99"):
        PI0Processor(tokenizer, norm_mode="quantile", norm_stats={k: NormStats(v.mean, v.std) for k, v in stats.items()})
    with pytest.raises(ValueError, match=r"required_cameras \['top'\] are not among camera_names"):
        PI0Processor(tokenizer, norm_stats=stats, required_cameras=["top"])
    with pytest.raises(ValueError, match="delta_action_mask has 9 entries"):
        PI0Processor(tokenizer, norm_stats=stats, delta_action_mask=[True] * 9)
    with pytest.raises(ValueError, match="norm_mode must be one of"):
        PI0Processor(tokenizer, norm_stats=stats, norm_mode="minmax")
    with pytest.raises(FileNotFoundError, match="processor_config.json is missing"):
        PI0Processor.from_pretrained(STATS_DIR)
    # stats longer than the robot are cut to its dims (openpi slices the same way)
    processor = PI0Processor(tokenizer, norm_stats=stats, state_dim=6, action_dim_robot=7)
    out = processor(images={"base_0_rgb": np.zeros((8, 8, 3), np.uint8)}, prompt="x", state=np.zeros(6))
    assert out["state"].shape == (1, 32)


def test_near_constant_stats_warn_at_construction(tokenizer, stats) -> None:
    flat = dict(stats)
    s = stats["state"]
    flat["state"] = NormStats(mean=s.mean, std=np.r_[s.std[:7], 0.0], q01=s.q01, q99=s.q99)
    with pytest.warns(UserWarning, match=r"norm stats 'state': dims \[7\] are \(near\) constant"):
        processor = PI0Processor(tokenizer, norm_stats=flat)
    state = np.r_[np.zeros(7), flat["state"].mean[7] + 0.01]
    out = processor(images={"base_0_rgb": np.zeros((8, 8, 3), np.uint8)}, prompt="x", state=state)
    assert abs(float(out["state"][0, 7])) <= 10.0 + 1e-3  # openpi: 0.01 / 1e-6 = 1e4


BAD_INPUTS = [
    (dict(state=np.zeros(7)), r"^state: expected shape \[8\], got \[7\]"),
    (dict(state=np.zeros((1, 2, 8))), r"^state: expected \[8\] or \[B, 8\], got shape \(1, 2, 8\)"),
    (dict(state=None), r"^state: required"),
    (dict(state=np.array([0, 1, np.nan, 3, 4, 5, np.inf, 7.0])), r"^state: contains NaN or inf at dims \[2, 6\]"),
    (dict(state=np.array(["a"] * 8)), r"^state: expected real numbers, got dtype <U1"),
    (dict(state=torch.zeros(8, dtype=torch.bool)), r"^state: expected real numbers, got dtype torch.bool"),
    (
        dict(images={"top": np.zeros((8, 8, 3), np.uint8)}),
        r"^images: unknown camera names \['top'\]; this model's cameras are "
        r"\['base_0_rgb', 'left_wrist_0_rgb', 'right_wrist_0_rgb'\]",
    ),
    (dict(images={}), r"^images: no camera frame given"),
    (dict(images={"base_0_rgb": None}), r"^images: no camera frame given"),
    (dict(images=[np.zeros((8, 8, 3), np.uint8)]), r"^images: expected a dict"),
    (
        dict(images={"base_0_rgb": np.zeros((8, 8, 3), np.uint16)}),
        r"^images\['base_0_rgb'\]: expected dtype uint8 or float, got uint16",
    ),
    (dict(images={"base_0_rgb": np.full((8, 8, 3), np.nan, np.float32)}), r"^images\['base_0_rgb'\]: contains NaN or inf"),
    (
        dict(images={"base_0_rgb": np.full((8, 8, 3), 255.0, np.float32)}),
        r"^images\['base_0_rgb'\]: float frame must be in \[0, 1\].*pass a uint8 frame",
    ),
    (dict(prompt=""), r"^prompt: empty after cleaning"),
    (dict(prompt="  \n "), r"^prompt: empty after cleaning"),
    (dict(prompt=None), r"^prompt: required"),
    (dict(prompt=["a", "b"]), r"^prompt: expected a string, got list"),
    (dict(actions=np.zeros((50, 7))), r"^actions: expected shape \[50, 8\], got \(50, 7\)"),
    (dict(actions=np.zeros((49, 8))), r"^actions: expected shape \[50, 8\], got \(49, 8\)"),
    (dict(actions=np.full((50, 8), np.nan)), r"^actions: contains NaN or inf"),
]


@pytest.mark.parametrize(("change", "message"), BAD_INPUTS)
def test_bad_inputs(tokenizer, stats, change: dict, message: str) -> None:
    processor = make_processor(tokenizer, stats)
    kwargs = dict(images={"base_0_rgb": np.zeros((8, 8, 3), np.uint8)}, prompt="pick up the fork", state=np.zeros(8))
    kwargs.update(change)
    with pytest.raises(ValueError, match=message):
        processor(**kwargs)


def test_bad_batches_and_dicts(tokenizer, stats) -> None:
    processor = make_processor(tokenizer, stats, required_cameras=["left_wrist_0_rgb"])
    frame = np.zeros((8, 8, 3), np.uint8)
    missing = r"^\[1\] images: required cameras \['left_wrist_0_rgb'\] are missing; got \['base_0_rgb'\]"
    with pytest.raises(ValueError, match=missing):
        processor(images={"base_0_rgb": [frame, frame], "left_wrist_0_rgb": [frame, None]}, prompt="x", state=np.zeros((2, 8)))
    with pytest.raises(ValueError, match=r"^images\['base_0_rgb'\]: a batch of 3, but state \[2, 8\] is a batch of 2"):
        processor(images={"base_0_rgb": [frame] * 3}, prompt="x", state=np.zeros((2, 8)))
    with pytest.raises(ValueError, match=r"^images\['base_0_rgb'\]: one frame \(48, 8, 3\), but state \[1, 8\] is a batch of 1 "
                                         r"\(2-D: one row per observation\); pass the state as a vector \[8\]"):
        processor(images={"base_0_rgb": np.zeros((48, 8, 3), np.uint8)}, prompt="x", state=np.zeros((1, 8)))  # (was "a batch of 48")
    with pytest.raises(ValueError, match=r"^prompt: a batch of 1, but state \[2, 8\] is a batch of 2"):
        processor(images={"left_wrist_0_rgb": [frame] * 2}, prompt=["x"], state=np.zeros((2, 8)))
    with pytest.raises(ValueError, match=r"^\[0\] state: contains NaN"):
        processor(images={"left_wrist_0_rgb": [frame] * 2}, prompt="x", state=np.array([[np.nan] * 8, [0.0] * 8]))
    good = {"images": {"left_wrist_0_rgb": frame}, "prompt": "x", "state": np.zeros(8)}
    with pytest.raises(ValueError, match=r"^observations\[1\]: unknown keys \['image'\]"):
        processor([good, {"image": {}, "prompt": "x", "state": np.zeros(8)}])
    with pytest.raises(ValueError, match=r"^observations\[1\]\.state: expected shape \[8\], got \[3\]"):
        processor([good, {**good, "state": np.zeros(3)}])
    with pytest.raises(ValueError, match="actions: given for some observations of the batch but not for others"):
        processor([good, {**good, "actions": np.zeros((50, 8))}])
    with pytest.raises(ValueError, match="pass either observation dicts or images="):
        processor(good, state=np.zeros(8))
    with pytest.raises(ValueError, match="return_tensors must be 'pt' or 'np'"):
        processor(good, return_tensors="tf")
    with pytest.raises(ValueError, match=r"actions: expected \[horizon, D\] or \[B, horizon, D\] with D >= action_dim_robot=8"):
        processor.postprocess_actions(np.zeros((50, 4)))
    with pytest.raises(ValueError, match="actions: expected a float array, got dtype int64"):
        processor.postprocess_actions(np.zeros((50, 32), np.int64))


def test_long_prompt_warns_or_raises(tokenizer, stats) -> None:
    long_prompt = "pick up the red cup and place it on the shelf " * 12
    obs = {"images": {"base_0_rgb": np.zeros((8, 8, 3), np.uint8)}, "prompt": long_prompt, "state": np.zeros(8)}
    with pytest.warns(UserWarning, match=r"prompt: \d+ tokens exceed max_token_len 48 .*truncating"):
        out = make_processor(tokenizer, stats)(obs)
    assert bool(out["attention_mask"].all())
    with pytest.raises(ValueError, match=r"^observation\.prompt: \d+ tokens exceed max_token_len 48"):
        make_processor(tokenizer, stats, truncation="error")(obs)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_processor(tokenizer, stats)({**obs, "prompt": "pick up the fork"})


@pytest.mark.parametrize("variant", ["pi0_small", "pi05_small"])
def test_end_to_end_with_fixture_model(tokenizer, stats, variant: str) -> None:
    reference = OpenpiReference(variant)
    model = reference.model()
    processor = PI0Processor.from_config(model.config, tokenizer=tokenizer, norm_stats=stats, state_dim=8, action_dim_robot=7)
    observations = [observation(i, cameras=CAMERAS[: 3 - i], horizon=50) for i in range(2)]
    for obs in observations:
        obs["actions"] = obs["actions"][:, :7]
    inputs = processor(observations)
    actions = model.generate_actions(**{k: inputs[k] for k in MODEL_KEYS}, generator=torch.Generator().manual_seed(0))
    robot = processor.postprocess_actions(actions)
    assert robot.shape == (2, 50, 7) and torch.isfinite(robot).all()
    single = processor.postprocess_actions(actions[0].numpy())
    assert single.shape == (50, 7) and np.allclose(single, robot[0].numpy(), rtol=1e-5, atol=1e-5)
    loss = model(**inputs).loss
    assert loss.ndim == 0 and torch.isfinite(loss)


def test_pi05_without_the_state_in_its_prompt_uses_pi0s_prompt() -> None:
    """openpi's pi05_libero (discrete_state_input=False): a π0.5 prompt without the discretized state is π0's
    `bos + text + "\\n"`; the published checkpoint's settings say so (it was refused before)."""
    from pi0_torch.conversion.download import PUBLISHED_CHECKPOINTS
    from pi0_torch.processing.normalization import NormStats
    from pi0_torch.processing.tokenization import build_test_tokenizer

    stats = NormStats(mean=np.zeros(3), std=np.ones(3), q01=-np.ones(3), q99=np.ones(3))
    common = dict(camera_names=["base_0_rgb"], max_token_len=48, norm_stats={"state": stats, "actions": stats})
    tokenizer = build_test_tokenizer()
    observation = {"images": {"base_0_rgb": np.zeros((8, 8, 3), np.uint8)}, "prompt": "pick up the cube", "state": np.ones(3)}
    without = PI0Processor(tokenizer, pi05=True, state_in_prompt=False, **common)(observation)
    pi0 = PI0Processor(tokenizer, pi05=False, norm_mode="quantile", **common)(observation)
    with_state = PI0Processor(tokenizer, pi05=True, **common)(observation)
    assert torch.equal(without["input_ids"], pi0["input_ids"]) and not torch.equal(without["input_ids"], with_state["input_ids"])
    assert PI0Processor(tokenizer, pi05=True, state_in_prompt=False, **common).to_dict()["state_in_prompt"] is False
    assert PUBLISHED_CHECKPOINTS["pi05_libero"].processor_options() == {"state_in_prompt": False}
    with pytest.raises(ValueError, match="state_in_prompt applies to π0.5"):
        PI0Processor(tokenizer, pi05=False, state_in_prompt=True, **common)


def test_a_delta_action_mask_is_a_list_of_booleans_one_per_action_dim(tokenizer) -> None:
    """Issue 63, round 5 item 10: `delta_action_mask: "110"` read as three trues, and a short mask was taken without a
    word. A string or non-boolean entries are refused; a short mask leaves the other dims absolute (openpi's rule)
    and says which; a relative dim beyond the state is refused."""
    stats = {key: NormStats(mean=np.zeros(3), std=np.ones(3)) for key in ("state", "actions")}
    make = lambda mask, **more: PI0Processor(tokenizer, camera_names=["base_0_rgb"], norm_stats=stats,  # noqa: E731
                                             delta_action_mask=mask, **more)
    for mask in ("110", [1, 1, 2], [True, None, False], 3):
        with pytest.raises(ValueError, match=r"delta_action_mask must be a list of true / false, one per robot action dim \(3\)"):
            make(mask)
    with pytest.warns(UserWarning, match=r"delta_action_mask has 2 entries for 3 action dims: dims \[2\] are absolute"):
        assert make([True, True]).delta_action_mask == [True, True, False]
    assert make([1, 0, 1]).delta_action_mask == [True, False, True]
    with pytest.raises(ValueError, match=r"delta_action_mask has 4 entries, more than the robot's 3 action dims"):
        make([True] * 4)
    with pytest.raises(ValueError, match=r"makes action dim 2 relative to the state, which has 2 dims"):
        make([False, False, True], state_dim=2)
