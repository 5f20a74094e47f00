"""The last check before actions leave a policy: a chunk with NaN or inf, or beyond the policy's bounds, is never
handed back.

[`PI0Policy`] (and its π0-FAST sibling, and `ExportedPolicy`) checks every chunk after sampling and unnormalizing.
The bounds: ±`MAX_NORMALIZED_ACTION` in the model's normalized space (as the state's, where the policy has norm
stats), and the policy's `max_abs_action` in the robot's units where its `policy_settings.json` sets one. A chunk
that is not finite or breaks a bound is withheld: the observations whose chunks were fine get their replies, the others an
[`UnsafeActionsError`] whose one-line message names the cause the policy found (the model's weights, the norm stats,
real-time chunking guidance, or the model itself). The policy server sends that line to the client instead of
actions; `pi0-torch eval` stops and keeps the episodes finished so far.

No torch here, so that the server can name the error without importing the model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np


class UnsafeActionsError(RuntimeError):
    """Some chunks of a batch were not finite and were withheld.

    `outcomes` has one entry per observation of the batch: its reply (a dict), or the `UnsafeActionsError` of its
    chunk (its message names the observation, the count of bad values and the cause).
    """

    def __init__(self, message: str, outcomes: Sequence[dict[str, Any] | UnsafeActionsError] = ()) -> None:
        super().__init__(message)
        self.outcomes = list(outcomes)


def non_finite_count(values: np.ndarray) -> int:
    """How many values are NaN or ±inf."""
    return int(np.count_nonzero(~np.isfinite(values)))


# |action| in the model's normalized space (z-scores, or the q01..q99 span mapped to [-1, 1]): a trained policy's
# actions lie within a few units of 0; a thousand is a broken model or statistics (the state's bound, likewise)
MAX_NORMALIZED_ACTION = 1_000.0


def withhold_unsafe(chunks: Sequence[np.ndarray], cause: Callable[[int], str], infer_ms: float,
                    max_abs_action: float | None = None,
                    normalized: Sequence[np.ndarray] | None = None) -> list[dict[str, Any]]:
    """The replies of a batch: each chunk (robot units) as `{"actions": float32, "policy_timing": ...}`. A chunk with
    NaN or inf is withheld: its outcome is an `UnsafeActionsError` naming the observation, the count and `cause(index)`,
    and the batch raises `UnsafeActionsError` (the first such message, with every outcome). So is a finite chunk with
    a value beyond `max_abs_action` (robot units), or whose `normalized` chunk (the model's actions on the robot's
    dims, before unnormalizing) leaves ±`MAX_NORMALIZED_ACTION`."""
    outcomes: list[dict[str, Any] | UnsafeActionsError] = []
    for index, chunk in enumerate(chunks):
        robot = np.asarray(chunk, dtype=np.float32)
        bad = non_finite_count(robot)
        where = f"observation {index} of a batch of {len(chunks)}: " if len(chunks) > 1 else ""
        model_space = None if normalized is None else np.asarray(normalized[index], dtype=np.float32)
        beyond = None
        if model_space is not None and not non_finite_count(model_space):  # (else the NaN's cause is named)
            beyond = _beyond(model_space, MAX_NORMALIZED_ACTION, "in the model's normalized space, where a trained "
                             "policy's actions lie within a few units of 0 (a broken model or action norm stats)")
        if beyond is None and not bad:
            beyond = _beyond(robot, max_abs_action, "robot units (the policy's max_abs_action, policy_settings.json)")
        if beyond is not None:
            outcomes.append(UnsafeActionsError(f"{where}the action chunk was withheld: {beyond}"))
        elif bad:
            outcomes.append(UnsafeActionsError(f"{where}the action chunk holds {bad} NaN/inf values and was withheld; "
                                               f"cause: {cause(index)}"))
        else:
            outcomes.append({"actions": robot, "policy_timing": {"infer_ms": infer_ms, "batch_size": len(chunks)}})
    unsafe = [outcome for outcome in outcomes if isinstance(outcome, UnsafeActionsError)]
    if unsafe:
        raise UnsafeActionsError(str(unsafe[0]), outcomes)
    return outcomes  # type: ignore[return-value]


def _beyond(values: np.ndarray, bound: float | None, what: str) -> str | None:
    """Where `values` `[horizon, dims]` leave ±`bound` (None: they do not, or there is no bound), in one line."""
    if bound is None or not values.size:
        return None
    magnitude = np.abs(values)
    if magnitude.max() <= bound:
        return None
    step, dim = (int(i) for i in np.unravel_index(int(magnitude.argmax()), values.shape))
    count = int(np.count_nonzero(magnitude > bound))
    return f"{count} values beyond ±{bound:g} {what}; the largest {values[step, dim]:.6g} at step {step}, dim {dim}"
