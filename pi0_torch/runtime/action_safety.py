"""The last check before actions leave a policy: a chunk with NaN or inf is never handed back.

[`PI0Policy`] (and its π0-FAST sibling) checks every chunk after sampling and unnormalizing. A chunk that is not
finite is withheld: the observations whose chunks were fine get their replies, the others an
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


def withhold_unsafe(chunks: Sequence[np.ndarray], cause: Callable[[int], str], infer_ms: float) -> list[dict[str, Any]]:
    """The replies of a batch: each chunk (robot units) as `{"actions": float32, "policy_timing": ...}`. A chunk with
    NaN or inf is withheld: its outcome is an `UnsafeActionsError` naming the observation, the count and `cause(index)`,
    and the batch raises `UnsafeActionsError` (the first such message, with every outcome)."""
    outcomes: list[dict[str, Any] | UnsafeActionsError] = []
    for index, chunk in enumerate(chunks):
        robot = np.asarray(chunk, dtype=np.float32)
        bad = non_finite_count(robot)
        if bad:
            where = f"observation {index} of a batch of {len(chunks)}: " if len(chunks) > 1 else ""
            outcomes.append(UnsafeActionsError(f"{where}the action chunk holds {bad} NaN/inf values and was withheld; "
                                               f"cause: {cause(index)}"))
        else:
            outcomes.append({"actions": robot, "policy_timing": {"infer_ms": infer_ms, "batch_size": len(chunks)}})
    unsafe = [outcome for outcome in outcomes if isinstance(outcome, UnsafeActionsError)]
    if unsafe:
        raise UnsafeActionsError(str(unsafe[0]), outcomes)
    return outcomes  # type: ignore[return-value]
