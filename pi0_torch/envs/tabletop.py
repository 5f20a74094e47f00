"""The 2-D tabletop world: bodies, dynamics and the top-down camera.

Coordinates are (x, y) in [-1, 1]^2, x to the right and y down (the image convention). The world holds colored
discs (objects), square zones, an optional conveyor belt and one effector with a gripper. One `World.step` is one
control step (the envs run at `CONTROL_HZ`):

1. the effector moves toward its position target, at most `MAX_SPEED` per step (targets are clipped to the table);
2. closing the gripper (open -> closed) within `GRASP_RADIUS` of object centres grasps the nearest such object;
   opening releases the held object where it is;
3. grip slip: while an object is held, a change of the effector's velocity larger than `slip_acceleration` between
   two consecutive steps (|v_t - v_{t-1}|) makes the object slip out; it drops where it was and the gripper stays
   closed, empty. Smooth motion never slips; a jump in the position target (e.g. where two action chunks disagree)
   does;
4. objects that are not held and lie on the belt drift by the belt's velocity.

`Renderer` draws the world with numpy only: the static layer (table, belt, zones) is drawn once; each frame copies
it and draws the moving bodies inside their bounding boxes.

>>> world = World(["red"], np.array([[0.3, 0.0]]), effector=np.array([0.0, 0.0]))
>>> world.step(np.array([0.5, 0.0]), gripper_command=-1.0)
>>> world.effector.round(3).tolist()  # moved MAX_SPEED toward the target
[0.1, 0.0]
>>> Renderer(32).draw(world).shape
(32, 32, 3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CONTROL_HZ = 10  # control steps per second of simulated time (the datasets' fps)
OBJECT_RADIUS = 0.1
GRASP_RADIUS = 0.08  # the effector grasps objects whose centre lies within this distance
MAX_SPEED = 0.1  # the effector's largest displacement per step
DEFAULT_SLIP_ACCELERATION = 0.06  # |v_t - v_{t-1}| above this makes a held object slip out
ZONE_HALF_SIZE = 0.2  # zones are squares of side 0.4

PALETTE: dict[str, tuple[int, int, int]] = {
    "red": (230, 40, 40),
    "green": (40, 200, 60),
    "blue": (50, 100, 255),
    "yellow": (240, 220, 30),
    "magenta": (225, 50, 225),
    "cyan": (40, 220, 230),
}
TABLE_COLOR = (96, 96, 96)
BELT_COLOR = (58, 58, 58)
BELT_EDGE_COLOR = (30, 30, 30)
BIN_COLOR = (200, 200, 200)  # the conveyor's bin: a light grey zone
EFFECTOR_COLOR = (255, 255, 255)
EFFECTOR_INNER_RADIUS = 0.045  # the open gripper: a white ring from here out to GRASP_RADIUS
CLOSED_EFFECTOR_RADIUS = 0.06  # the closed gripper: a filled white disc (a held object shows around it)
OFF_TABLE_COLOR = (0, 0, 0)  # what a zoomed view shows beyond the table's edge


@dataclass(frozen=True)
class Zone:
    """A square zone on the table, named by its color ("bin" for the conveyor's bin)."""

    name: str
    center: np.ndarray  # float64 [2]
    rgb: tuple[int, int, int]
    half_size: float = ZONE_HALF_SIZE

    def contains(self, point: np.ndarray) -> bool:
        return bool(np.all(np.abs(point - self.center) <= self.half_size))


@dataclass(frozen=True)
class Belt:
    """A conveyor belt: the horizontal band `y_min <= y <= y_max` moves objects on it by `velocity` per step."""

    y_min: float
    y_max: float
    velocity: np.ndarray  # float64 [2]

    def carries(self, positions: np.ndarray) -> np.ndarray:  # [N, 2] -> bool [N]
        return (positions[:, 1] >= self.y_min) & (positions[:, 1] <= self.y_max)


class World:
    """The bodies of one episode and their dynamics (float64 inside; see the module docstring for one step)."""

    def __init__(
        self,
        colors: list[str],
        positions: np.ndarray,  # [N, 2] object centres
        effector: np.ndarray,  # [2]
        zones: tuple[Zone, ...] = (),
        belt: Belt | None = None,
        slip_acceleration: float = DEFAULT_SLIP_ACCELERATION,
    ) -> None:
        self.colors = list(colors)
        self.positions = np.array(positions, dtype=np.float64).reshape(len(self.colors), 2)
        self.effector = np.array(effector, dtype=np.float64)
        self.velocity = np.zeros(2)  # the effector's last displacement
        self.gripper_closed = False
        self.held = -1  # index of the held object, -1 for none
        self.held_offset = np.zeros(2)  # object centre - effector while held
        self.slipped = 0  # how many times a held object slipped out
        self.zones = zones
        self.belt = belt
        self.slip_acceleration = float(slip_acceleration)

    def step(self, target: np.ndarray, gripper_command: float) -> None:
        """Advance one control step toward the position `target` [2]; `gripper_command > 0` closes the gripper."""
        displacement = np.clip(target, -1.0, 1.0) - self.effector
        distance = float(np.hypot(*displacement))
        if distance > MAX_SPEED:
            displacement *= MAX_SPEED / distance
        jerk = float(np.hypot(*(displacement - self.velocity)))
        self.effector = self.effector + displacement
        self.velocity = displacement

        if self.held >= 0:
            if jerk > self.slip_acceleration:
                self.held = -1  # slips out and stays where it was
                self.slipped += 1
            else:
                self.positions[self.held] = self.effector + self.held_offset

        close = gripper_command > 0
        if close and not self.gripper_closed:
            self.gripper_closed = True
            distances = np.hypot(*(self.positions - self.effector).T)
            candidates = np.flatnonzero(distances <= GRASP_RADIUS)
            if len(candidates):
                self.held = int(candidates[np.argmin(distances[candidates])])
                self.held_offset = self.positions[self.held] - self.effector
        elif not close and self.gripper_closed:
            self.gripper_closed = False
            self.held = -1

        if self.belt is not None:
            moving = self.belt.carries(self.positions)
            if self.held >= 0:
                moving[self.held] = False
            self.positions[moving] += self.belt.velocity

    def predicted_position(self, index: int, steps: int) -> np.ndarray:
        """Where object `index` will be after `steps` more steps if nobody touches it (the belt moves it)."""
        position = self.positions[index]
        if self.belt is None or self.held == index or not self.belt.carries(position[None])[0]:
            return position.copy()
        return position + steps * self.belt.velocity

    def state(self) -> np.ndarray:
        """The robot's proprioception: float32 `[x, y, gripper]` (gripper 0 open, 1 closed)."""
        return np.array([*self.effector, float(self.gripper_closed)], dtype=np.float32)


def _tint(rgb: tuple[int, int, int], background: tuple[int, int, int], amount: float) -> np.ndarray:
    return (np.array(background) * (1 - amount) + np.array(rgb) * amount).astype(np.uint8)


class Renderer:
    """Draws a `World` seen from above into uint8 `[size, size, 3]` frames: the whole table (the base camera), or with
    `wrist_zoom` a window of the table magnified that many times and centred on the effector (the wrist camera; beyond
    the table's edge it shows `OFF_TABLE_COLOR`).

    The static layer (table, belt, zones) depends only on the zones and the belt, so it is drawn once per layout
    (`set_layout`); `draw` copies it and paints the objects, then the effector on top (a held object lies under it).
    """

    def __init__(self, size: int, wrist_zoom: float | None = None) -> None:
        if size < 8:
            raise ValueError(f"image size must be >= 8 pixels, got {size}")
        if wrist_zoom is not None and not wrist_zoom >= 1.0:
            raise ValueError(f"wrist_zoom must be >= 1, got {wrist_zoom}")
        self.size = size
        self.wrist_zoom = wrist_zoom
        self.scale = size * (wrist_zoom or 1.0) / 2.0  # pixels per world unit
        self.table_size = round(2.0 * self.scale)  # side of the whole table in pixels (= size without zoom)
        self._static = np.empty((self.table_size, self.table_size, 3), np.uint8)
        self._pixels = np.arange(size, dtype=np.float64)  # pixel indices of a frame, rows and columns alike
        self._layout: tuple[tuple[Zone, ...], Belt | None] | None = None
        self.set_layout((), None)

    def set_layout(self, zones: tuple[Zone, ...], belt: Belt | None) -> None:
        """Redraw the static layer for these zones and belt (skipped when they are the ones already drawn)."""
        if self._layout is not None and self._layout[0] is zones and self._layout[1] is belt:
            return
        self._layout = (zones, belt)
        image = self._static
        image[:] = TABLE_COLOR
        if belt is not None:
            top, bottom = self._row(belt.y_min), self._row(belt.y_max)
            image[top:bottom + 1] = BELT_COLOR
            image[top], image[bottom] = BELT_EDGE_COLOR, BELT_EDGE_COLOR
        border = max(1, round(0.025 * self.scale))
        for zone in zones:
            r0, r1 = self._row(zone.center[1] - zone.half_size), self._row(zone.center[1] + zone.half_size) + 1
            c0, c1 = self._row(zone.center[0] - zone.half_size), self._row(zone.center[0] + zone.half_size) + 1
            image[r0:r1, c0:c1] = zone.rgb
            image[r0 + border:r1 - border, c0 + border:c1 - border] = _tint(zone.rgb, TABLE_COLOR, 0.3)

    def _row(self, coordinate: float) -> int:
        """The table pixel holding world coordinate `coordinate` (rows and columns alike), clipped to the table."""
        return int(np.clip(np.floor((coordinate + 1.0) * self.scale), 0, self.table_size - 1))

    def _disc(self, image: np.ndarray, center: np.ndarray, outer: float, inner: float, rgb: tuple[int, int, int],
              origin: tuple[int, int]) -> None:
        """Paint the frame pixels whose centres lie at distance in [inner, outer] (world units) from `center`; the
        frame's top-left pixel is table pixel `origin` (row, column)."""
        cx = (float(center[0]) + 1.0) * self.scale - 0.5 - origin[1]  # frame pixel coordinates of the centre
        cy = (float(center[1]) + 1.0) * self.scale - 0.5 - origin[0]
        radius = outer * self.scale
        c0, c1 = max(math.floor(cx - radius), 0), min(math.ceil(cx + radius) + 1, self.size)
        r0, r1 = max(math.floor(cy - radius), 0), min(math.ceil(cy + radius) + 1, self.size)
        if c0 >= c1 or r0 >= r1:
            return
        dx = self._pixels[c0:c1] - cx  # [w]
        dy = self._pixels[r0:r1, None] - cy  # [h, 1]
        squared = dx * dx + dy * dy  # [h, w]
        mask = squared <= radius * radius
        if inner > 0:
            mask &= squared >= (inner * self.scale) ** 2
        image[r0:r1, c0:c1][mask] = rgb

    def draw(self, world: World) -> np.ndarray:
        """The camera frame, uint8 `[size, size, 3]` (a new array)."""
        self.set_layout(world.zones, world.belt)
        if self.wrist_zoom is not None:
            top, left = (np.floor((world.effector[::-1] + 1.0) * self.scale) - self.size // 2).astype(int)
            image = np.empty((self.size, self.size, 3), np.uint8)
            image[:] = OFF_TABLE_COLOR
            r0, r1 = max(top, 0), min(top + self.size, self.table_size)
            c0, c1 = max(left, 0), min(left + self.size, self.table_size)
            if r0 < r1 and c0 < c1:
                image[r0 - top:r1 - top, c0 - left:c1 - left] = self._static[r0:r1, c0:c1]
            origin = (int(top), int(left))
        else:
            image, origin = self._static.copy(), (0, 0)
        order = [i for i in range(len(world.colors)) if i != world.held] + ([world.held] if world.held >= 0 else [])
        for index in order:
            self._disc(image, world.positions[index], OBJECT_RADIUS, 0.0, PALETTE[world.colors[index]], origin)
        if world.gripper_closed:
            self._disc(image, world.effector, CLOSED_EFFECTOR_RADIUS, 0.0, EFFECTOR_COLOR, origin)
        else:
            self._disc(image, world.effector, GRASP_RADIUS, EFFECTOR_INNER_RADIUS, EFFECTOR_COLOR, origin)
        return image
