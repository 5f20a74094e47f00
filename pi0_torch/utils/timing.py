"""Wall time of calls on a device, for the benchmarks: each call with the device's queued work finished before and
after, and several calls timed in turn so that a busy stretch of a shared machine falls on all of them alike."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import torch


def seconds(fn: Callable[[], object], device: torch.device) -> float:
    """Wall time of one call of `fn`, with the device's queued work finished before and after."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def time_alternating(fns: Sequence[Callable[[], object]], device: torch.device, repeats: int) -> list[list[float]]:
    """Seconds of each of `fns` over `repeats` rounds, run in turn (order reversed every other round) so that a
    slower or faster stretch of a shared machine falls on all of them alike."""
    for fn in fns:
        fn()
    durations: list[list[float]] = [[] for _ in fns]
    for round_ in range(repeats):
        order = range(len(fns)) if round_ % 2 == 0 else reversed(range(len(fns)))
        for index in order:
            durations[index].append(seconds(fns[index], device))
    return durations
