"""Closed loop: chunk schedules and stitching, the real-time executor, `evaluate` / `pi0-torch eval` with local,
remote and scripted policies, real-time chunking requests through `PI0Policy` and the server, third-party envs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image
import pytest
import torch

from conftest import HANG_S, HORIZON, tiny_policy
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.chunking import ChunkSchedule, ChunkStitcher, RealTimeExecutor, continuation_fields
from pi0_torch.runtime.rollout import (
    EpisodeResult,
    EvalResult,
    EvalSettings,
    LocalPolicy,
    RemotePolicy,
    ScriptedPolicy,
    _per_task,
    evaluate,
    wilson_interval,
)
from pi0_torch.runtime.serving import PolicyServer

REPO = Path(__file__).resolve().parents[1]
# -- schedules and stitching ---------------------------------------------------------------------------------------------


def test_sync_waits_and_asynchronous_modes_keep_going() -> None:
    sync = ChunkSchedule("sync", horizon=8, replan_steps=4, inference_delay=2)
    assert [t for t in range(14) if sync.observes(t)] == [0, 6, 12] and sync.anchor(6) == 8 == sync.arrival(6)
    stitcher, hold = ChunkStitcher("sync", replan_steps=4), np.full(1, -1.0)
    stitcher.add(np.arange(8.0)[:, None], anchor=2)
    executed = [float(stitcher.action(t, hold)[0]) for t in range(2, 8)]
    stitcher.add(10 + np.arange(8.0)[:, None], anchor=8)
    executed += [float(stitcher.action(t, hold)[0]) for t in range(8, 13)]
    assert executed == [0.0, 1.0, 2.0, 3.0, -1.0, -1.0, 10.0, 11.0, 12.0, 13.0, -1.0]  # s = 4 actions, then it waits
    assert float(ChunkStitcher("sync", 4).action(0, hold)[0]) == -1.0  # nothing arrived: stand still

    ensemble = ChunkStitcher("ensemble", replan_steps=4)
    ensemble.add(np.zeros((8, 1)), anchor=0)
    ensemble.add(np.ones((8, 1)), anchor=4)
    weights = np.exp(-0.01 * np.arange(2))
    assert float(ensemble.action(3, hold)[0]) == 0.0
    assert float(ensemble.action(5, hold)[0]) == pytest.approx(weights[1] / weights.sum())  # the older chunk weighs more
    assert float(ensemble.action(9, hold)[0]) == 1.0

    naive = ChunkStitcher("rtc", replan_steps=4)
    assert continuation_fields("rtc", naive, 0, 2) == {}  # nothing to continue yet
    naive.add(np.arange(8.0)[:, None], anchor=2)
    fields = continuation_fields("rtc", naive, 6, 2)
    assert (fields["execution_horizon"], fields["inference_delay"], fields["rtc_method"]) == (4, 2, "guidance")
    assert continuation_fields("rtc-trained", naive, 9, 5)["inference_delay"] == 1  # what the chunk has left
    assert continuation_fields("naive", naive, 6, 2) == {}
    with pytest.raises(ValueError, match=r"replan_steps \+ inference_delay \(6 \+ 4\) must not exceed"):
        ChunkSchedule("naive", horizon=8, replan_steps=6, inference_delay=4)


@pytest.mark.parametrize("mode", ["sync", "naive", "rtc"])
def test_real_time_executor_continues_where_the_robot_is(mode: str) -> None:
    """A policy that knows the future (chunk value = the step it is meant for) run by the real-time executor with
    ~30 ms of latency at 100 Hz: every step executes its own value, or holds the previous one when a chunk came later
    than the executing one lasts; the delay estimate follows the latency."""
    requests = []

    def infer(observation: dict) -> dict:
        requests.append(observation)
        time.sleep(0.03)
        return {"actions": (observation["step"] + np.arange(HORIZON, dtype=np.float32))[:, None]}

    executor = RealTimeExecutor(infer, mode, horizon=HORIZON, replan_steps=3, control_hz=100, hold=np.zeros(1))
    executed = []
    for step in range(40):
        executed.append(float(executor.step({"step": step})[0]))
        time.sleep(0.01)
    if mode == "sync":  # the robot waits for every chunk: no step is skipped or held
        assert executed == [float(t) for t in range(40)]
    else:
        assert all(value == t or value == executed[t - 1] for t, value in enumerate(executed))
        assert sum(value == t for t, value in enumerate(executed)) >= 30
        assert 3 <= executor.estimated_delay <= HORIZON - 3  # ceil(30 ms * 100 Hz), plus scheduling
    if mode == "rtc":
        continued = [r for r in requests if "previous_actions" in r]
        assert continued and all(r["rtc_method"] == "guidance" and r["execution_horizon"] >= 3 for r in continued)  # later when a chunk came late


def test_wilson_interval() -> None:
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == pytest.approx(1.0)
    low, high = wilson_interval(80, 100)
    assert low == pytest.approx(0.7112, abs=1e-4) and high == pytest.approx(0.8666, abs=1e-4)


def test_success_per_task_of_a_suite() -> None:
    """Episodes that name their task (benchmark suites) are summarized per task too, with their own intervals."""
    episodes = [EpisodeResult(seed, success, 10, [], [], task) for seed, (task, success) in
                enumerate([("open", True), ("press", False), ("open", True), ("press", True), ("open", False)])]
    per_task = _per_task(episodes)
    assert list(per_task) == ["open", "press"]  # in order of first appearance
    assert per_task["open"] == {"episodes": 3, "success_rate": 2 / 3, "success_ci95": wilson_interval(2, 3)}
    result = EvalResult(env="suite", episodes=5, seed=0, execution="sync", inference_delay=0, replan_steps=5,
                        success_rate=0.6, success_ci95=wilson_interval(3, 5), mean_steps=10.0, latency_ms=1.0,
                        boundary_jerk=None, interior_jerk=None, policy={}, episodes_detail=[], per_task=per_task)
    assert result.task_lines() == ["  open: success 66.7% [20.8, 93.9] over 3 episodes",
                                   "  press: success 50.0% [9.5, 90.5] over 2 episodes"]
    assert _per_task([EpisodeResult(0, True, 3, [], [])]) == {}  # (envs without tasks: nothing per task)


# -- closed loop in the tabletop envs --------------------------------------------------------------------------------------


def test_scripted_expert_and_random_through_the_harness(tmp_path: Path) -> None:
    expert = evaluate(ScriptedPolicy("expert"), EvalSettings(env="pi0_torch/PickPlace-v0", episodes=6, num_envs=3,
                                                              output_dir=str(tmp_path / "expert")))
    random = evaluate(ScriptedPolicy("random"), EvalSettings(env="pi0_torch/PickPlace-v0", episodes=6, num_envs=3))
    assert expert.success_rate == 1.0 and random.success_rate == 0.0
    saved = json.loads((tmp_path / "expert" / "eval.json").read_text())
    for key in ("env", "episodes", "seed", "success_rate", "success_ci95", "mean_steps", "latency_ms", "execution",
                "inference_delay", "boundary_jerk"):
        assert key in saved
    assert [e["seed"] for e in saved["episodes_detail"]] == list(range(1_000_000, 1_000_006))
    with Image.open(tmp_path / "expert" / "success.png") as chart:  # (issue 63: the success chart beside eval.json)
        assert chart.format == "PNG" and chart.size[0] == 900


def test_episodes_do_not_depend_on_batching_or_on_the_wire() -> None:
    """Per-chunk noise seeds: one env at a time, three in lockstep, and through `pi0-torch serve`'s server give the
    same episodes (real-time chunking requests included)."""
    policy = tiny_policy()
    settings = dict(env="pi0_torch/Conveyor-v0", episodes=3, max_steps=14, execution="rtc", inference_delay=2,
                    replan_steps=4)
    one = evaluate(LocalPolicy(policy), EvalSettings(num_envs=1, **settings))
    three = evaluate(LocalPolicy(policy), EvalSettings(num_envs=3, **settings))
    with PolicyServer(policy, port=0, max_batch_size=3).serve_in_thread() as port:
        remote = RemotePolicy(f"ws://127.0.0.1:{port}", connections=3)
        try:
            served = evaluate(remote, EvalSettings(num_envs=3, **settings))
        finally:
            remote.close()
    for other in (three, served):
        assert [e["steps"] for e in other.episodes_detail] == [e["steps"] for e in one.episodes_detail]
        assert other.boundary_jerk == pytest.approx(one.boundary_jerk, rel=1e-4)
        assert other.interior_jerk == pytest.approx(one.interior_jerk, rel=1e-4)


@pytest.mark.parametrize("mode", ["sync", "naive", "ensemble", "rtc", "rtc-trained"])
def test_every_execution_mode_runs_under_delay(mode: str) -> None:
    result = evaluate(LocalPolicy(tiny_policy()), EvalSettings(env="pi0_torch/Reach-v0", episodes=2, num_envs=2,
                                                               max_steps=12, execution=mode, inference_delay=3))
    assert result.execution == mode and result.inference_delay == 3 and result.boundary_jerk is not None
    assert result.replan_steps == (HORIZON if mode == "sync" else HORIZON - 3)


def test_a_chunk_arriving_at_the_next_observation_is_the_one_continued() -> None:
    """d = s: each chunk arrives exactly when the next inference starts, which must continue it (s steps executed),
    not the chunk before it."""
    result = evaluate(LocalPolicy(tiny_policy()), EvalSettings(env="pi0_torch/Conveyor-v0", episodes=2, num_envs=2,
                                                               max_steps=20, execution="rtc", inference_delay=4,
                                                               replan_steps=4))
    assert result.episodes == 2 and result.boundary_jerk is not None


def test_policy_continues_a_chunk_in_robot_units() -> None:
    """`rtc_method="conditioning"` through `PI0Policy.infer`: the committed steps come back as the previous chunk's
    actions (robot units -> model space -> robot units), the rest is sampled; bad fields are named."""
    policy = tiny_policy(low=-2.0, high=6.0)
    observation = {"images": {"base_0_rgb": np.zeros((32, 32, 3), np.uint8)}, "state": np.ones(3), "prompt": "reach"}
    previous = np.linspace(-2, 6, HORIZON * 3, dtype=np.float32).reshape(HORIZON, 3)
    out = policy.infer({**observation, "previous_actions": previous, "execution_horizon": 2, "inference_delay": 3,
                        "rtc_method": "conditioning", "noise_seed": 5})["actions"]
    np.testing.assert_allclose(out[:3], previous[2:5], rtol=1e-5, atol=1e-5)
    assert not np.allclose(out[3:6], previous[5:8])
    with pytest.raises(ValueError, match=r"inference_delay must be an integer in \[0, 6\], got 7"):
        policy.prepare({**observation, "previous_actions": previous, "execution_horizon": 2, "inference_delay": 7})
    with pytest.raises(ValueError, match=r"inference_delay: 4 exceeds the 3 steps this model was trained"):
        policy.prepare({**observation, "previous_actions": previous, "execution_horizon": 2, "inference_delay": 4,
                        "rtc_method": "conditioning"})
    with pytest.raises(ValueError, match=r"previous_actions: expected shape \[8, 3\]"):
        policy.prepare({**observation, "previous_actions": previous[:4], "execution_horizon": 2})
    with pytest.raises(ValueError, match="given without previous_actions"):
        policy.prepare({**observation, "inference_delay": 2})


def test_noise_scale_scales_the_noise_the_flow_starts_from() -> None:
    """`noise_scale` 1 samples exactly as the model's own sampler did; s multiplies the (seeded) noise; 0 gives one
    chunk per observation whatever the seed; a bad value is refused with its name."""
    policy = tiny_policy()
    observation = {"images": {"base_0_rgb": np.zeros((32, 32, 3), np.uint8)}, "state": np.ones(3), "prompt": "reach"}
    batch = policy.prepare(observation).inputs
    model, shape = policy.model, (1, HORIZON, 4)
    with torch.no_grad():
        plain = model.generate_actions(**batch, num_steps=2, generator=torch.Generator().manual_seed(0))
        np.testing.assert_array_equal(policy.model_actions(batch), plain.numpy())  # (policy seeded with 0)
        policy.noise_scale = 0.5
        scaled = model.generate_actions(**batch, num_steps=2, noise=0.5 * torch.randn(shape, generator=torch.Generator().manual_seed(7)))
        np.testing.assert_array_equal(policy._generate([policy.prepare({**observation, "noise_seed": 7})], None), scaled.numpy())
    policy.noise_scale = 0.0
    first, second = (policy.infer({**observation, "noise_seed": seed})["actions"] for seed in (1, 2))
    np.testing.assert_array_equal(first, second)
    assert policy.metadata["noise_scale"] == 0.0
    with pytest.raises(ValueError, match=r"noise_scale must be a finite number >= 0 and <= 10, got -1.0"):
        PI0Policy(policy.model, policy.processor, noise_scale=-1.0)


def test_policy_guides_with_its_rtc_schedule(monkeypatch: pytest.MonkeyPatch) -> None:
    """`rtc_schedule` reaches the model's guidance (and changes the chunk); the metadata says which; bad names fail."""
    policy = tiny_policy(rtc_max_delay=0)
    observation = {"images": {"base_0_rgb": np.zeros((32, 32, 3), np.uint8)}, "state": np.ones(3), "prompt": "reach",
                   "previous_actions": np.linspace(-1, 1, HORIZON * 3, dtype=np.float32).reshape(HORIZON, 3),
                   "execution_horizon": 2, "inference_delay": 2, "noise_seed": 3}
    seen, generate = [], policy.model.generate_actions
    monkeypatch.setattr(policy.model, "generate_actions", lambda **kw: seen.append(kw["rtc_schedule"]) or generate(**kw))
    chunks = {}
    for schedule in ("exp", "ones"):
        policy.rtc_schedule = schedule
        chunks[schedule] = policy.infer(observation)["actions"]
    assert seen == ["exp", "ones"] and not np.allclose(chunks["exp"], chunks["ones"])
    assert policy.metadata["real_time_chunking"]["guidance_schedule"] == "ones"
    with pytest.raises(ValueError, match=r"rtc_schedule must be one of \('exp', 'linear', 'ones', 'hard'\), got 'flat'"):
        PI0Policy(policy.model, policy.processor, rtc_schedule="flat")


def test_mismatches_are_named() -> None:
    with pytest.raises(ValueError, match=r"action dims differ: the policy acts in 2 dims, the env .* takes 3"):
        evaluate(LocalPolicy(tiny_policy(action_dim=2)), EvalSettings(env="pi0_torch/Reach-v0", episodes=1))
    top_camera_only = LocalPolicy(tiny_policy(cameras=("base_0_rgb",)))
    with pytest.raises(ValueError, match=r"cameras differ: the env pi0_torch/Reach-v0 gives \['base_0_rgb', 'left_wrist_0_rgb'\], the policy "
                                         r"knows \['base_0_rgb'\] \(map them with --obs-format, or drop the wrist camera "
                                         r"with --env-kwargs '\{\"wrist_camera\": false\}'\)"):
        evaluate(top_camera_only, EvalSettings(env="pi0_torch/Reach-v0", episodes=1))
    assert evaluate(top_camera_only, EvalSettings(env="pi0_torch/Reach-v0", episodes=1, max_steps=2,
                                                  env_kwargs={"wrist_camera": False})).episodes == 1
    with pytest.raises(ValueError, match=r"unknown environment id 'pi0_torch/Nope-v0'; known: pi0_torch/Conveyor-v0"):
        evaluate(ScriptedPolicy("expert"), EvalSettings(env="pi0_torch/Nope-v0", episodes=1))
    with pytest.raises(ValueError, match=r"^the environment no_such_sim/Env-v0 needs the package no_such_sim, which is "
                                         r"not installed: pip install no-such-sim$"):
        evaluate(ScriptedPolicy("expert"), EvalSettings(env="no_such_sim/Env-v0", episodes=1))
    with pytest.raises(ValueError, match=r"rtc-trained needs a policy trained with --rtc-max-delay >= 5"):
        evaluate(LocalPolicy(tiny_policy()), EvalSettings(env="pi0_torch/Reach-v0", episodes=1,
                                                           execution="rtc-trained", inference_delay=5, replan_steps=2))


# -- the command, on a third-party simulator ---------------------------------------------------------------------------------


def test_eval_command_on_gym_pusht(tmp_path: Path) -> None:
    """`pi0-torch eval` end to end on LeRobot's PushT simulator (pygame rendering off-screen): a few steps, video,
    PNG strip and eval.json; an id whose package is not installed is one line naming it."""
    pytest.importorskip("gym_pusht")
    policy = tiny_policy(action_dim=2, low=0.0, high=512.0)
    policy.model.save_pretrained(tmp_path / "policy")
    policy.processor.save_pretrained(tmp_path / "policy")
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "pi0_torch.cli", "eval", "--policy", str(tmp_path / "policy"),
               "--env", "gym_pusht/PushT-v0", "--episodes", "2", "--num-envs", "2", "--max-steps", "10",
               "--prompt", "push the T onto the target", "--output-dir", str(tmp_path / "out"), "--video",
               "--noise-scale", "0.5"]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=HANG_S, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "gym_pusht/PushT-v0 sync d=0 s=8: success" in done.stdout
    result = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert result["episodes"] == 2 and all(e["steps"] == 10 for e in result["episodes_detail"])
    assert result["policy"]["noise_scale"] == 0.5
    assert (tmp_path / "out" / "rollout_1000000.mp4").stat().st_size > 0
    assert (tmp_path / "out" / "rollout_1000000.png").stat().st_size > 0
    bad = subprocess.run([*command[:6], "--env", "gym_nothing/Nope-v0"], capture_output=True, text=True, env=env,
                         timeout=HANG_S, check=False)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0
    assert "needs the package gym_nothing, which is not installed: pip install gym-nothing" in bad.stderr


def test_perturb_shifts_non_wrist_cameras_and_jitters_every_camera_per_episode() -> None:
    """Issue 60, targets: `eval --perturb` sees held-out episodes through a camera shifted by a few pixels and other
    light. Per episode, from its seed: the same seed the same perturbation, another seed another; wrist cameras are
    not shifted; channels-first frames (ALOHA's) alike; no perturbation at 0, 0."""
    from pi0_torch.runtime.perturbation import Perturbation, parse_perturbation

    ramp = np.broadcast_to(np.arange(16, dtype=np.uint8)[:, None, None] * 10, (16, 16, 3)).copy()  # row r: 10 r
    frames = {"base_0_rgb": ramp, "left_wrist_0_rgb": ramp, "cam_high": np.moveaxis(ramp, -1, 0).copy()}
    shifted = Perturbation(shift=3, jitter=0.0).for_episode(1)
    once, again = shifted(frames), shifted(frames)
    assert all(np.array_equal(once[c], again[c]) for c in frames)  # (the episode keeps its draw)
    np.testing.assert_array_equal(once["left_wrist_0_rgb"], ramp)  # (wrist cameras: not shifted)
    dy = 8 - int(once["base_0_rgb"][8, 0, 0]) // 10  # (content moved down by dy: row r shows row r - dy)
    expected = (np.clip(np.arange(16) - dy, 0, 15) * 10).astype(np.uint8)[:, None].repeat(16, 1)
    assert -3 <= dy <= 3 and np.array_equal(once["base_0_rgb"][:, :, 0], expected)  # (edges repeated)
    assert once["cam_high"].shape == (3, 16, 16)
    draws = {tuple(Perturbation(3, 0.2).for_episode(seed)(frames)["base_0_rgb"].ravel()[:64]) for seed in range(8)}
    assert len(draws) > 1  # (other seeds, other perturbations)
    identity = Perturbation(0, 0.0).for_episode(5)(frames)
    assert all(np.array_equal(identity[c], frames[c]) for c in frames)
    assert parse_perturbation("4,0.2") == Perturbation(4, 0.2) and parse_perturbation("2") == Perturbation(2, 0.2)
    with pytest.raises(ValueError, match=r"--perturb: SHIFT must be in \[0, 64\]"):
        parse_perturbation("100")
