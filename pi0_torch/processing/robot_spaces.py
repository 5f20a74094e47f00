"""Value conversions between a robot's own units and the space a checkpoint was trained in.

Some openpi checkpoints were trained on values that differ from what the robot reports. openpi's ALOHA policies
(`policies/aloha_policy.py`, `adapt_to_pi=True` by default in its ALOHA data configs) move ALOHA's state and
actions into the space of PI's own runtime, which the base models were trained in: two joints of each arm turn
the other way, and the gripper is an angle rather than ALOHA's linearised opening.

[`PI0Processor`] applies a conversion when it has one (`value_conversion="aloha"`, saved with the processor):
- the state is converted before it is normalized (delta actions are taken against the converted state);
- training actions are converted before the delta and the normalization;
- predicted actions are converted back after unnormalization and the delta inverse.

```python
>>> import numpy as np
>>> aloha = get_conversion("aloha")
>>> state = np.zeros(14, np.float32); state[[6, 13]] = 1.0   # both grippers fully open (ALOHA's [0, 1] opening)
>>> aloha.state_to_model(state)[[1, 6]].round(4)               # a joint sign flip, the gripper as PI's angle
array([-0.    ,  0.9457], dtype=float32)
>>> actions = np.zeros((2, 14), np.float32)
>>> np.allclose(aloha.actions_to_model(aloha.actions_to_robot(actions)), actions, atol=1e-6)
True

```
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

Convert = Callable[[np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class ValueConversion:
    """Maps robot values into a checkpoint's training space and its actions back. Each function takes and returns
    arrays `[..., dim]` (float32 out)."""

    name: str
    dim: int  # the state and action length it applies to
    state_to_model: Convert
    actions_to_model: Convert  # training targets, robot -> model space
    actions_to_robot: Convert  # predictions, model -> robot space


# --- ALOHA (two arms of 6 joints + 1 gripper) --------------------------------------------------------------------

_ALOHA_JOINT_SIGNS = np.array([1, -1, -1, 1, 1, 1, 1] * 2, dtype=np.float64)
_ALOHA_GRIPPERS = [6, 13]
_ALOHA_GRIPPER_OPENING = (0.01844, 0.05800)  # metres, ALOHA's PUPPET_GRIPPER_POSITION_CLOSE / _OPEN
_ALOHA_GRIPPER_JOINT = (-0.6213, 1.4910)  # radians, ALOHA's PUPPET_GRIPPER_JOINT_CLOSE / _OPEN
_PI_GRIPPER_ANGLE = (0.5476, 1.6296)  # radians, the range of PI's gripper angle
_GRIPPER_ARM, _GRIPPER_HORN = 0.036, 0.022  # metres, the Interbotix gripper linkage


def _to_unit(x: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return (x - bounds[0]) / (bounds[1] - bounds[0])


def _from_unit(x: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return x * (bounds[1] - bounds[0]) + bounds[0]


def _aloha_state_to_pi(state: np.ndarray) -> np.ndarray:
    """Flip joint signs; undo ALOHA's gripper linearisation (opening in metres -> the linkage's horn angle)."""
    converted = np.asarray(state, np.float64) * _ALOHA_JOINT_SIGNS
    opening = _from_unit(converted[..., _ALOHA_GRIPPERS], _ALOHA_GRIPPER_OPENING)
    cosine = (_GRIPPER_HORN**2 + opening**2 - _GRIPPER_ARM**2) / (2 * _GRIPPER_HORN * opening)
    converted[..., _ALOHA_GRIPPERS] = _to_unit(np.arcsin(np.clip(cosine, -1.0, 1.0)), _PI_GRIPPER_ANGLE)
    return converted.astype(np.float32)


def _aloha_actions_to_pi(actions: np.ndarray) -> np.ndarray:
    """Flip joint signs; ALOHA's normalised gripper joint -> PI's gripper angle (inverse of `_aloha_actions_from_pi`)."""
    converted = np.asarray(actions, np.float64) * _ALOHA_JOINT_SIGNS
    converted[..., _ALOHA_GRIPPERS] = _from_unit(converted[..., _ALOHA_GRIPPERS], _ALOHA_GRIPPER_JOINT) - _PI_GRIPPER_ANGLE[0]
    return converted.astype(np.float32)


def _aloha_actions_from_pi(actions: np.ndarray) -> np.ndarray:
    """Flip joint signs; PI's gripper angle -> ALOHA's normalised gripper joint."""
    converted = np.asarray(actions, np.float64) * _ALOHA_JOINT_SIGNS
    converted[..., _ALOHA_GRIPPERS] = _to_unit(converted[..., _ALOHA_GRIPPERS] + _PI_GRIPPER_ANGLE[0], _ALOHA_GRIPPER_JOINT)
    return converted.astype(np.float32)


CONVERSIONS: dict[str, ValueConversion] = {
    "aloha": ValueConversion("aloha", 14, _aloha_state_to_pi, _aloha_actions_to_pi, _aloha_actions_from_pi),
}


def get_conversion(name: str) -> ValueConversion:
    """The conversion called `name` (`"aloha"`: openpi's `adapt_to_pi`)."""
    if name not in CONVERSIONS:
        raise ValueError(f"unknown value conversion {name!r}; expected one of {', '.join(CONVERSIONS)}")
    return CONVERSIONS[name]
