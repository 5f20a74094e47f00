"""Closed-loop tabletop environments (gymnasium) and their scripted experts.

Importing this package registers the ids `pi0_torch/Reach-v0`, `pi0_torch/PickPlace-v0` and `pi0_torch/Conveyor-v0`
(`gymnasium.make("pi0_torch.envs:pi0_torch/Reach-v0")` imports it for you). See `docs/envs.md`. Needs
`pip install 'pi0-torch[envs]'`.

>>> import gymnasium
>>> env = gymnasium.make("pi0_torch/Conveyor-v0", image_size=64)
>>> env.spec.max_episode_steps, env.unwrapped.control_hz
(100, 10)
"""

from __future__ import annotations

from pi0_torch.utils.extras import require_extra

require_extra("envs", __name__)
import gymnasium

from pi0_torch.envs.experts import ScriptedExpert, has_scripted_expert, make_expert
from pi0_torch.envs.tasks import ConveyorEnv, PickPlaceEnv, ReachEnv, TabletopEnv

ENV_CLASSES: dict[str, type[TabletopEnv]] = {
    "pi0_torch/Reach-v0": ReachEnv,
    "pi0_torch/PickPlace-v0": PickPlaceEnv,
    "pi0_torch/Conveyor-v0": ConveyorEnv,
}
ENV_IDS: tuple[str, ...] = tuple(ENV_CLASSES)

for _env_id, _env_class in ENV_CLASSES.items():
    if _env_id not in gymnasium.registry:
        gymnasium.register(
            id=_env_id,
            entry_point=f"{_env_class.__module__}:{_env_class.__name__}",
            max_episode_steps=_env_class.default_max_episode_steps,
        )

__all__ = [
    "ENV_CLASSES", "ENV_IDS", "ConveyorEnv", "PickPlaceEnv", "ReachEnv", "ScriptedExpert", "TabletopEnv",
    "has_scripted_expert", "make_expert",
]
