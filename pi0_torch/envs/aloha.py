"""ALOHA sim (gym-aloha) as openpi's `examples/aloha_sim` runs it: `pi0-torch eval --env aloha/<task>`.

Tasks: `AlohaTransferCube-v0` and `AlohaInsertion-v0` (gym-aloha's ids, made with `obs_type="pixels_agent_pos"`).
An observation is the message openpi's aloha_sim client (`examples/aloha_sim/env.py`) sends its policy server:

| key | value | openpi |
|---|---|---|
| `state` | gym-aloha's `agent_pos` as it comes: 14 values (6 joints + gripper per arm, grippers normalized to [0, 1]) | `env.py` `_convert_observation` |
| `images` | `{"cam_high": [3, 224, 224] uint8}`: the `top` camera's 480x640 frame, `resize_with_pad` to 224x224 (PIL bilinear, black bars), channels first | `env.py`, `openpi_client.image_tools` |

No prompt is sent: openpi's `pi0_aloha_sim` config injects its default prompt "Transfer cube" on the server side (for
both tasks), as the processor of a converted `pi0_aloha_sim` does (its `default_prompt`).
The rest of openpi's server-side preprocessing (`AlohaInputs` with `adapt_to_pi`, cameras, normalization) is the
processor's (`value_conversion="aloha"`) and the `aloha` observation format's.

The unwrapped env carries openpi's protocol: `replan_steps` 10 (`examples/aloha_sim/main.py`: `action_horizon=10`,
the actions executed per chunk), `control_hz` 50, `task_name`, and `hold_action(observation)`: the state itself,
as gym-aloha's actions are absolute joint targets in the units of its state (grippers included). Episodes end on
success (`info["is_success"]`, gym-aloha's reward 4) or after gym-aloha's 300 steps (or `max_episode_steps`).
Episode seeds go to gym-aloha's `reset(seed=...)` (the cube or peg/socket poses); openpi's client draws them from
`numpy.random.default_rng(0)` instead, so its episodes are other draws of the same distribution.

```python
>>> import numpy as np
>>> raw = {"pixels": {"top": np.full((480, 640, 3), 200, np.uint8)}, "agent_pos": np.zeros(14)}
>>> message = aloha_observation(raw)
>>> message["images"]["cam_high"].shape, message["images"]["cam_high"][:, 0, 0], message["state"].shape
((3, 224, 224), array([0, 0, 0], dtype=uint8), (14,))

```
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import gymnasium
import numpy as np

from pi0_torch.envs.rendering import configure_mujoco_gl
from pi0_torch.processing.images import resize_with_pad
from pi0_torch.utils.validation import first_line

TASKS = ("AlohaTransferCube-v0", "AlohaInsertion-v0")
IMAGE_SIZE = 224  # the client's resize_with_pad target
REPLAN_STEPS = 10  # openpi examples/aloha_sim/main.py: Args.action_horizon
CONTROL_HZ = 50  # gym-aloha's control step DT = 0.02 s
STATE_DIM = 14


def aloha_observation(raw: Mapping[str, Any]) -> dict[str, Any]:
    """A gym-aloha `pixels_agent_pos` observation -> the message openpi's aloha_sim client sends (see the module)."""
    top = np.asarray(raw["pixels"]["top"])
    if top.dtype != np.uint8 or top.ndim != 3 or top.shape[-1] != 3:
        raise ValueError(f"gym-aloha pixels/top: expected an [H, W, 3] uint8 frame, got shape {top.shape} dtype {top.dtype}")
    state = np.array(raw["agent_pos"])  # (a copy: the message outlives the env's buffer)
    if state.shape != (STATE_DIM,):
        raise ValueError(f"gym-aloha agent_pos: expected {STATE_DIM} values, got shape {state.shape}")
    frame = resize_with_pad(top, IMAGE_SIZE, IMAGE_SIZE)  # [224, 224, 3] uint8
    return {"state": state, "images": {"cam_high": np.ascontiguousarray(frame.transpose(2, 0, 1))}}


class AlohaSimEnv(gymnasium.Env):
    """One gym-aloha task whose observations are openpi's aloha_sim client messages (see the module docstring)."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    replan_steps = REPLAN_STEPS
    control_hz = CONTROL_HZ
    max_seed = 2**32 - 1  # (gym-aloha seeds numpy's RandomState, which takes seeds below 2^32)

    def __init__(self, task_name: str, simulator: gymnasium.Env) -> None:
        self.task_name = task_name
        self.simulator = simulator  # gym-aloha's env, with its TimeLimit
        self.render_mode = "rgb_array"
        self.action_space = simulator.action_space
        self.observation_space = gymnasium.spaces.Dict({
            "state": gymnasium.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float64),
            "images": gymnasium.spaces.Dict({
                "cam_high": gymnasium.spaces.Box(0, 255, (3, IMAGE_SIZE, IMAGE_SIZE), np.uint8),
            }),
        })
        self._frame: np.ndarray | None = None  # the latest top camera frame [480, 640, 3]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict]:
        super().reset(seed=seed)
        raw, info = self.simulator.reset(seed=seed, options=options)
        return self._observe(raw), info

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict]:
        raw, reward, terminated, truncated, info = self.simulator.step(np.asarray(action))
        return self._observe(raw), float(reward), bool(terminated), bool(truncated), info

    def _observe(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        self._frame = np.asarray(raw["pixels"]["top"])
        return aloha_observation(raw)

    def hold_action(self, observation: Mapping[str, Any]) -> np.ndarray:
        """The action that keeps both arms where they are: the current state as the joint and gripper targets."""
        return np.asarray(observation["state"], np.float32).copy()

    def render(self) -> np.ndarray:
        """The top camera's latest full-size frame [480, 640, 3] uint8 (what the policy saw, before resizing)."""
        if self._frame is None:
            raise RuntimeError("render() before reset(): no frame yet")
        return self._frame

    def close(self) -> None:
        """Close gym-aloha's env and free its MuJoCo rendering contexts now: left to the interpreter's exit, dm_control
        frees them after its render thread has stopped, and prints a traceback per context."""
        self.simulator.close()
        physics = getattr(getattr(self.simulator.unwrapped, "_env", None), "physics", None)
        if physics is not None and hasattr(physics, "free"):
            physics.free()  # (dm_control's `Physics.free`: twice is harmless)


def make_env(name: str, **kwargs: Any) -> AlohaSimEnv:
    """`AlohaTransferCube-v0` or `AlohaInsertion-v0` as openpi's aloha_sim example runs it.

    `max_episode_steps` replaces gym-aloha's 300 steps; `render_mode` may only be `"rgb_array"` (frames come from
    the observations); other keyword arguments go to gym-aloha's env.
    """
    if name not in TASKS:
        raise ValueError(f"unknown ALOHA sim task {name!r}; expected one of {', '.join(TASKS)}")
    render_mode = kwargs.pop("render_mode", None)
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"aloha/{name}: render_mode must be 'rgb_array', got {render_mode!r}")
    if kwargs.get("max_episode_steps") is None:
        kwargs.pop("max_episode_steps", None)  # gym-aloha's registered limit
    configure_mujoco_gl()  # before gym-aloha imports MuJoCo
    import gym_aloha  # noqa: F401  (registers the gym_aloha/ ids)

    try:
        simulator = gymnasium.make(f"gym_aloha/{name}", obs_type="pixels_agent_pos", **kwargs)
    except TypeError as error:  # a setting gym-aloha does not take
        raise ValueError(f"aloha/{name} cannot be made with the settings {sorted(kwargs)}: {first_line(error)}") from None
    return AlohaSimEnv(name, simulator)
