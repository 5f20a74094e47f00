"""Meta-World tasks behind `pi0-torch eval --env metaworld/<task>-v3` and `pi0-torch demos`, with their scripted
experts.

Each episode seed draws its own object and goal placement (Meta-World's random reset space, seeded per episode),
so held-out seeds (evaluation starts at 1,000,000) are scenes no demonstration showed. The policy sees:

- `images`: `{"base_0_rgb": the corner2 camera, HxWx3 uint8}` (`image_size`, default 64);
- `state`: the effector position (x, y, z) and the gripper opening in [0, 1] (4 values);
- `prompt`: the task in words (`TASK_PROMPTS`, e.g. "open the drawer").

Actions are Meta-World's own: a displacement of the effector (x, y, z in [-1, 1], scaled by the env) and the gripper
effort (-1 opens, 1 closes). An episode ends on success (`info["is_success"]`) or after `max_episode_steps` (default
Meta-World's 500). The env's full vector observation (goal included) stays inside: only the scripted expert
(`metaworld.policies`, [`MetaWorldExpert`]) reads it.

```python
>>> env = make_env("reach-v3", image_size=32)
>>> observation, _ = env.reset(seed=0)
>>> observation["images"]["base_0_rgb"].shape, observation["state"].shape, observation["prompt"]
((32, 32, 3), (4,), 'reach the goal')
>>> expert = env.unwrapped.scripted_expert()
>>> for _ in range(200):
...     observation, _, terminated, truncated, info = env.step(expert.act(env))
...     if terminated or truncated:
...         break
>>> info["is_success"]
True
>>> env.close()

```
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium
import numpy as np

from pi0_torch.envs.rendering import check_mujoco_rendering
from pi0_torch.utils.extras import require_extra

require_extra("metaworld", __name__)
check_mujoco_rendering()  # (MUJOCO_GL is chosen before metaworld imports MuJoCo)
import metaworld  # noqa: E402
from metaworld.env_dict import ALL_V3_ENVIRONMENTS  # noqa: E402
from metaworld.policies import ENV_POLICY_MAP  # noqa: E402

CAMERA = "corner2"  # (Meta-World's camera)
CAMERA_NAME = "base_0_rgb"  # the model camera its frames feed
CAMERA_POSITION = (0.75, 0.075, 0.7)  # (LeRobot's Meta-World envs move corner2 here too)
DEFAULT_IMAGE_SIZE = 64
STATE_NAMES = ["x", "y", "z", "gripper_opening"]
ACTION_NAMES = ["dx", "dy", "dz", "gripper_effort"]
# the instruction of each task the adapter knows a sentence for; others get their name in words ("door-lock-v3" ->
# "door lock")
TASK_PROMPTS = {
    "reach-v3": "reach the goal",
    "push-v3": "push the puck to the goal",
    "pick-place-v3": "pick up the puck and place it at the goal",
    "door-open-v3": "open the door",
    "door-close-v3": "close the door",
    "drawer-open-v3": "open the drawer",
    "drawer-close-v3": "close the drawer",
    "button-press-topdown-v3": "press the button from the top",
    "button-press-v3": "press the button",
    "window-open-v3": "open the window",
    "window-close-v3": "close the window",
    "peg-insert-side-v3": "insert the peg into the hole",
    "faucet-open-v3": "turn the faucet on",
    "faucet-close-v3": "turn the faucet off",
    "handle-press-v3": "press the handle down",
    "lever-pull-v3": "pull the lever up",
    "plate-slide-v3": "slide the plate into the goal",
    "coffee-button-v3": "press the coffee machine button",
    "dial-turn-v3": "turn the dial",
    "sweep-into-v3": "sweep the puck into the hole",
}
TASKS: tuple[str, ...] = tuple(sorted(ALL_V3_ENVIRONMENTS))


def task_prompt(task: str) -> str:
    """The instruction of a task: its sentence in `TASK_PROMPTS`, else its name in words."""
    return TASK_PROMPTS.get(task, task.removesuffix("-v3").replace("-", " "))


class MetaWorldEnv(gymnasium.Env):
    """One Meta-World task with pi0-torch's observation layout (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    replan_steps = None  # (no published protocol: the policy's recommended setting)
    state_names, action_names, robot_type = STATE_NAMES, ACTION_NAMES, "sawyer"  # (for recorded datasets)

    def __init__(self, task: str, image_size: int = DEFAULT_IMAGE_SIZE, max_episode_steps: int | None = None,
                 render_mode: str | None = None) -> None:
        if task not in ALL_V3_ENVIRONMENTS:
            raise ValueError(f"unknown Meta-World task {task!r}; expected one of {', '.join(TASKS)}")
        if not isinstance(image_size, int) or isinstance(image_size, bool) or not 16 <= image_size <= 1024:
            raise ValueError(f"image_size must be an integer in [16, 1024], got {image_size!r}")
        self.task_name, self.image_size, self.render_mode = task, image_size, render_mode
        self.sim = ALL_V3_ENVIRONMENTS[task](render_mode="rgb_array", camera_name=CAMERA, width=image_size,
                                             height=image_size)
        camera = self.sim.model.camera(CAMERA).id
        self.sim.model.cam_pos[camera] = CAMERA_POSITION  # nearer than Meta-World's: the table fills the frame
        # no multisampling, no shadows: 10x faster in software OpenGL (OSMesa: 130 -> 12 ms a frame on 2 CPU cores)
        self.sim.model.vis.quality.offsamples = 0
        self.sim.model.vis.quality.shadowsize = 0
        self.sim.set_task(metaworld.MT1(task, seed=0).train_tasks[0])  # (required once; placements come per seed)
        self.sim._partially_observable = False  # the expert reads the goal; the policy never sees this vector
        self.sim.__dict__.pop("sawyer_observation_space", None)  # (a cached property of the old observability)
        self.sim._freeze_rand_vec = False  # each episode seed draws its own placement ...
        self.sim.seeded_rand_vec = True  # ... from the env's seeded generator (not numpy's global one)
        self.max_episode_steps = int(max_episode_steps or self.sim.max_path_length)
        self.sim.max_path_length = self.max_episode_steps
        self.control_hz = self.metadata["render_fps"]
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = gymnasium.spaces.Dict({
            "images": gymnasium.spaces.Dict({CAMERA_NAME: gymnasium.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)}),
            "state": gymnasium.spaces.Box(-np.inf, np.inf, (4,), np.float32),
            "prompt": gymnasium.spaces.Text(256),
        })
        self.vector = np.zeros(39)  # Meta-World's own observation (for the expert)
        self.steps = 0

    def _observation(self) -> dict[str, Any]:
        frame = np.ascontiguousarray(self.sim.render()[::-1])  # (MuJoCo's frames are bottom-up)
        return {"images": {CAMERA_NAME: frame}, "state": self.vector[:4].astype(np.float32),
                "prompt": task_prompt(self.task_name)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        self.sim.seed(int(self.np_random.integers(2**31)))  # the placement and the sim's own randomness
        self.vector, _ = self.sim.reset()
        self.steps = 0
        return self._observation(), {"is_success": False}

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, np.float32).reshape(4)
        if not np.isfinite(action).all():
            raise ValueError(f"action must be finite, got {action.tolist()}")
        self.vector, reward, _, _, info = self.sim.step(np.clip(action, -1.0, 1.0))
        self.steps += 1
        success = bool(info["success"])
        return self._observation(), float(reward), success, self.steps >= self.max_episode_steps and not success, {
            "is_success": success}

    def scripted_expert(self) -> MetaWorldExpert:
        """Meta-World's scripted policy for this task (`pi0-torch demos`, `eval --policy expert`)."""
        return MetaWorldExpert(self)

    def hold_action(self, observation: Any = None) -> np.ndarray:
        """Standing still: no displacement, no gripper effort."""
        return np.zeros(4, np.float32)

    def render(self) -> np.ndarray:
        return self._observation()["images"][CAMERA_NAME]

    def close(self) -> None:
        self.sim.close()


class MetaWorldExpert:
    """Meta-World's scripted policy for the env's task (it reads the full vector observation, goal included)."""

    def __init__(self, env: gymnasium.Env) -> None:
        self.policy = ENV_POLICY_MAP[env.unwrapped.task_name]()

    def reset(self, seed: int) -> None:
        """(The scripted policies are deterministic.)"""

    def act(self, env: gymnasium.Env) -> np.ndarray:
        with warnings.catch_warnings():  # ("Constant(s) may be too high" on large moves: the action is clipped here)
            warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high", category=UserWarning)
            action = self.policy.get_action(env.unwrapped.vector)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def make_env(name: str, **kwargs: Any) -> MetaWorldEnv:
    """`metaworld/<name>`: a Meta-World task (`reach-v3`, `drawer-open-v3`, ...). Keyword arguments: `image_size`,
    `max_episode_steps`, `render_mode`."""
    return MetaWorldEnv(name, **kwargs)
