"""The LIBERO suites as openpi's `examples/libero/main.py` runs them: `pi0-torch eval --env libero/<suite>`.

Suites: `libero_spatial`, `libero_object`, `libero_goal`, `libero_10` (10 tasks each) and `libero_90` (90 tasks),
from the `hf-libero` package (`pip install 'pi0-torch[libero]'`). One env runs a whole suite; the episode seed picks
the task and its initial state:

    task = seed % n_tasks,   initial state = (seed // n_tasks) % n_init_states   (LIBERO stores 50 per task)

so `--episodes 500 --seed 0` on a 10-task suite is openpi's evaluation: every task, with each of its 50 initial
states once (`--episodes 4500` for libero_90). Each episode, as openpi's client does it:

1. the task's `OffScreenRenderEnv` (bddl file, 256x256 cameras), `reset()`, `set_init_state(initial state)`;
2. 10 steps of the dummy action `[0, 0, 0, 0, 0, 0, -1]` while the objects settle (done inside `reset`, not counted);
3. at most the suite's step limit of policy steps (openpi's table: spatial 220, object 280, goal 300, libero_10 520,
   libero_90 400; `max_episode_steps` replaces it); the episode succeeds, and ends, when LIBERO's `done` is set.

An observation is the message openpi's client sends ([`libero_observation`]):

| key | value |
|---|---|
| `observation/image` | `agentview_image` rotated 180 degrees (`[::-1, ::-1]`, as the training data), `resize_with_pad` to 224x224 uint8 |
| `observation/wrist_image` | `robot0_eye_in_hand_image`, the same |
| `observation/state` | 8 values: `robot0_eef_pos` (3), the axis-angle of `robot0_eef_quat` (3, openpi's `_quat2axisangle`), `robot0_gripper_qpos` (2) |
| `prompt` | the task's language instruction |

The unwrapped env carries openpi's protocol: `replan_steps` 5, `hold_action` the dummy action, `control_hz` 20
(LIBERO's control frequency), `task_name` (the task's name, unique in its suite). numpy's global random state, which
LIBERO's `env.seed` sets and robosuite's reset draws from, is seeded with the episode seed at each reset (openpi
seeds it with 7 once per task). LIBERO's scene assets are fetched from the Hugging Face Hub on first use; without
them `make_env` stops with one line saying so.

```python
>>> import numpy as np
>>> raw = {"agentview_image": np.zeros((256, 256, 3), np.uint8), "robot0_eye_in_hand_image": np.zeros((256, 256, 3), np.uint8),
...        "robot0_eef_pos": np.zeros(3), "robot0_eef_quat": np.array([0.0, 0.0, 0.0, 1.0]), "robot0_gripper_qpos": np.zeros(2)}
>>> message = libero_observation(raw, "put the bowl on the plate")
>>> sorted(message), message["observation/image"].shape, message["observation/state"].shape
(['observation/image', 'observation/state', 'observation/wrist_image', 'prompt'], (224, 224, 3), (8,))

```
"""

from __future__ import annotations

import importlib.util
import os
import string
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import gymnasium
import numpy as np

from pi0_torch.envs.rendering import configure_mujoco_gl
from pi0_torch.processing.images import resize_with_pad

SUITE_MAX_STEPS = {  # openpi examples/libero/main.py (the longest training demo of each suite, plus a margin)
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
CAMERA_RESOLUTION = 256  # LIBERO_ENV_RESOLUTION: the resolution the training data was rendered at
IMAGE_SIZE = 224  # the client's resize_with_pad target
WAIT_STEPS = 10  # num_steps_wait: dummy steps while the dropped objects settle
DUMMY_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)  # LIBERO_DUMMY_ACTION: no motion, gripper open
REPLAN_STEPS = 5
CONTROL_HZ = 20  # LIBERO's control_freq
ACTION_DIM = 7
STATE_DIM = 8
FRAME_KEYS = ("agentview_image", "robot0_eye_in_hand_image")
VECTOR_SIZES = {"robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}
ASSET_FOLDERS = ("articulated_objects", "stable_scanned_objects", "turbosquid_objects", "stable_hope_objects")


def quat_to_axis_angle(quat: Any) -> np.ndarray:
    """An `(x, y, z, w)` quaternion -> axis-angle (3,), as openpi's `_quat2axisangle` (robosuite's `quat2axisangle`):
    `w` clipped to [-1, 1], the angle `2 acos(w)` (in [0, 2 pi]: not folded to at most pi), zeros for `w = ±1`."""
    quat = np.asarray(quat, np.float64)
    w = min(max(float(quat[3]), -1.0), 1.0)
    sin_half = np.sqrt(1.0 - w * w)
    if sin_half == 0.0:  # (openpi's math.isclose(den, 0.0) is true only at exactly 0)
        return np.zeros(3)
    return quat[:3] * 2.0 * np.arccos(w) / sin_half


def libero_observation(raw: Mapping[str, Any], prompt: str) -> dict[str, Any]:
    """A LIBERO observation (robosuite's dict) -> the message openpi's LIBERO client sends (see the module)."""
    frames = {}
    for key in FRAME_KEYS:
        if key not in raw:
            raise ValueError(f"LIBERO observation: missing {key!r}")
        frame = np.asarray(raw[key])
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[-1] != 3:
            raise ValueError(f"LIBERO observation {key}: expected an [H, W, 3] uint8 frame, got shape {frame.shape} "
                             f"dtype {frame.dtype}")
        upright = np.ascontiguousarray(frame[::-1, ::-1])  # rotated 180 degrees, as the training data
        frames[key] = resize_with_pad(upright, IMAGE_SIZE, IMAGE_SIZE)  # [224, 224, 3] uint8
    vectors = {}
    for key, size in VECTOR_SIZES.items():
        if key not in raw:
            raise ValueError(f"LIBERO observation: missing {key!r}")
        vectors[key] = np.asarray(raw[key], np.float64)
        if vectors[key].shape != (size,):
            raise ValueError(f"LIBERO observation {key}: expected {size} values, got shape {vectors[key].shape}")
    state = np.concatenate([vectors["robot0_eef_pos"], quat_to_axis_angle(vectors["robot0_eef_quat"]),
                            vectors["robot0_gripper_qpos"]])  # [8]
    return {
        "observation/image": frames["agentview_image"],
        "observation/wrist_image": frames["robot0_eye_in_hand_image"],
        "observation/state": state,
        "prompt": str(prompt),
    }


class LiberoSuiteEnv(gymnasium.Env):
    """A LIBERO suite, one task and initial state per episode seed (see the module docstring)."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    replan_steps = REPLAN_STEPS
    control_hz = CONTROL_HZ

    def __init__(self, suite_name: str, suite: Any, max_episode_steps: int, env_kwargs: Mapping[str, Any]) -> None:
        self.suite_name = suite_name
        self.suite = suite  # libero.libero.benchmark's suite object
        self.max_episode_steps = int(max_episode_steps)
        # more OffScreenRenderEnv settings; robosuite refuses steps past its horizon (LIBERO's default 1000)
        self.env_kwargs = {"horizon": max(1000, self.max_episode_steps + WAIT_STEPS), **env_kwargs}
        self.render_mode = "rgb_array"
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        frame = gymnasium.spaces.Box(0, 255, (IMAGE_SIZE, IMAGE_SIZE, 3), np.uint8)
        self.observation_space = gymnasium.spaces.Dict({
            "observation/image": frame,
            "observation/wrist_image": frame,
            "observation/state": gymnasium.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float64),
            "prompt": gymnasium.spaces.Text(max_length=1000, charset=string.printable),
        })
        self.task_id: int | None = None
        self.task_name = ""
        self.prompt = ""
        self._simulator: Any = None  # the current task's OffScreenRenderEnv
        self._initial_states: Any = None
        self._next_seed = 0
        self._steps = 0
        self._frame: np.ndarray | None = None  # the latest agentview frame, upright [256, 256, 3]

    def _open_task(self, task_id: int) -> None:
        from libero.libero import get_libero_path
        from libero.libero.envs import OffScreenRenderEnv

        if self._simulator is not None:
            self._simulator.close()
            self._simulator = None
        task = self.suite.get_task(task_id)
        bddl_file = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
        self._simulator = OffScreenRenderEnv(bddl_file_name=str(bddl_file), camera_heights=CAMERA_RESOLUTION,
                                             camera_widths=CAMERA_RESOLUTION, **self.env_kwargs)
        self._initial_states = self.suite.get_task_init_states(task_id)
        self.task_id, self.task_name, self.prompt = task_id, task.name, task.language

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict]:
        """Start the episode of `seed` (None: the seed after the previous episode's, from 0): its task and initial
        state, then openpi's settling steps."""
        super().reset(seed=seed)
        seed = self._next_seed if seed is None else int(seed)
        self._next_seed = seed + 1
        task_id = seed % self.suite.n_tasks
        if task_id != self.task_id:
            self._open_task(task_id)
        state_index = (seed // self.suite.n_tasks) % len(self._initial_states)
        np.random.seed(seed % 2**32)  # LIBERO's env.seed: numpy's global state, which robosuite's reset draws from
        self._simulator.reset()
        raw = self._simulator.set_init_state(self._initial_states[state_index])
        for _ in range(WAIT_STEPS):
            raw, _, _, _ = self._simulator.step(list(DUMMY_ACTION))
        self._steps = 0
        info = {"is_success": False, "task_id": task_id, "init_state": state_index}
        return self._observe(raw), info

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict]:
        if self._simulator is None:
            raise RuntimeError("step() before reset()")
        raw, reward, done, info = self._simulator.step(np.asarray(action, np.float64).tolist())
        self._steps += 1
        success = bool(done)  # (LIBERO's done: the task's goal predicates hold)
        truncated = not success and self._steps >= self.max_episode_steps
        return self._observe(raw), float(reward), success, truncated, {**info, "is_success": success}

    def _observe(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        self._frame = np.ascontiguousarray(np.asarray(raw["agentview_image"])[::-1, ::-1])
        return libero_observation(raw, self.prompt)

    def hold_action(self, observation: Mapping[str, Any]) -> np.ndarray:
        """openpi's dummy action: LIBERO's actions are end-effector deltas, so zeros keep the arm still (gripper open)."""
        return np.asarray(DUMMY_ACTION, np.float32)

    def render(self) -> np.ndarray:
        """The agentview camera's latest frame, upright, at 256x256 (openpi's videos)."""
        if self._frame is None:
            raise RuntimeError("render() before reset(): no frame yet")
        return self._frame

    def close(self) -> None:
        if self._simulator is not None:
            self._simulator.close()
            self._simulator = None


def ensure_libero_config() -> Path:
    """Write LIBERO's `$LIBERO_CONFIG_PATH/config.yaml` (default `~/.libero/config.yaml`) with the package's default
    paths (those of `libero.libero.get_default_path_dict()`) when it is absent, so that importing `libero.libero`
    does not stop to ask for a dataset folder. Returns the file."""
    config_file = Path(os.environ.get("LIBERO_CONFIG_PATH") or os.path.expanduser("~/.libero")) / "config.yaml"
    if config_file.is_file():
        return config_file
    spec = importlib.util.find_spec("libero.libero")  # (imports the empty top package `libero` only)
    if spec is None or not spec.submodule_search_locations:
        raise ValueError("the package libero (hf-libero) has no libero.libero module: pip install 'pi0-torch[libero]'")
    root = next(iter(spec.submodule_search_locations))
    paths = {
        "benchmark_root": root,
        "bddl_files": os.path.join(root, "./bddl_files"),
        "init_states": os.path.join(root, "./init_files"),
        "datasets": os.path.join(root, "../datasets"),
        "assets": os.path.join(root, "./assets"),
    }
    import yaml

    config_file.parent.mkdir(parents=True, exist_ok=True)
    config_file.write_text(yaml.dump(paths))
    return config_file


def check_libero_assets() -> str:
    """The folder of LIBERO's scene assets (fetched from the Hugging Face Hub on first use by hf-libero); a
    `FileNotFoundError` of one line naming what is missing when they cannot be had (`pi0-torch eval` prints it as
    its one-line error)."""
    import contextlib
    import io
    import warnings

    from libero.libero import get_assets_path

    # (it prints its download attempt, and a failure as a warning; the hub client warns about a deprecated argument)
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        folder = get_assets_path()
    missing = [name for name in ASSET_FOLDERS if not os.path.isdir(os.path.join(folder, name))]
    if missing:
        raise FileNotFoundError(f"LIBERO's scene assets are missing ({', '.join(missing)} not in {folder}): hf-libero "
                           "downloads them from the Hugging Face Hub dataset lerobot/libero-assets on first use, which "
                           "failed (offline?); run once where the Hub is reachable, or copy them to "
                           "~/.cache/libero/assets")
    return folder


def make_env(name: str, **kwargs: Any) -> LiberoSuiteEnv:
    """The LIBERO suite `name` as openpi's example runs it (see the module docstring).

    `max_episode_steps` replaces the suite's step limit; `render_mode` may only be `"rgb_array"`; other keyword
    arguments go to LIBERO's `OffScreenRenderEnv`.
    """
    if name not in SUITE_MAX_STEPS:
        raise ValueError(f"unknown LIBERO suite {name!r}; expected one of {', '.join(SUITE_MAX_STEPS)}")
    render_mode = kwargs.pop("render_mode", None)
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"libero/{name}: render_mode must be 'rgb_array', got {render_mode!r}")
    max_episode_steps = kwargs.pop("max_episode_steps", None) or SUITE_MAX_STEPS[name]
    configure_mujoco_gl()  # before robosuite imports MuJoCo
    ensure_libero_config()
    check_libero_assets()
    from libero.libero import benchmark

    return LiberoSuiteEnv(name, benchmark.get_benchmark_dict()[name](), max_episode_steps, kwargs)
