"""The tabletop environments: registration, spaces, determinism, dynamics, each task's success and failure, experts."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from pi0_torch.envs import ENV_IDS, ConveyorEnv, PickPlaceEnv, ReachEnv, make_expert
from pi0_torch.envs.tabletop import (
    GRASP_RADIUS, MAX_SPEED, OFF_TABLE_COLOR, PALETTE, TABLE_COLOR, Renderer, World, Zone,
)
from pi0_torch.envs.tasks import BELT_SPEED


def _placed(env_class: type, seed: int = 0, **kwargs) -> tuple:
    """An env reset with `seed`, its world, and the index of the named object."""
    env = env_class(image_size=32, **kwargs)
    env.reset(seed=seed)
    return env, env.world, env.layout.target_object


def _rollout(env: gymnasium.Env, seed: int, actions=None) -> tuple[list, list]:
    """(observations, infos) of one episode: the expert's actions, or the given ones."""
    observation, info = env.reset(seed=seed)
    expert = make_expert(env)
    expert.reset(seed)
    observations, infos = [observation], [info]
    for t in range(env.spec.max_episode_steps if actions is None else len(actions)):
        action = expert.act(env) if actions is None else actions[t]
        observation, _, terminated, truncated, info = env.step(action)
        observations.append(observation)
        infos.append(info)
        if terminated or truncated:
            break
    return observations, infos


def test_ids_register_with_default_step_limits():
    assert ENV_IDS == ("pi0_torch/Reach-v0", "pi0_torch/PickPlace-v0", "pi0_torch/Conveyor-v0")
    limits = {env_id: gymnasium.make(env_id).spec.max_episode_steps for env_id in ENV_IDS}
    assert limits == {"pi0_torch/Reach-v0": 40, "pi0_torch/PickPlace-v0": 100, "pi0_torch/Conveyor-v0": 100}
    env = gymnasium.make("pi0_torch.envs:pi0_torch/Reach-v0", image_size=32)  # the module-qualified form too
    assert isinstance(env.unwrapped, ReachEnv) and env.unwrapped.control_hz == 10


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_observation_format_and_spaces(env_id):
    env = gymnasium.make(env_id, image_size=48)
    observation, info = env.reset(seed=1)
    assert set(observation) == {"images", "state", "prompt"}
    image = observation["images"]["base_0_rgb"]
    assert image.shape == (48, 48, 3) and image.dtype == np.uint8
    assert observation["state"].shape == (3,) and observation["state"].dtype == np.float32
    assert observation["state"][2] == 0.0  # the gripper starts open
    assert isinstance(observation["prompt"], str) and observation["prompt"] == env.unwrapped.prompt
    assert env.observation_space.contains(observation)
    assert env.action_space.shape == (3,) and env.action_space.dtype == np.float32
    assert set(info) >= {"is_success", "stage", "held_object", "slipped"} and info["is_success"] is False
    observation, _, _, _, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(observation) and isinstance(info["is_success"], bool)


def test_prompts_name_the_target():
    env, world, target = _placed(PickPlaceEnv, seed=4)
    zone = env.layout.zones[env.layout.target_zone].name
    assert env.prompt == f"put the {world.colors[target]} object in the {zone} zone"
    env, world, target = _placed(ConveyorEnv, seed=4)
    assert env.prompt == f"put the {world.colors[target]} object in the bin"


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_seed_same_episode(env_id):
    first, second = gymnasium.make(env_id, image_size=32), gymnasium.make(env_id, image_size=32)
    observations_a, _ = _rollout(first, seed=7)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(12, 3)).astype(np.float32)
    observations_b, _ = _rollout(second, seed=7)
    assert len(observations_a) == len(observations_b)
    for a, b in zip(observations_a, observations_b):  # the expert's random choices are seeded too
        assert np.array_equal(a["images"]["base_0_rgb"], b["images"]["base_0_rgb"])
        assert np.array_equal(a["state"], b["state"]) and a["prompt"] == b["prompt"]
    random_a, _ = _rollout(first, seed=8, actions=actions)
    random_b, _ = _rollout(second, seed=8, actions=actions)
    assert all(np.array_equal(a["images"]["base_0_rgb"], b["images"]["base_0_rgb"]) for a, b in zip(random_a, random_b))
    other, _ = _rollout(second, seed=9, actions=actions)
    assert not np.array_equal(random_a[0]["images"]["base_0_rgb"], other[0]["images"]["base_0_rgb"])


def test_sync_vector_env_batches_the_prompt_as_a_tuple():
    envs = gymnasium.vector.SyncVectorEnv([lambda: gymnasium.make("pi0_torch/PickPlace-v0", image_size=32)] * 3)
    observations, infos = envs.reset(seed=[0, 1, 2])
    assert observations["images"]["base_0_rgb"].shape == (3, 32, 32, 3) and observations["state"].shape == (3, 3)
    assert isinstance(observations["prompt"], tuple) and len(observations["prompt"]) == 3
    assert all(isinstance(prompt, str) for prompt in observations["prompt"])
    observations, _, _, _, infos = envs.step(np.zeros((3, 3), np.float32))
    images = {camera: frames[0] for camera, frames in observations["images"].items()}
    assert sorted(images) == ["base_0_rgb", "left_wrist_0_rgb"]
    assert infos["is_success"].shape == (3,) and envs.single_observation_space.contains(
        {"images": images, "state": observations["state"][0], "prompt": observations["prompt"][0]}
    )


def test_truncation_follows_the_step_limit_override():
    env = gymnasium.make("pi0_torch/Reach-v0", image_size=32, max_episode_steps=3)
    _, infos = _rollout(env, seed=0, actions=[np.zeros(3, np.float32)] * 10)
    assert len(infos) == 4  # reset + 3 steps


def test_bad_actions_are_refused():
    env, _, _ = _placed(ReachEnv)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0.0, np.nan, 0.0]))


def test_render_returns_a_larger_frame():
    env = ReachEnv(image_size=32, render_mode="rgb_array", render_size=128)
    observation, _ = env.reset(seed=0)
    assert env.render().shape == (128, 128, 3) and observation["images"]["base_0_rgb"].shape == (32, 32, 3)


def test_effector_speed_limit_table_clip_and_standing_still():
    world = World(["red"], np.array([[0.8, 0.8]]), effector=np.array([0.0, 0.0]))
    world.step(np.array([0.5, 0.0]), -1.0)
    assert np.allclose(world.effector, [MAX_SPEED, 0.0])
    for _ in range(30):
        world.step(np.array([5.0, -5.0]), -1.0)  # off the table: clipped to the corner
    assert np.allclose(world.effector, [1.0, -1.0])
    world.step(np.array([5.0, -5.0]), -1.0)  # holding the last action: standing still
    assert np.allclose(world.velocity, 0.0)


def test_grasp_radius_nearest_object_and_release():
    world = World(["red", "blue"], np.array([[GRASP_RADIUS - 0.01, 0.0], [-0.05, 0.0]]), effector=np.zeros(2))
    world.step(np.zeros(2), 1.0)
    assert world.held == 1 and world.gripper_closed  # both in reach: the nearest
    world.step(np.array([0.0, 0.03]), 1.0)
    assert np.allclose(world.positions[1], [-0.05, 0.03])  # carried
    world.step(np.array([0.0, 0.03]), -1.0)
    assert world.held == -1 and np.allclose(world.positions[1], [-0.05, 0.03])  # released where it is
    world = World(["red"], np.array([[GRASP_RADIUS + 0.01, 0.0]]), effector=np.zeros(2))
    world.step(np.zeros(2), 1.0)
    assert world.gripper_closed and world.held == -1  # closed on nothing
    world.step(np.array([0.1, 0.0]), 1.0)
    assert world.held == -1  # closing only grasps on the open -> closed transition


def test_slip_under_a_jump_but_not_under_smooth_motion():
    def carry(speeds, **kwargs):
        world = World(["red"], np.array([[0.0, 0.0]]), effector=np.zeros(2), **kwargs)
        world.step(np.zeros(2), 1.0)
        for speed in speeds:
            world.step(world.effector + np.array([speed, 0.0]), 1.0)
        return world

    smooth = carry([0.02, 0.04, 0.06, 0.08, 0.08, 0.06, 0.04, 0.02, 0.0])
    assert smooth.held == 0 and smooth.slipped == 0 and np.allclose(smooth.positions[0], smooth.effector)
    jerky = carry([0.02, 0.1])  # the target jumps: |v_t - v_t-1| = 0.08 > 0.06
    assert jerky.held == -1 and jerky.slipped == 1 and jerky.gripper_closed
    assert np.allclose(jerky.positions[0], [0.02, 0.0])  # dropped where it was
    assert carry([0.02, 0.1], slip_acceleration=0.1).slipped == 0
    assert carry([0.0, 0.1], slip_acceleration=float("inf")).slipped == 0


def test_reach_success():
    env, world, target = _placed(ReachEnv)
    goal = world.positions[target]
    world.effector = goal + np.array([GRASP_RADIUS + 0.02 + MAX_SPEED, 0.0])
    _, reward, terminated, _, info = env.step(np.array([*(goal + [GRASP_RADIUS + 0.02, 0.0]), -1.0], np.float32))
    assert not info["is_success"] and not terminated and reward == 0.0
    _, reward, terminated, _, info = env.step(np.array([*(goal + [GRASP_RADIUS - 0.01, 0.0]), -1.0], np.float32))
    assert info["is_success"] and terminated and reward == 1.0


def test_pick_place_success_needs_the_named_object_resting_in_the_named_zone():
    env, world, target = _placed(PickPlaceEnv, seed=2)
    zone, wrong = env.layout.zones[env.layout.target_zone], env.layout.zones[env.layout.target_zone - 1]
    world.effector = world.positions[target].copy()
    env.step(np.array([*world.effector, 1.0], np.float32))
    assert world.held == target
    world.effector, world.velocity = zone.center.copy(), np.zeros(2)  # teleport while held: still held
    world.positions[target] = zone.center.copy()
    _, _, terminated, _, info = env.step(np.array([*zone.center, 1.0], np.float32))
    assert info["stage"] == "carry" and not info["is_success"] and not terminated  # held: not placed yet
    _, _, terminated, _, info = env.step(np.array([*zone.center, -1.0], np.float32))
    assert info["is_success"] and terminated and info["stage"] == "done"
    env, world, target = _placed(PickPlaceEnv, seed=2)
    world.positions[target] = wrong.center.copy()
    other = (target + 1) % len(world.colors)
    world.positions[other] = zone.center.copy()
    _, _, _, _, info = env.step(np.array([*world.effector, -1.0], np.float32))
    assert not info["is_success"]  # the wrong zone, or the wrong object in the right zone


def test_conveyor_drift_fall_off_and_bin():
    env, world, target = _placed(ConveyorEnv, seed=5)
    start = world.positions.copy()
    env.step(np.array([*world.effector, -1.0], np.float32))
    assert np.allclose(world.positions - start, [[BELT_SPEED, 0.0]] * len(start))
    world.positions[target] = [1.0 - BELT_SPEED / 2, 0.0]
    _, reward, terminated, _, info = env.step(np.array([*world.effector, -1.0], np.float32))
    assert terminated and not info["is_success"] and info["stage"] == "fell_off" and reward == 0.0

    env, world, target = _placed(ConveyorEnv, seed=5)
    world.effector = world.positions[target].copy()
    env.step(np.array([*world.effector, 1.0], np.float32))
    held_at = world.positions[target].copy()
    env.step(np.array([*world.effector, 1.0], np.float32))
    assert np.allclose(world.positions[target], held_at)  # held objects do not drift
    world.effector = world.positions[target] = env.place_zone().center.copy()
    _, _, terminated, _, info = env.step(np.array([*world.effector, -1.0], np.float32))
    assert info["is_success"] and terminated


def test_renderer_draws_objects_zones_and_both_gripper_states():
    zone = Zone("blue", np.array([0.5, 0.5]), PALETTE["blue"])
    world = World(["red"], np.array([[-0.5, -0.5]]), effector=np.array([0.5, -0.5]), zones=(zone,))
    renderer = Renderer(64)
    image = renderer.draw(world)
    assert tuple(image[16, 16]) == PALETTE["red"]  # object centre (-0.5, -0.5) -> pixel (16, 16)
    assert tuple(image[48, 48]) != PALETTE["blue"] and tuple(image[48, 41]) == PALETTE["blue"]  # tinted fill, border
    assert tuple(image[15, 48]) != (255, 255, 255)  # the open gripper is a ring
    world.step(world.effector, 1.0)
    assert tuple(renderer.draw(world)[15, 48]) == (255, 255, 255)  # closed: filled


def test_wrist_view_follows_the_effector_magnified_and_shows_the_table_edge():
    world = World(["red"], np.array([[0.2, 0.0]]), effector=np.array([0.0, 0.0]))
    wrist = Renderer(64, wrist_zoom=2.0)  # 64 pixels see a square of side 1 around the effector
    image = wrist.draw(world)
    # the effector sits between pixels 31 and 32; its open ring spans 2.9 to 5.1 pixels from there, on every side
    assert [tuple(image[32, column]) for column in (28, 31, 36)] == [(255, 255, 255), TABLE_COLOR, (255, 255, 255)]
    assert tuple(image[28, 32]) == (255, 255, 255) and tuple(image[36, 32]) == (255, 255, 255)
    # the object 0.2 to the right: its centre 12.8 pixels right of the effector's, its radius 0.1 = 6.4 pixels
    red = [column for column in range(64) if tuple(image[32, column]) == PALETTE["red"]]
    assert (red[0], red[-1]) == (38, 50)
    world.effector = np.array([0.9, -0.9])  # near the top-right corner: beyond the table is black
    corner = wrist.draw(world)
    assert tuple(corner[0, 63]) == OFF_TABLE_COLOR and tuple(corner[63, 0]) == TABLE_COLOR
    with pytest.raises(ValueError, match="wrist_zoom must be >= 1"):
        Renderer(64, wrist_zoom=0.5)


def test_wrist_camera_is_optional():
    env = gymnasium.make("pi0_torch/Reach-v0", image_size=32, wrist_camera=False)
    observation, _ = env.reset(seed=0)
    assert list(observation["images"]) == ["base_0_rgb"] and list(env.observation_space["images"]) == ["base_0_rgb"]
    assert list(gymnasium.make("pi0_torch/Reach-v0", image_size=32).reset(seed=0)[0]["images"]) == [
        "base_0_rgb", "left_wrist_0_rgb"]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_expert_succeeds_on_99_percent_of_100_seeds_without_slipping(env_id):
    env = gymnasium.make(env_id, image_size=16)
    results = [_rollout(env, seed)[1][-1] for seed in range(1000, 1100)]
    assert sum(info["is_success"] for info in results) >= 99
    assert sum(info["slipped"] for info in results) == 0


def test_expert_paths_are_multimodal():
    env = gymnasium.make("pi0_torch/Reach-v0", image_size=16)
    expert = make_expert(env)
    middles = []
    for expert_seed in range(8):  # one scene, different expert seeds: paths bend either way
        env.reset(seed=0)
        expert.reset(expert_seed)
        for _ in range(5):
            env.step(expert.act(env))
        middles.append(env.unwrapped.world.effector.copy())
    start, goal = env.unwrapped.layout.effector, env.unwrapped.world.positions[env.unwrapped.layout.target_object]
    chord = goal - start
    sides = {np.sign(chord[0] * (m - start)[1] - chord[1] * (m - start)[0]) for m in middles}
    assert sides == {-1.0, 1.0}


def test_fewer_objects_make_easier_scenes_the_expert_still_solves() -> None:
    for count in (1, 2):
        env = gymnasium.make("pi0_torch/PickPlace-v0", num_objects=count)
        observation, _ = env.reset(seed=4)
        assert len(env.unwrapped.world.positions) == count
        expert = make_expert(env)
        expert.reset(4)
        done, info = False, {}
        while not done:
            observation, _, terminated, truncated, info = env.step(expert.act(env))
            done = terminated or truncated
        assert info["is_success"]
    with pytest.raises(ValueError, match=r"num_objects must lie in \[1, 3\], got 4"):
        gymnasium.make("pi0_torch/Reach-v0", num_objects=4)
