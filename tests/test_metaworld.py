"""Meta-World behind `pi0-torch eval` / `demos` (`pi0_torch.envs.metaworld`): the observation layout, seeds that fix a
scene, the scripted expert, a dataset of its demonstrations, and evaluation with the benchmark's own settings; and
the headless rendering choice (`pi0_torch.envs.rendering`). Skipped where MuJoCo cannot render offscreen."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

if importlib.util.find_spec("metaworld") is None:
    pytest.skip("metaworld is not installed (the [envs] extra)", allow_module_level=True)
from pi0_torch.envs import rendering  # noqa: E402

try:  # (before metaworld is imported: it imports MuJoCo, which fails to import where its GL library is missing)
    rendering.check_mujoco_rendering()
except rendering.RenderingError as error:
    pytest.skip(f"MuJoCo cannot render here: {error}", allow_module_level=True)

from pi0_torch.envs.demos import record_demos  # noqa: E402
from pi0_torch.envs.metaworld import TASKS, make_env, task_prompt  # noqa: E402
from pi0_torch.runtime.rollout import EvalSettings, ScriptedPolicy, evaluate, make_env as make_any_env  # noqa: E402

TASK = "button-press-topdown-v3"  # (its expert needs about 65 steps)


def test_observations_are_the_default_layout_and_a_seed_fixes_the_scene() -> None:
    env = make_env(TASK, image_size=32, max_episode_steps=5)
    first, _ = env.reset(seed=7)
    assert sorted(first) == ["images", "prompt", "state"] and first["prompt"] == task_prompt(TASK)
    frame = first["images"]["base_0_rgb"]
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8 and frame.std() > 0
    assert first["state"].shape == (4,) and first["state"].dtype == np.float32
    again, _ = env.reset(seed=7)
    other, _ = env.reset(seed=8)
    np.testing.assert_array_equal(again["images"]["base_0_rgb"], frame)  # the same seed: the same scene
    assert not np.array_equal(other["images"]["base_0_rgb"], frame)  # another seed: the button elsewhere
    steps = 0
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(env.unwrapped.hold_action())
        steps, done = steps + 1, terminated or truncated
    assert (steps, terminated, info["is_success"]) == (5, False, False)  # standing still ends at the step limit
    env.close()


def test_bad_settings_and_actions_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="unknown Meta-World task 'reach-v2'.*reach-v3"):
        make_env("reach-v2")
    with pytest.raises(ValueError, match="image_size"):
        make_env(TASK, image_size=4)
    env = make_env(TASK, image_size=16)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0]))
    env.close()
    assert "reach-v3" in TASKS and task_prompt("door-lock-v3") == "door lock"


def test_the_expert_through_eval_with_per_task_results(tmp_path: Path) -> None:
    settings = EvalSettings(env=f"metaworld/{TASK}", episodes=2, num_envs=2, seed=1_000_000,
                            env_kwargs={"image_size": 16, "max_episode_steps": 150}, output_dir=str(tmp_path / "eval"))
    result = evaluate(ScriptedPolicy("expert"), settings)
    assert result.success_rate == 1.0 and result.per_task == {
        TASK: {"episodes": 2, "success_rate": 1.0, "success_ci95": result.success_ci95}}
    written = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert [e["task"] for e in written["episodes_detail"]] == [TASK, TASK]
    assert result.task_lines() == []  # (one task: the summary line says it all)


def test_random_actions_fail_and_the_env_id_goes_through_eval_s_make_env() -> None:
    env = make_any_env(f"metaworld/{TASK}", image_size=16, max_episode_steps=30)
    assert env.unwrapped.task_name == TASK and env.unwrapped.replan_steps is None
    env.close()
    settings = EvalSettings(env=f"metaworld/{TASK}", episodes=2, num_envs=1, env_kwargs={"image_size": 16, "max_episode_steps": 30})
    assert evaluate(ScriptedPolicy("random"), settings).success_rate == 0.0


def test_demos_of_a_metaworld_task_are_a_lerobot_dataset(tmp_path: Path) -> None:
    from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset

    summary = record_demos(f"metaworld/{TASK}", 2, tmp_path / "demos", image_size=16, storage="image",
                           env_kwargs={"max_episode_steps": 150})
    assert (summary.episodes, summary.failed_seeds) == (2, [])
    info = json.loads((tmp_path / "demos" / "meta" / "info.json").read_text())
    assert info["robot_type"] == "sawyer" and info["features"]["action"]["names"] == ["dx", "dy", "dz", "gripper_effort"]
    sample = LeRobotEpisodeDataset(tmp_path / "demos", action_horizon=8)[0]
    assert sample["state"].shape == (4,) and sample["actions"].shape == (8, 4) and sample["prompt"] == task_prompt(TASK)
    assert sample["images"]["observation.images.base_0_rgb"].shape == (16, 16, 3)


def test_the_backend_is_the_users_or_egl_with_an_nvidia_driver_else_osmesa(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delitem(__import__("sys").modules, "mujoco")  # as if MuJoCo were not loaded yet (restored after)
    for user, nvidia, expected in [(None, True, "egl"), (None, False, "osmesa"), ("glfw", True, "glfw")]:
        if user is None:
            monkeypatch.delenv("MUJOCO_GL", raising=False)
        else:
            monkeypatch.setenv("MUJOCO_GL", user)
        monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
        monkeypatch.setattr(rendering, "nvidia_driver_loaded", lambda nvidia=nvidia: nvidia)
        assert rendering.configure_mujoco_gl() == expected
        assert __import__("os").environ["MUJOCO_GL"] == expected
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    with pytest.raises(rendering.RenderingError, match="MUJOCO_GL='vulkan' is not a MuJoCo backend; expected one of egl, osmesa, glfw"):
        rendering.configure_mujoco_gl()


def test_the_scripted_expert_acts_without_warnings_and_errors_name_the_env_id(recwarn: pytest.WarningsRecorder) -> None:
    """Issue 63, first hour 7: the expert leaked Meta-World's `UserWarning: Constant(s) may be too high` (it clips the
    action anyway), and a dims mismatch named `<MetaWorldEnv instance>` instead of the env id."""
    from pi0_torch.runtime.rollout import _check_match

    env = make_env(TASK, image_size=32, max_episode_steps=70)
    expert = env.unwrapped.scripted_expert()
    observation, _ = env.reset(seed=0)
    for _ in range(70):  # (its raw policy warns about 70 times on this task)
        observation, _, terminated, truncated, _ = env.step(expert.act(env))
        if terminated or truncated:
            break
    assert not [str(w.message) for w in recwarn if "Constant" in str(w.message)]
    policy = ScriptedPolicy("random")
    policy.metadata = {**policy.metadata, "action_dim": 7}
    with pytest.raises(ValueError, match=rf"the env metaworld/{TASK} takes 4"):
        _check_match(policy, env, observation, f"metaworld/{TASK}")
    env.close()
