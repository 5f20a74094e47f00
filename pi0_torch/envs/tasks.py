"""The three tabletop tasks as gymnasium environments: layouts, instructions, success and failure.

- `ReachEnv` ("move to the red object"): three objects; success when the effector is within `GRASP_RADIUS` of the
  named one.
- `PickPlaceEnv` ("put the red object in the blue zone"): three objects, two or three zones; success when the named
  object rests (not held) with its centre inside the named zone.
- `ConveyorEnv` ("put the red object in the bin"): three objects drift to the right on a belt at `BELT_SPEED` per
  step (the same in every episode); success when the named object rests in the fixed bin below the belt; failure
  (terminated) when it leaves the table (x > 1) first.

Observation (the server's default format, what `PI0Policy.infer` takes):
`{"images": {"base_0_rgb": uint8 [H, W, 3], "left_wrist_0_rgb": uint8 [H, W, 3]}, "state": float32 [3], "prompt": str}`
with state `[x, y, gripper]` (the wrist camera only with `wrist_camera=True`, the default). Object and zone positions
are only in the images. Action: float32 `[target_x, target_y, gripper_command]`, an absolute position target
(clipped to the table) and a gripper command (> 0 close); repeating the last action keeps the robot still once it
has reached the target.

Episodes are truncated by gymnasium's `TimeLimit` (the registered ids carry each task's `default_max_episode_steps`;
`gymnasium.make(id, max_episode_steps=N)` overrides it). `reset(seed=s)` fully determines the layout and instruction.

>>> env = ReachEnv(image_size=64)
>>> observation, info = env.reset(seed=0)
>>> observation["images"]["base_0_rgb"].shape, observation["state"].dtype, info["is_success"]
((64, 64, 3), dtype('float32'), False)
>>> observation["prompt"].startswith("move to the ")
True
"""

from __future__ import annotations

import string
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium import spaces

from pi0_torch.envs.tabletop import (
    BIN_COLOR,
    CONTROL_HZ,
    DEFAULT_SLIP_ACCELERATION,
    GRASP_RADIUS,
    OBJECT_RADIUS,
    PALETTE,
    ZONE_HALF_SIZE,
    Belt,
    Renderer,
    World,
    Zone,
)

CAMERA = "base_0_rgb"  # the whole table, seen from above
WRIST_CAMERA = "left_wrist_0_rgb"  # the effector's surroundings, magnified (π0's name for a single arm's wrist camera)
WRIST_ZOOM = 2.5  # the wrist camera sees a square of side 2 / WRIST_ZOOM = 0.8 centred on the effector
NUM_OBJECTS = 3
OBJECT_SPACING = 2 * OBJECT_RADIUS + 0.1  # minimum distance between object centres at the start
BELT_SPEED = 0.025  # conveyor: +x per step
BELT_BAND = (-1.0, 0.2)  # conveyor: the belt covers these y
BIN_CENTER = (-0.55, 0.68)  # conveyor: the bin, below the belt
PROMPT_CHARSET = string.ascii_lowercase + " "
PROMPT_MAX_LENGTH = 64


@dataclass(frozen=True)
class Layout:
    """One episode's scene: objects, zones, belt, the effector's start, and which object and zone are named."""

    colors: list[str]
    positions: np.ndarray  # [N, 2]
    effector: np.ndarray  # [2]
    target_object: int
    zones: tuple[Zone, ...] = ()
    target_zone: int = -1
    belt: Belt | None = None


class TabletopEnv(gymnasium.Env):
    """Base class of the tasks: the gymnasium API around a `World` and its `Renderer`.

    Args:
        image_size: side of the square camera image `base_0_rgb` in pixels.
        slip_acceleration: a held object slips out when the effector's velocity changes by more than this between
            two consecutive steps (`float("inf")` turns slipping off).
        render_mode: None or "rgb_array" (`render()` returns the frame).
        render_size: side of the frame `render()` returns (default `image_size`).
        num_objects: objects on the table, 1 to 3 (default 3, the benchmark; fewer make easier training scenes).
        wrist_camera: also observe `left_wrist_0_rgb`, a view centred on the effector, magnified `WRIST_ZOOM` times
            (same size as `base_0_rgb`).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    control_hz: ClassVar[int] = CONTROL_HZ  # control steps per second (simulated time)
    motion_action_dims: ClassVar[tuple[int, ...]] = (0, 1)  # the position target; the gripper command is a switch
    default_max_episode_steps: ClassVar[int]

    def __init__(
        self,
        image_size: int = 96,
        slip_acceleration: float = DEFAULT_SLIP_ACCELERATION,
        render_mode: str | None = None,
        render_size: int | None = None,
        num_objects: int = NUM_OBJECTS,
        wrist_camera: bool = True,
    ) -> None:
        if not 1 <= num_objects <= NUM_OBJECTS:
            raise ValueError(f"num_objects must lie in [1, {NUM_OBJECTS}], got {num_objects}")
        self.num_objects = int(num_objects)  # fewer than 3: easier scenes (a training curriculum), not the benchmark
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not slip_acceleration > 0:
            raise ValueError(f"slip_acceleration must be > 0, got {slip_acceleration}")
        self.image_size = int(image_size)
        self.slip_acceleration = float(slip_acceleration)
        self.render_mode = render_mode
        self._renderer = Renderer(self.image_size)
        self._render_renderer = Renderer(render_size) if render_size and render_size != self.image_size else self._renderer
        self._wrist_renderer = Renderer(self.image_size, WRIST_ZOOM) if wrist_camera else None
        frame = spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        cameras = [CAMERA, WRIST_CAMERA] if wrist_camera else [CAMERA]
        self.observation_space = spaces.Dict(
            {
                "images": spaces.Dict({name: frame for name in cameras}),
                "state": spaces.Box(np.array([-1, -1, 0], np.float32), np.array([1, 1, 1], np.float32), dtype=np.float32),
                "prompt": spaces.Text(PROMPT_MAX_LENGTH, min_length=1, charset=PROMPT_CHARSET),
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.layout: Layout | None = None
        self.world: World | None = None
        self.prompt = ""
        self.elapsed_steps = 0

    # --- the task: subclasses define these ---

    def sample_layout(self, rng: np.random.Generator) -> Layout:
        raise NotImplementedError

    def instruction(self, layout: Layout) -> str:
        raise NotImplementedError

    def is_success(self) -> bool:
        raise NotImplementedError

    def is_failure(self) -> bool:
        """True when the episode can no longer succeed (it terminates as a failure)."""
        return False

    def stage(self) -> str:
        """A coarse progress label for logs (`info["stage"]`)."""
        return "done" if self.is_success() else "reach"

    def place_zone(self) -> Zone:
        """The zone the named object must end in (tasks that place something)."""
        raise NotImplementedError

    # --- gymnasium API ---

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        self.layout = self.sample_layout(self.np_random)
        self.world = World(
            self.layout.colors, self.layout.positions, self.layout.effector, self.layout.zones, self.layout.belt,
            self.slip_acceleration,
        )
        self.prompt = self.instruction(self.layout)
        self.elapsed_steps = 0
        return self._observation(), self._info()

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (3,):
            raise ValueError(f"action must have shape (3,) [target_x, target_y, gripper], got shape {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action.tolist()}")
        self.world.step(action[:2], float(action[2]))
        self.elapsed_steps += 1
        success = self.is_success()
        terminated = success or self.is_failure()
        return self._observation(), float(success), terminated, False, self._info(success)

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self.world is None:
            return None
        return self._render_renderer.draw(self.world)

    def _observation(self) -> dict[str, Any]:
        assert self.world is not None
        images = {CAMERA: self._renderer.draw(self.world)}
        if self._wrist_renderer is not None:
            images[WRIST_CAMERA] = self._wrist_renderer.draw(self.world)
        return {"images": images, "state": self.world.state(), "prompt": self.prompt}

    def _info(self, success: bool | None = None) -> dict[str, Any]:
        assert self.world is not None and self.layout is not None
        return {
            "is_success": self.is_success() if success is None else success,
            "stage": self.stage(),
            "held_object": self.world.held,
            "target_object": self.layout.target_object,
            "slipped": self.world.slipped,
        }

    # --- shared helpers of the tasks ---

    def _target_position(self) -> np.ndarray:
        assert self.world is not None and self.layout is not None
        return self.world.positions[self.layout.target_object]

    def _placed_in(self, zone: Zone) -> bool:
        assert self.world is not None and self.layout is not None
        return self.world.held != self.layout.target_object and zone.contains(self._target_position())

    def _place_stage(self) -> str:
        assert self.world is not None and self.layout is not None
        if self.is_success():
            return "done"
        return "carry" if self.world.held == self.layout.target_object else "reach"


def _sample_points(
    rng: np.random.Generator, count: int, low: np.ndarray, high: np.ndarray, spacing: float,
    allowed: Any = None, existing: np.ndarray | None = None,
) -> np.ndarray:
    """`count` uniform points in the box [low, high] at least `spacing` apart (and from `existing`), each passing
    `allowed(point)`; rejection sampling."""
    points: list[np.ndarray] = [] if existing is None else list(existing)
    first = len(points)
    for _ in range(10_000):
        point = rng.uniform(low, high)
        if all(np.hypot(*(point - other)) >= spacing for other in points) and (allowed is None or allowed(point)):
            points.append(point)
            if len(points) - first == count:
                return np.array(points[first:])
    raise RuntimeError("could not place the bodies; the layout constraints are too tight")


def _choose_colors(rng: np.random.Generator, count: int) -> list[str]:
    return [str(c) for c in rng.choice(list(PALETTE), size=count, replace=False)]


class ReachEnv(TabletopEnv):
    """`pi0_torch/Reach-v0`: "move to the <color> object" among three objects."""

    default_max_episode_steps = 40

    def sample_layout(self, rng: np.random.Generator) -> Layout:
        colors = _choose_colors(rng, self.num_objects)
        positions = _sample_points(rng, self.num_objects, np.full(2, -0.8), np.full(2, 0.8), OBJECT_SPACING)
        target = int(rng.integers(self.num_objects))
        effector = _sample_points(rng, 1, np.full(2, -0.5), np.full(2, 0.5), 0.3, existing=positions[target:target + 1])[0]
        return Layout(colors, positions, effector, target)

    def instruction(self, layout: Layout) -> str:
        return f"move to the {layout.colors[layout.target_object]} object"

    def is_success(self) -> bool:
        assert self.world is not None
        return bool(np.hypot(*(self.world.effector - self._target_position())) <= GRASP_RADIUS)


class PickPlaceEnv(TabletopEnv):
    """`pi0_torch/PickPlace-v0`: "put the <color> object in the <color> zone" (three objects, two or three zones)."""

    default_max_episode_steps = 100

    def sample_layout(self, rng: np.random.Generator) -> Layout:
        num_zones = int(rng.integers(2, 4))
        zone_colors = _choose_colors(rng, num_zones)
        # zones at least a side plus a gap apart along one axis, so they never overlap
        centers: list[np.ndarray] = []
        while len(centers) < num_zones:
            center = rng.uniform(-0.75, 0.75, size=2)
            if all(np.max(np.abs(center - other)) >= 2 * ZONE_HALF_SIZE + 0.1 for other in centers):
                centers.append(center)
        zones = tuple(Zone(color, center, PALETTE[color]) for color, center in zip(zone_colors, centers))
        clear = ZONE_HALF_SIZE + OBJECT_RADIUS + 0.05

        def outside_zones(point: np.ndarray) -> bool:
            return all(np.max(np.abs(point - zone.center)) >= clear for zone in zones)

        colors = _choose_colors(rng, self.num_objects)
        positions = _sample_points(rng, self.num_objects, np.full(2, -0.85), np.full(2, 0.85), OBJECT_SPACING, outside_zones)
        effector = rng.uniform(-0.8, 0.8, size=2)
        return Layout(colors, positions, effector, int(rng.integers(self.num_objects)), zones, int(rng.integers(num_zones)))

    def instruction(self, layout: Layout) -> str:
        return f"put the {layout.colors[layout.target_object]} object in the {layout.zones[layout.target_zone].name} zone"

    def place_zone(self) -> Zone:
        assert self.layout is not None
        return self.layout.zones[self.layout.target_zone]

    def is_success(self) -> bool:
        return self._placed_in(self.place_zone())

    def stage(self) -> str:
        return self._place_stage()


class ConveyorEnv(TabletopEnv):
    """`pi0_torch/Conveyor-v0`: "put the <color> object in the bin" while the objects drift off the table."""

    default_max_episode_steps = 100

    def sample_layout(self, rng: np.random.Generator) -> Layout:
        colors = _choose_colors(rng, self.num_objects)
        positions = _sample_points(rng, self.num_objects, np.array([-0.9, -0.8]), np.array([0.0, 0.05]), OBJECT_SPACING)
        effector = rng.uniform([-0.9, 0.45], [0.9, 0.9])
        belt = Belt(*BELT_BAND, np.array([BELT_SPEED, 0.0]))
        bin_zone = Zone("bin", np.array(BIN_CENTER), BIN_COLOR)
        return Layout(colors, positions, effector, int(rng.integers(self.num_objects)), (bin_zone,), 0, belt)

    def instruction(self, layout: Layout) -> str:
        return f"put the {layout.colors[layout.target_object]} object in the bin"

    def place_zone(self) -> Zone:
        assert self.layout is not None
        return self.layout.zones[0]

    def is_success(self) -> bool:
        return self._placed_in(self.place_zone())

    def is_failure(self) -> bool:
        return bool(self._target_position()[0] > 1.0)

    def stage(self) -> str:
        return "fell_off" if self.is_failure() else self._place_stage()
