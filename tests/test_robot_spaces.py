"""Value conversions between a robot's units and a checkpoint's space (openpi's ALOHA `adapt_to_pi`), on their own
and inside `PI0Processor` (training targets in, actions out, saved with the processor)."""

from __future__ import annotations

import numpy as np
import pytest

from pi0_torch import PI0Config
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.robot_spaces import get_conversion
from pi0_torch.processing.tokenization import build_test_tokenizer

ALOHA = get_conversion("aloha")
SIGNS = np.array([1, -1, -1, 1, 1, 1, 1] * 2)
JOINTS = [i for i in range(14) if i not in (6, 13)]
ALOHA_DELTA_MASK = [True] * 6 + [False] + [True] * 6 + [False]  # openpi: make_bool_mask(6, -1, 6, -1)


def test_aloha_matches_openpis_formulas_at_hand_worked_points() -> None:
    """Two joints per arm flip sign. A fully open gripper (0.058 m) puts the linkage at arcsin(1) = pi/2, a closed one
    (0.01844 m) at arcsin(-0.5816979); a gripper action moves from PI's angle to ALOHA's normalised joint range."""
    state = np.arange(1, 15, dtype=np.float32) / 10
    state[6], state[13] = 1.0, 0.0  # left gripper fully open, right one closed (ALOHA's normalised opening)
    converted = ALOHA.state_to_model(state)
    np.testing.assert_allclose(converted[JOINTS], (SIGNS * state)[JOINTS], rtol=1e-6)
    np.testing.assert_allclose(converted[6], (np.pi / 2 - 0.5476) / (1.6296 - 0.5476), rtol=1e-5)
    np.testing.assert_allclose(converted[13], (np.arcsin(-0.5816979) - 0.5476) / (1.6296 - 0.5476), rtol=1e-4)

    actions = np.tile(state, (2, 1))
    actions[:, 6], actions[:, 13] = 0.0, 1.0621  # PI gripper angles
    robot = ALOHA.actions_to_robot(actions)
    np.testing.assert_allclose(robot[:, JOINTS], (SIGNS * actions)[:, JOINTS], rtol=1e-6)
    np.testing.assert_allclose(robot[:, 6], (0.5476 + 0.6213) / (1.4910 + 0.6213), rtol=1e-5)
    np.testing.assert_allclose(robot[:, 13], (1.0621 + 0.5476 + 0.6213) / (1.4910 + 0.6213), rtol=1e-5)
    np.testing.assert_allclose(ALOHA.actions_to_model(robot), actions, rtol=1e-5, atol=1e-6)  # openpi's inverse
    assert converted.dtype == robot.dtype == np.float32
    # any leading batch axes
    batched = ALOHA.state_to_model(np.stack([state, state])[None])
    assert batched.shape == (1, 2, 14) and np.allclose(batched[0, 1], converted)
    with pytest.raises(ValueError, match="unknown value conversion 'ur5'; expected one of aloha"):
        get_conversion("ur5")


def aloha_processor(value_conversion: str | None, **kwargs) -> PI0Processor:
    rng = np.random.default_rng(0)
    stats = {key: NormStats(mean=rng.normal(size=14), std=rng.uniform(0.5, 2.0, size=14)) for key in ("state", "actions")}
    return PI0Processor.from_config(
        PI0Config.from_preset("pi0_small"), build_test_tokenizer(), stats, delta_action_mask=ALOHA_DELTA_MASK,
        value_conversion=value_conversion, **kwargs,
    )


def aloha_observation(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "images": {"base_0_rgb": rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)},
        "prompt": "fold the towel",
        "state": rng.uniform(0.1, 0.9, 14),
        "actions": rng.uniform(0.1, 0.9, (50, 14)),
    }


def test_processor_converts_state_and_targets_in_and_actions_out(tmp_path) -> None:
    """With `value_conversion`, the processor is the plain one fed converted values; postprocessing converts back,
    so targets survive the round trip in robot units (delta actions taken against the converted state)."""
    converting, plain = aloha_processor("aloha"), aloha_processor(None)
    obs = aloha_observation()
    in_model_space = dict(obs, state=ALOHA.state_to_model(obs["state"]), actions=ALOHA.actions_to_model(obs["actions"]))
    encoded, expected = converting(obs), plain(in_model_space)
    for name in ("state", "input_ids", "actions"):
        np.testing.assert_allclose(encoded[name].numpy(), expected[name].numpy(), rtol=1e-6, atol=1e-6)

    model_actions = encoded["actions"][0].numpy()
    robot = converting.postprocess_actions(model_actions, state=obs["state"])
    plain_robot = plain.postprocess_actions(model_actions, state=in_model_space["state"])
    np.testing.assert_allclose(robot, ALOHA.actions_to_robot(plain_robot), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(robot, obs["actions"], atol=1e-5)  # round trip
    as_torch = converting.postprocess_actions(encoded["actions"], state=obs["state"][None])
    np.testing.assert_allclose(as_torch[0].numpy(), robot, atol=1e-6)

    converting.save_pretrained(tmp_path)
    assert PI0Processor.from_pretrained(tmp_path).value_conversion == "aloha"
    with pytest.raises(ValueError, match="value_conversion 'aloha' applies to a state and actions of 14 values, got "
                                         "state_dim 8 and action_dim_robot 8"):
        aloha_processor("aloha", state_dim=8, action_dim_robot=8)
