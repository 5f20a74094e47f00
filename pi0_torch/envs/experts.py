"""Scripted experts for the tabletop tasks: they read the true world state and act like a careful robot.

Each motion segment (to the object, to the place point) follows a quadratic Bezier curve whose control point sits
off the straight line by a random fraction (`CURVATURE`) of its length, to a random side chosen per segment, at a
trapezoidal speed profile (acceleration at most `ACCELERATION` per step, a cruise speed drawn per episode from
`CRUISE_SPEEDS`). So the experts never slip, and the demonstrations are multimodal on purpose: the same scene has
paths bending either way, which a policy must model as a distribution.

An expert re-plans when the world is not where its plan expects (the robot was paused, an object slipped out, the
object it intercepts is no longer where it will be at the planned grasp). On the conveyor it intercepts: it aims at
where the object will be when the effector gets there.

>>> import gymnasium
>>> import pi0_torch.envs
>>> env = gymnasium.make("pi0_torch/PickPlace-v0", image_size=32)
>>> expert = make_expert(env)
>>> _, info = env.reset(seed=3)
>>> expert.reset(seed=3)
>>> done = False
>>> while not done:
...     _, _, terminated, truncated, info = env.step(expert.act(env))
...     done = terminated or truncated
>>> info["is_success"], info["slipped"]
(True, 0)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np

from pi0_torch.envs.tabletop import GRASP_RADIUS
from pi0_torch.envs.tasks import ReachEnv, TabletopEnv

CRUISE_SPEEDS = (0.06, 0.09)  # per-episode cruise speed range (the world allows up to MAX_SPEED = 0.1)
ACCELERATION = 0.015  # largest speed change per step, well under the default slip threshold (0.06)
CURVATURE = (0.1, 0.3)  # control point offset, as a fraction of the segment's length
PLACE_JITTER = 0.08  # the place point lies this far (at most) from the zone centre along each axis
ON_TRACK = 1e-6  # the effector is where the plan put it
INTERCEPT_TOLERANCE = 0.02  # replan when the intercepted object will miss the planned grasp point by more
OPEN, CLOSE = -1.0, 1.0


def bezier_path(start: np.ndarray, end: np.ndarray, bend: float, samples: int = 64) -> np.ndarray:
    """Points `[samples, 2]` of the quadratic Bezier from `start` to `end` whose control point is the midpoint
    moved sideways by `bend` times the distance (positive: to the left of the direction of travel)."""
    chord = end - start
    normal = np.array([-chord[1], chord[0]])
    control = (start + end) / 2 + bend * normal
    u = np.linspace(0.0, 1.0, samples)[:, None]
    return (1 - u) ** 2 * start + 2 * u * (1 - u) * control + u**2 * end


def speed_profile(length: float, start_speed: float, cruise: float, acceleration: float) -> np.ndarray:
    """Distances along a path of `length` after each step of a trapezoidal profile: speed up by at most
    `acceleration` per step to `cruise`, slow down to arrive at rest (the last entry is `length`)."""
    travelled, speed, distances = 0.0, start_speed, []
    while length - travelled > 1e-9:
        remaining = length - travelled
        speed = min(cruise, speed + acceleration, np.sqrt(2 * acceleration * remaining))
        speed = max(speed, min(remaining, acceleration))
        travelled = min(travelled + speed, length)
        distances.append(travelled)
    return np.array(distances)


def follow_path(path: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """Points `[len(distances), 2]` at the given arc lengths along the polyline `path`."""
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    return np.stack([np.interp(distances, arc, path[:, 0]), np.interp(distances, arc, path[:, 1])], axis=1)


@dataclass
class Plan:
    """Waypoints `[n, 2]` for the steps `start_step .. start_step + n - 1`, and the gripper command along them."""

    kind: str
    waypoints: np.ndarray
    start_step: int
    gripper: float

    def index(self, step: int) -> int:
        return step - self.start_step

    def finished(self, step: int) -> bool:
        return self.index(step) >= len(self.waypoints)

    def on_track(self, step: int, effector: np.ndarray) -> bool:
        i = self.index(step)
        expected = self.waypoints[min(i, len(self.waypoints)) - 1] if i > 0 else None
        return expected is None or bool(np.hypot(*(effector - expected)) <= ON_TRACK)

    def action(self, step: int) -> np.ndarray:
        point = self.waypoints[min(self.index(step), len(self.waypoints) - 1)]
        return np.array([*point, self.gripper], dtype=np.float32)


class ScriptedExpert:
    """The expert of one env (any of the three tasks). `reset(seed)` with the episode's seed, then `act(env)`."""

    def __init__(self, env: gymnasium.Env) -> None:
        if not isinstance(env.unwrapped, TabletopEnv):
            raise TypeError(f"make_expert needs a pi0_torch tabletop env, got {type(env.unwrapped).__name__}")
        self.rng = np.random.default_rng()
        self.cruise = CRUISE_SPEEDS[0]
        self.plan: Plan | None = None
        self.place_offset = np.zeros(2)

    def reset(self, seed: int | None = None) -> None:
        """Draw this episode's cruise speed and the stream of random path choices (deterministic given `seed`)."""
        self.rng = np.random.default_rng(None if seed is None else [seed, 0x5EED])
        self.cruise = float(self.rng.uniform(*CRUISE_SPEEDS))
        self.place_offset = self.rng.uniform(-PLACE_JITTER, PLACE_JITTER, size=2)
        self.plan = None

    def act(self, env: gymnasium.Env) -> np.ndarray:
        """The next action, float32 `[target_x, target_y, gripper_command]`."""
        task = env.unwrapped
        assert isinstance(task, TabletopEnv) and task.world is not None and task.layout is not None
        world, target, step = task.world, task.layout.target_object, task.elapsed_steps
        if isinstance(task, ReachEnv):
            return self._approach(task, step, OPEN)
        if world.held == target:
            goal = task.place_zone().center + self.place_offset - world.held_offset
            if self.plan is not None and self.plan.kind == "carry" and self.plan.finished(step):
                return np.array([*world.effector, OPEN], dtype=np.float32)  # at the place point: let go
            return self._static_goal(task, "carry", goal, step, CLOSE)
        if world.gripper_closed:  # closed on nothing (or after a slip): open first
            self.plan = None
            return np.array([*world.effector, OPEN], dtype=np.float32)
        action = self._approach(task, step, OPEN)
        assert self.plan is not None
        if self.plan.finished(step) and np.hypot(*(world.effector - world.positions[target])) <= 0.75 * GRASP_RADIUS:
            return np.array([*world.effector, CLOSE], dtype=np.float32)
        return action

    def _static_goal(self, task: TabletopEnv, kind: str, goal: np.ndarray, step: int, gripper: float) -> np.ndarray:
        world = task.world
        assert world is not None
        plan = self.plan
        if plan is None or plan.kind != kind or not plan.on_track(step, world.effector):
            self.plan = plan = self._plan(kind, world.effector, world.velocity, goal, step, gripper)
        return plan.action(step)

    def _approach(self, task: TabletopEnv, step: int, gripper: float) -> np.ndarray:
        """Move to the named object, intercepting it where the belt will have carried it."""
        world, layout = task.world, task.layout
        assert world is not None and layout is not None
        plan = self.plan
        if plan is not None and plan.kind == "approach" and plan.on_track(step, world.effector):
            remaining = max(len(plan.waypoints) - plan.index(step), 0)
            meets = world.predicted_position(layout.target_object, remaining)
            if np.hypot(*(meets - plan.waypoints[-1])) <= INTERCEPT_TOLERANCE:
                return plan.action(step)
        # plan so that the effector waits at the point where the object will be at the grasp step
        bend = self._bend()
        arrival = 0
        for _ in range(50):
            goal = world.predicted_position(layout.target_object, arrival)
            waypoints = self._waypoints(world.effector, world.velocity, goal, bend)
            if len(waypoints) <= arrival:
                break
            arrival = len(waypoints)
        padding = np.repeat(waypoints[-1:], arrival - len(waypoints), axis=0)
        self.plan = Plan("approach", np.concatenate([waypoints, padding]), step, gripper)
        return self.plan.action(step)

    def _bend(self) -> float:
        return float(self.rng.choice([-1.0, 1.0]) * self.rng.uniform(*CURVATURE))

    def _waypoints(self, start: np.ndarray, velocity: np.ndarray, goal: np.ndarray, bend: float) -> np.ndarray:
        if np.hypot(*(goal - start)) < 1e-9:
            return goal[None].copy()
        path = bezier_path(start, goal, bend)
        direction = path[1] - path[0]
        start_speed = max(float(velocity @ direction) / float(np.hypot(*direction)), 0.0)
        distances = speed_profile(float(np.sum(np.hypot(*np.diff(path, axis=0).T))), start_speed, self.cruise, ACCELERATION)
        return follow_path(path, distances)

    def _plan(self, kind: str, start: np.ndarray, velocity: np.ndarray, goal: np.ndarray, step: int, gripper: float) -> Plan:
        return Plan(kind, self._waypoints(start, velocity, goal, self._bend()), step, gripper)


def has_scripted_expert(env_id: str) -> bool:
    """Whether `pi0-torch eval --policy expert` has an expert for this env id: the tabletop envs (`pi0_torch/...`)
    and Meta-World's (`metaworld/...`, its own scripted policies). ALOHA sim, LIBERO and PushT have none here
    (gym-aloha ships its tasks, not the scripted policies ACT recorded its demos with)."""
    return env_id.startswith(("pi0_torch/", "metaworld/"))


def make_expert(env: gymnasium.Env) -> Any:
    """The scripted expert of an env (wrapped or not): a tabletop env's [`ScriptedExpert`], or the one an env
    provides (`scripted_expert()`: Meta-World's). It has `reset(seed)` and `act(env) -> action`; an env with
    neither is a `ValueError` naming it."""
    if hasattr(env.unwrapped, "scripted_expert"):
        return env.unwrapped.scripted_expert()
    if not isinstance(env.unwrapped, TabletopEnv):
        raise ValueError(f"{type(env.unwrapped).__name__} has no scripted expert (the pi0_torch tabletop envs and "
                         "Meta-World's have one)")
    return ScriptedExpert(env)
