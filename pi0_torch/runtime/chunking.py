"""Executing action chunks at the control rate while the next chunk is computed, and how chunks are stitched.

Time is counted in control steps. A chunk's *anchor* is the step its index 0 is meant for: the step of the
observation it was computed from (the first chunk of an episode: the step it arrived, since the robot waited for it).
The robot observes every `s` steps (`replan_steps`, the execution horizon); a chunk takes `d` steps to arrive (the
inference delay). Execution modes, as compared by Black, Galliker and Levine (2025):

- `sync`: the robot stands still (repeats its last action) while a chunk is computed, then executes `s` of its actions.
- `naive`: the robot keeps executing the current chunk; the new one takes over on arrival, at the index of the
  arrival step (its first `d` actions are already in the past). Consecutive chunks may disagree: the robot jumps.
- `ensemble`: ACT's temporal ensembling: every step executes the weighted mean of the actions that all arrived
  chunks hold for that step, weights `exp(-m * k)` with `k = 0` for the oldest chunk (ACT's `m = 0.01`).
- `rtc` / `rtc-trained`: as `naive`, but each request carries the executing chunk, `s` and `d`, so the new chunk
  continues it (`pi0_torch.inference.rtc`: guidance, or conditioning for a model trained with `--rtc-max-delay`).

[`ChunkSchedule`] says when to observe and when chunks arrive in simulated time (deterministic evaluation,
`pi0_torch.runtime.rollout`); [`ChunkStitcher`] picks each step's action; [`RealTimeExecutor`] does the same on a
robot, with inference in a background thread and `d` estimated from measured latency.

```python
>>> import numpy as np
>>> schedule = ChunkSchedule("naive", horizon=8, replan_steps=4, inference_delay=2)
>>> [schedule.observes(t) for t in range(8)]  # the first chunk at 0, then every 4 steps after it arrived
[True, False, False, False, False, False, True, False]
>>> stitcher = ChunkStitcher("naive", replan_steps=4)
>>> stitcher.add(np.arange(8.0)[:, None], anchor=2)  # the first chunk: computed at step 0, executed from step 2
>>> [float(stitcher.action(t, hold=np.zeros(1))[0]) for t in range(2, 8)]
[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
>>> stitcher.add(100 + np.arange(8.0)[:, None], anchor=6)  # observed at step 6, arrives at 8: index 2 first
>>> [float(stitcher.action(t, hold=np.zeros(1))[0]) for t in range(8, 11)]
[102.0, 103.0, 104.0]

```
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

EXECUTION_MODES = ("sync", "naive", "ensemble", "rtc", "rtc-trained")
RTC_METHODS = {"rtc": "guidance", "rtc-trained": "conditioning"}  # execution mode -> the model's rtc_method
ENSEMBLE_DECAY = 0.01  # ACT's m


def check_execution(mode: str, horizon: int, replan_steps: int, inference_delay: int) -> None:
    """Refuse a mode / horizon / `s` / `d` combination that cannot run, naming the values."""
    if mode not in EXECUTION_MODES:
        raise ValueError(f"execution must be one of {EXECUTION_MODES}, got {mode!r}")
    if not 1 <= replan_steps <= horizon:
        raise ValueError(f"replan_steps must lie in [1, action horizon = {horizon}], got {replan_steps}")
    if inference_delay < 0:
        raise ValueError(f"inference_delay must be >= 0 control steps, got {inference_delay}")
    if mode != "sync" and replan_steps + inference_delay > horizon:
        raise ValueError(
            f"replan_steps + inference_delay ({replan_steps} + {inference_delay}) must not exceed the action horizon "
            f"({horizon}) with execution {mode!r}: the executing chunk must last until the next one arrives"
        )


@dataclass(frozen=True)
class ChunkSchedule:
    """When a robot with a fixed inference delay observes, and where each chunk is anchored (simulated time)."""

    mode: str
    horizon: int
    replan_steps: int  # s
    inference_delay: int  # d

    def __post_init__(self) -> None:
        check_execution(self.mode, self.horizon, self.replan_steps, self.inference_delay)

    def observes(self, step: int) -> bool:
        """Whether an inference starts at `step` (an episode starts at step 0)."""
        s, d = self.replan_steps, self.inference_delay
        if self.mode == "sync":
            return step % (s + d) == 0
        return step == 0 or (step > d and (step - d) % s == 0)

    def anchor(self, step: int) -> int:
        """The anchor of the chunk observed at `step`."""
        return step + self.inference_delay if self.mode == "sync" or step == 0 else step

    def arrival(self, step: int) -> int:
        """The step from which the chunk observed at `step` is available."""
        return step + self.inference_delay


class ChunkStitcher:
    """The action a robot executes at each step, from the chunks that have arrived so far (robot units)."""

    def __init__(self, mode: str, replan_steps: int, ensemble_decay: float = ENSEMBLE_DECAY) -> None:
        if mode not in EXECUTION_MODES:
            raise ValueError(f"execution must be one of {EXECUTION_MODES}, got {mode!r}")
        self.mode, self.replan_steps, self.ensemble_decay = mode, replan_steps, ensemble_decay
        self.chunks: list[tuple[int, np.ndarray]] = []  # (anchor, [H, A]) in arrival order

    def add(self, chunk: np.ndarray, anchor: int) -> None:
        self.chunks.append((anchor, np.asarray(chunk, np.float32)))
        if self.mode != "ensemble":
            del self.chunks[:-1]  # only the newest is ever read

    @property
    def latest(self) -> tuple[int, np.ndarray] | None:
        """(anchor, chunk) of the newest chunk, what a real-time chunking request continues."""
        return self.chunks[-1] if self.chunks else None

    def action(self, step: int, hold: np.ndarray) -> np.ndarray:
        """The action for `step`; `hold` (standing still) where no arrived chunk covers it."""
        if self.mode == "ensemble":
            covering = [chunk[step - anchor] for anchor, chunk in self.chunks if 0 <= step - anchor < len(chunk)]
            if not covering:
                return hold
            weights = np.exp(-self.ensemble_decay * np.arange(len(covering)))
            return (np.tensordot(weights, np.stack(covering), axes=1) / weights.sum()).astype(np.float32)
        if not self.chunks:
            return hold
        anchor, chunk = self.chunks[-1]
        index = step - anchor
        limit = self.replan_steps if self.mode == "sync" else len(chunk)
        return chunk[index] if 0 <= index < limit else hold


def continuation_fields(mode: str, stitcher: ChunkStitcher, step: int, inference_delay: int) -> dict[str, Any]:
    """The request fields of [`PI0Policy`] that make a chunk observed at `step` continue the executing one
    (`rtc` / `rtc-trained` only; empty for other modes and for an episode's first chunk)."""
    latest = stitcher.latest
    if mode not in RTC_METHODS or latest is None:
        return {}
    anchor, chunk = latest
    executed = step - anchor
    delay = max(0, min(inference_delay, len(chunk) - executed))
    return {"previous_actions": chunk, "execution_horizon": executed, "inference_delay": delay,
            "rtc_method": RTC_METHODS[mode]}


def second_differences(actions: np.ndarray) -> np.ndarray:
    """`|a[t+1] - 2 a[t] + a[t-1]|` (L2 over action dims) for t = 1 .. T-2 of executed actions `[T, A]`."""
    if len(actions) < 3:
        return np.zeros(0, np.float32)
    return np.linalg.norm(actions[2:] - 2 * actions[1:-1] + actions[:-2], axis=-1)


class RealTimeExecutor:
    """Runs a chunk policy beside a robot's control loop: call [`step`] once per control period with the newest
    observation and send the action it returns.

    Inference runs in a background thread. `d` is estimated as `ceil(latency * control_hz)` from the slowest of
    the last few chunks (the first chunk's latency counts too), clipped so the executing chunk lasts. In `sync`
    mode `step` blocks until the chunk is there (the robot waits).

    Args:
        infer: one observation (default layout, plus the real-time chunking fields) -> `{"actions": [H, A]}`, e.g.
            `PI0Policy.infer` or a websocket client's `infer`.
        mode: an execution mode of [`EXECUTION_MODES`].
        horizon: the policy's action horizon.
        replan_steps: `s`, steps executed from a chunk before the next observation.
        control_hz: the robot's control rate.
        hold: the action that keeps the robot still before the first chunk.
    """

    def __init__(
        self,
        infer: Callable[[Mapping[str, Any]], Mapping[str, Any]],
        mode: str,
        horizon: int,
        replan_steps: int,
        control_hz: float,
        hold: np.ndarray,
    ) -> None:
        check_execution(mode, horizon, replan_steps, 0)
        self.infer, self.mode, self.horizon, self.replan_steps = infer, mode, horizon, replan_steps
        self.period = 1.0 / control_hz
        self.stitcher = ChunkStitcher(mode, replan_steps)
        self.hold = np.asarray(hold, np.float32)
        self.step_index = 0
        self.latencies: list[float] = []
        self._pending: threading.Thread | None = None
        self._result: tuple[int, np.ndarray] | None = None
        self._error: BaseException | None = None
        self._next_observation = 0

    @property
    def estimated_delay(self) -> int:
        """`d` in control steps from the slowest recent chunk, at most what the executing chunk leaves."""
        if not self.latencies:
            return 0
        steps = math.ceil(max(self.latencies[-5:]) / self.period - 1e-9)
        return max(0, min(steps, self.horizon - self.replan_steps))

    def step(self, observation: Mapping[str, Any]) -> np.ndarray:
        """The action for this control step."""
        self._collect(block=self.mode == "sync" or not self.stitcher.chunks)
        if self._pending is None and self.step_index >= self._next_observation:
            self._start(observation)
            self._collect(block=self.mode == "sync" or not self.stitcher.chunks)
        action = self.stitcher.action(self.step_index, self.hold)
        self.hold = action
        self.step_index += 1
        return action

    def _start(self, observation: Mapping[str, Any]) -> None:
        step = self.step_index
        request = {**observation, **continuation_fields(self.mode, self.stitcher, step, self.estimated_delay)}

        def work() -> None:
            start = time.monotonic()
            try:
                chunk = np.asarray(self.infer(request)["actions"], np.float32)
            except BaseException as error:  # re-raised in the control loop
                self._error = error
                return
            self.latencies.append(time.monotonic() - start)
            self._result = (step, chunk)

        self._pending = threading.Thread(target=work, daemon=True)
        self._pending.start()

    def _collect(self, block: bool) -> None:
        if self._pending is None or (not block and self._pending.is_alive()):
            return
        self._pending.join()
        self._pending = None
        if self._error is not None:
            raise self._error
        observed, chunk = self._result
        first = not self.stitcher.chunks
        # sync and an episode's first chunk start from index 0 now; an asynchronous one is anchored where observed
        anchor = self.step_index if first or self.mode == "sync" else observed
        self.stitcher.add(chunk, anchor)
        self._next_observation = anchor + self.replan_steps
