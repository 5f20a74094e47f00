"""Public simulated benchmarks behind `pi0-torch eval --env NAMESPACE/NAME`: Meta-World, ALOHA sim and LIBERO.

| `--env` | what | extra | observation layout |
|---|---|---|---|
| `metaworld/<task>-v3`, e.g. `metaworld/reach-v3` | one Meta-World task (MT1), its scripted expert | `metaworld` | `default` |
| `aloha/AlohaTransferCube-v0`, `aloha/AlohaInsertion-v0` | gym-aloha's tasks as openpi's `examples/aloha_sim` runs them | `aloha` | `aloha` |
| `libero/libero_spatial` (`_object`, `_goal`, `_10`, `_90`) | a whole LIBERO suite as openpi's `examples/libero` runs it | `libero` | `libero` |

Each adapter module defines `make_env(name, **kwargs) -> gymnasium.Env`. Its observations are what openpi's example
client sends to a policy server (so the same [`ObservationFormat`] preset maps them, locally and over `serve`), and
its unwrapped env carries the benchmark's protocol:

- `replan_steps`: actions executed per chunk in the published evaluations (None: the policy's choice);
- `hold_action(observation)`: the action that keeps the robot still before the first chunk arrives;
- `task_name`: the task of the current episode (results are reported per task);
- `control_hz`: for videos.

A suite of several tasks maps episode seeds onto its tasks and their initial states (see the module).
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from pi0_torch.envs.rendering import check_mujoco_rendering
from pi0_torch.utils.extras import require_extra


@dataclasses.dataclass(frozen=True)
class Benchmark:
    module: str  # defines make_env(name, **kwargs)
    extra: str
    obs_format: str  # the ObservationFormat preset of its observations (π0 / π0.5 cameras)
    fast_obs_format: str  # the same for π0-FAST's cameras


BENCHMARKS: dict[str, Benchmark] = {
    "metaworld": Benchmark("pi0_torch.envs.metaworld", "metaworld", "default", "default"),
    "aloha": Benchmark("pi0_torch.envs.aloha", "aloha", "aloha", "aloha_fast"),
    "libero": Benchmark("pi0_torch.envs.libero", "libero", "libero", "libero_fast"),
}


def benchmark_of(env_id: str) -> Benchmark | None:
    """The benchmark an env id belongs to (by its namespace), or None."""
    return BENCHMARKS.get(env_id.split("/", 1)[0]) if "/" in env_id else None


def make_benchmark_env(env_id: str, **kwargs: Any) -> Any:
    """Make the env `NAMESPACE/NAME` of a benchmark, after checking its extra and that MuJoCo can render."""
    benchmark = benchmark_of(env_id)
    if benchmark is None:
        raise ValueError(f"{env_id!r} is not a benchmark env; expected one of {', '.join(f'{n}/...' for n in BENCHMARKS)}")
    require_extra(benchmark.extra, f"the environment {env_id}")
    check_mujoco_rendering()
    return importlib.import_module(benchmark.module).make_env(env_id.split("/", 1)[1], **kwargs)
