"""Closed-loop evaluation: a policy acting in gymnasium environments, success rates with 95% intervals.

`pi0-torch eval --policy DIR|ws://HOST:PORT --env ID --episodes N` runs N episodes (seeds S, S+1, ...) in groups of
`--num-envs` environments stepped in lockstep, so a local policy computes one batched chunk for the whole group.
Inference delay is simulated in control steps ([`ChunkSchedule`]): the numbers do not depend on the machine's
speed, and every chunk's noise comes from `noise_seed` (episode seed, chunk number), so the same seeds give the same
episodes locally, through `pi0-torch serve`, and with any `--num-envs`.

Nothing is lost when the policy fails part way (a server that drops the connection, sends no reply within
`--timeout`, or replies without actions): the episodes finished so far are summarized, written to `eval.json` (marked
`"complete": false` with the reason) and the error is one line ([`EvaluationStopped`]). Each episode is recorded as it
ends (`episodes.jsonl`, `pi0_torch.runtime.eval_record`), SIGTERM stops like Ctrl-C, and `--resume` continues an
evaluation that was stopped or killed. The output folder is checked
before the first episode ([`pi0_torch.utils.files.check_output_dir`]: absent, empty, or with `--overwrite` a folder
pi0-torch wrote) and is never the evaluated policy's folder.

```python
>>> [round(bound, 3) for bound in wilson_interval(45, 50)]  # 95% interval of a 90% success rate over 50 episodes
[0.786, 0.957]

```
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import importlib
import importlib.util
import json
import logging
import math
import shutil
import signal
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pi0_torch.runtime.chunking import (
    EXECUTION_MODES,
    ChunkSchedule,
    ChunkStitcher,
    continuation_fields,
    second_differences,
)
from pi0_torch.cli import json_object
from pi0_torch.shipped_policy import policy_location
from pi0_torch.runtime.observation_formats import ObservationFormat
from pi0_torch.utils.extras import require_extra
from pi0_torch.runtime.policy_settings import SETTINGS_FILE
from pi0_torch.runtime.eval_record import RECORD_FILE, EvalRecord, partial_folder, stopped_record
from pi0_torch.runtime.perturbation import Perturbation, parse_perturbation
from pi0_torch.utils.charts import bar_chart
from pi0_torch.utils.files import check_output_dir, check_separate, check_writable, resumable_output_dir
from pi0_torch.utils.hardware import usable_device
from pi0_torch.utils.threads import add_threads_argument, set_threads
from pi0_torch.utils.validation import MAX_SEED, check_finite, check_float, check_int, first_line

logger = logging.getLogger(__name__)

SUCCESS_PLOT_FILE = "success.png"  # beside eval.json: `success_chart`
DEFAULT_TIMEOUT_S = 600.0  # per reply of a policy server (a CPU-served full-size π0 batch takes minutes)
MAX_EPISODES = 1_000_000
MAX_NUM_ENVS = 1_024
MAX_INFERENCE_DELAY = 10_000  # control steps
MAX_EPISODE_STEPS = 10_000_000

MUJOCO_NAMESPACES = ("gym_aloha",)  # third-party env packages that render with MuJoCo (checked before they import it)
# Third-party simulators: the keyword arguments that make them emit images, and their observation layout.
KNOWN_ENVS: dict[str, tuple[dict[str, Any], str]] = {
    "gym_pusht/PushT-v0": ({"obs_type": "pixels_agent_pos"}, "pusht"),
    "gym_aloha/AlohaInsertion-v0": ({"obs_type": "pixels_agent_pos"}, "gym_aloha"),
    "gym_aloha/AlohaTransferCube-v0": ({"obs_type": "pixels_agent_pos"}, "gym_aloha"),
}


class ChunkPolicy(Protocol):
    """What rollouts need from a policy: its shape and a batch of observations -> action chunks (robot units).
    A policy may also define `start_group(envs, seeds, done)`, called when a group of episodes starts (`done`: the
    group's live list of finished flags; observations come for the unfinished envs in order)."""

    metadata: Mapping[str, Any]

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]: ...


class ScriptedPolicy:
    """Reference policies that act one step at a time: `"expert"` (the env's scripted expert, reading the true
    state: `pi0_torch.envs.make_expert`) or `"random"` (uniform actions from the action space, seeded per episode)."""

    def __init__(self, kind: str) -> None:
        if kind not in ("expert", "random"):
            raise ValueError(f"unknown scripted policy {kind!r}; expected 'expert' or 'random'")
        self.kind = kind
        self.metadata: dict[str, Any] = {"policy": kind, "action_horizon": 1}
        self.recommended_replan_steps: int | None = None  # (every policy here: see `LocalPolicy`)
        self.envs: Sequence[Any] = []
        self.done: Sequence[bool] = []
        self.actors: list[Any] = []

    def start_group(self, envs: Sequence[Any], seeds: Sequence[int], done: Sequence[bool]) -> None:
        self.envs, self.done = envs, done
        if self.kind == "expert":
            from pi0_torch.envs import make_expert

            self.actors = [make_expert(env) for env in envs]
            for actor, seed in zip(self.actors, seeds):
                actor.reset(seed)
        else:
            self.actors = [np.random.default_rng(seed) for seed in seeds]

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        chunks = []
        for i in [i for i, finished in enumerate(self.done) if not finished]:
            env, actor = self.envs[i], self.actors[i]
            if self.kind == "expert":
                action = actor.act(env.unwrapped)
            else:
                space = env.action_space
                action = actor.uniform(space.low, space.high).astype(np.float32)
            chunks.append(np.asarray(action, np.float32)[None])
        return chunks


class LocalPolicy:
    """A [`PI0Policy`] running in this process; a group of observations is one batched model call. `source`: the
    folder it was loaded from (evaluation outputs are never written into it)."""

    def __init__(self, policy: Any, source: str | Path | None = None) -> None:
        self.policy = policy
        self.metadata = policy.metadata
        self.source = source
        # actions to execute per chunk that the policy's folder recommends (`policy_settings.json`), or None
        self.recommended_replan_steps: int | None = self.metadata.get("replan_steps")

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        prepared = [self.policy.prepare(observation) for observation in observations]
        return [result["actions"] for result in self.policy.infer_prepared(prepared)]


class RemotePolicy:
    """A `pi0-torch serve` (or any openpi-protocol server) reached over websockets: one connection per environment,
    a group's requests sent concurrently so that the server can batch them.

    Everything the server sends is checked: its metadata (an `action_horizon`), and each reply (float `actions`
    `[horizon, action dims]`, finite). A closed connection, a reply later than `timeout` seconds, or a malformed
    reply raises a one-line `ConnectionError` / `ValueError` naming the server."""

    def __init__(self, url: str, connections: int, api_key: str | None = None, timeout: float = DEFAULT_TIMEOUT_S) -> None:
        require_extra("serve", f"a ws:// policy ({url})")
        from websockets.exceptions import WebSocketException
        from websockets.sync.client import connect

        from pi0_torch.runtime.serving import pack_message, unpack_message

        self.url = url
        self.timeout = check_float("--timeout", timeout, minimum=0.0, exclusive_minimum=True)
        self._pack, self._unpack = pack_message, unpack_message
        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        # (each connection entered as the context manager websockets asks for: a plain `connect()` warns since
        # websockets 17.1, which is to return a reconnecting iterator there instead; `close` leaves them)
        self._connections = contextlib.ExitStack()
        try:
            try:
                self.sockets = [self._connections.enter_context(connect(url, max_size=None, additional_headers=headers,
                                                                        open_timeout=timeout))
                                for _ in range(connections)]
                metadata = [self._unpack(socket.recv(timeout)) for socket in self.sockets][0]
            except (OSError, WebSocketException) as error:  # refused, unreachable, a rejected handshake, no metadata
                raise ConnectionError(f"cannot reach the policy server at {url}: {first_line(error) or type(error).__name__}") from None
            self.metadata = _checked_metadata(metadata, url)
        except BaseException:
            self._connections.close()  # (the connections already open)
            raise
        self.recommended_replan_steps: int | None = self.metadata.get("replan_steps")  # (the served policy's)
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=connections)

    def _ask(self, socket: Any, observation: Mapping[str, Any]) -> np.ndarray:
        from websockets.exceptions import ConnectionClosed, WebSocketException

        try:
            socket.send(self._pack(dict(observation)))
            reply = socket.recv(self.timeout)
        except TimeoutError:
            raise ConnectionError(f"the policy server at {self.url} sent no reply within {self.timeout:g} s "
                                  "(--timeout)") from None
        except ConnectionClosed as error:
            closed = error.rcvd or error.sent
            why = f"code {closed.code}{', ' + closed.reason if closed.reason else ''}" if closed else "no close frame"
            raise ConnectionError(f"the policy server at {self.url} closed the connection ({why})") from None
        except (OSError, WebSocketException) as error:
            raise ConnectionError(f"the policy server at {self.url} failed: {first_line(error)}") from None
        if isinstance(reply, str):  # the server's one-line error
            raise ValueError(f"policy server: {reply}")
        return self._actions(reply)

    def _actions(self, reply: bytes) -> np.ndarray:
        """The `actions` of a reply, checked: a finite float array `[horizon, action dims]`."""
        message = self._unpack(reply)
        if not isinstance(message, Mapping) or "actions" not in message:
            keys = sorted(map(str, message)) if isinstance(message, Mapping) else type(message).__name__
            raise ValueError(f"policy server at {self.url}: a reply without 'actions' (got {keys})")
        actions = np.asarray(message["actions"])
        dims = self.metadata.get("action_dim")
        if actions.dtype.kind not in "iuf" or actions.ndim != 2 or not actions.shape[0] or (
                dims is not None and actions.shape[1] != dims):
            raise ValueError(f"policy server at {self.url}: reply 'actions' must be numbers [horizon, "
                             f"{dims if dims is not None else 'action dims'}], got shape {list(actions.shape)} "
                             f"dtype {actions.dtype}")
        check_finite(f"policy server at {self.url}: reply 'actions'", actions)
        return actions.astype(np.float32)

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        futures = [self.pool.submit(self._ask, socket, obs) for socket, obs in zip(self.sockets, observations)]
        return [future.result() for future in futures]

    def close(self) -> None:
        self._connections.close()
        self.pool.shutdown()


def _checked_metadata(metadata: Any, url: str) -> dict[str, Any]:
    """The metadata a server sent on connect, with the fields evaluation reads checked."""
    from pi0_torch.models.configuration_pi0 import MAX_ACTION_DIM, MAX_ACTION_HORIZON

    where = f"policy server at {url}: metadata"
    if not isinstance(metadata, Mapping):
        raise ValueError(f"{where} must be a dict, got {type(metadata).__name__}")
    if "action_horizon" not in metadata:
        raise ValueError(f"{where} lacks 'action_horizon' (got {sorted(map(str, metadata))})")
    checked = dict(metadata)
    checked["action_horizon"] = check_int(f"{where} action_horizon", metadata["action_horizon"], 1, MAX_ACTION_HORIZON)
    for name in ("action_dim", "state_dim"):
        if metadata.get(name) is not None:
            checked[name] = check_int(f"{where} {name}", metadata[name], 1, MAX_ACTION_DIM)
    if metadata.get("replan_steps") is not None:
        checked["replan_steps"] = check_int(f"{where} replan_steps", metadata["replan_steps"], 1, checked["action_horizon"])
    cameras = metadata.get("camera_names")
    if cameras is not None and (not isinstance(cameras, list) or not all(isinstance(c, str) for c in cameras)):
        raise ValueError(f"{where} camera_names must be a list of strings, got {cameras!r:.80}")
    return checked


def wilson_interval(successes: int, trials: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95% by default)."""
    if trials == 0:
        return (0.0, 1.0)
    rate = successes / trials
    centre = (rate + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(rate * (1 - rate) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return (max(0.0, centre - half), min(1.0, centre + half))


def make_env(env_id: str, **kwargs: Any) -> Any:
    """`gymnasium.make(env_id)` after importing the id's namespace package (`pi0_torch/...`, `gym_pusht/...`);
    an id whose package is not installed, or an unknown id, is a `ValueError` naming the package or the known ids."""
    require_extra("envs", f"the environment {env_id}")
    import gymnasium

    from pi0_torch.envs.benchmarks import benchmark_of, make_benchmark_env

    render_mode = kwargs.get("render_mode")
    if render_mode is not None and not isinstance(render_mode, str):  # (gymnasium.make: an AttributeError)
        raise ValueError(f"--env-kwargs: render_mode must be a string such as 'rgb_array', got {render_mode!r:.40}")

    if benchmark_of(env_id) is not None:  # metaworld/..., aloha/..., libero/...
        return make_benchmark_env(env_id, **kwargs)
    namespace = env_id.split("/")[0] if "/" in env_id else None
    if namespace == "pi0_torch":
        importlib.import_module("pi0_torch.envs")
    elif namespace is not None and env_id not in gymnasium.registry:
        if namespace in MUJOCO_NAMESPACES and importlib.util.find_spec(namespace) is not None:
            from pi0_torch.envs.rendering import check_mujoco_rendering

            check_mujoco_rendering()  # (one line naming what to install, before MuJoCo fails to load its GL library)
        try:
            importlib.import_module(namespace)
        except ModuleNotFoundError as error:
            if error.name != namespace:
                raise
            raise ValueError(f"the environment {env_id} needs the package {namespace}, which is not installed: "
                             f"pip install {namespace.replace('_', '-')}") from None
    if env_id not in gymnasium.registry:
        importlib.import_module("pi0_torch.envs")
        known = (sorted(i for i in gymnasium.registry if i.startswith("pi0_torch/")) + sorted(KNOWN_ENVS)
                 + ["metaworld/<task>-v3", "aloha/AlohaTransferCube-v0", "libero/<suite>"])
        raise ValueError(f"unknown environment id {env_id!r}; known: {', '.join(known)} (a third-party id needs its "
                         "package installed, e.g. pip install gym-pusht)")
    try:
        return gymnasium.make(env_id, **{**KNOWN_ENVS.get(env_id, ({}, ""))[0], **kwargs})
    except TypeError as error:  # an argument the env does not take (--env-kwargs)
        raise ValueError(f"{env_id} cannot be made with the settings {sorted(kwargs)}: {first_line(error)} "
                         "(--env-kwargs)") from None


@dataclass
class EvalSettings:
    """One evaluation; fields mirror `pi0-torch eval`'s options."""

    env: str
    episodes: int = 50
    num_envs: int = 1
    seed: int = 1_000_000  # held out: demonstrations use seeds from 0
    replan_steps: int | None = None  # default: the horizon (sync) or horizon - delay
    execution: str = "sync"
    inference_delay: int = 0
    max_steps: int | None = None
    obs_format: str | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    prompt: str | None = None
    video_episodes: int = 0
    output_dir: str | None = None
    overwrite: bool = False  # replace a non-empty output_dir that pi0-torch wrote
    resume: bool = False  # continue the stopped evaluation recorded for output_dir (`pi0_torch.runtime.eval_record`)
    perturb: Perturbation | None = None  # each episode's camera shift and colour jitter (`pi0_torch.runtime.perturbation`)
    progress: bool = False


@dataclass
class EpisodeResult:
    seed: int
    success: bool
    steps: int
    boundary_jerk: list[float]  # per chunk switch
    interior_jerk: list[float]
    task: str = ""  # the env's `task_name` (benchmark suites of several tasks)


@dataclass
class EvalResult:
    """What `eval.json` holds (`episodes_detail` per episode)."""

    env: str
    episodes: int
    seed: int
    execution: str
    inference_delay: int
    replan_steps: int
    success_rate: float
    success_ci95: tuple[float, float]
    mean_steps: float | None  # of the successful episodes
    latency_ms: float  # per policy call (one group of environments)
    boundary_jerk: float | None
    interior_jerk: float | None
    policy: dict[str, Any]
    episodes_detail: list[dict[str, Any]]
    complete: bool = True  # False: the evaluation stopped early; these are the episodes finished before
    stopped_by: str | None = None  # why it stopped (one line)
    per_task: dict[str, dict[str, Any]] = field(default_factory=dict)  # task -> episodes, success_rate, success_ci95
    perturb: dict[str, Any] | None = None  # `--perturb`'s shift (pixels) and jitter, where the frames were perturbed

    def task_lines(self) -> list[str]:
        """One line per task, when the episodes ran more than one task."""
        return [f"  {task}: success {100 * t['success_rate']:.1f}% [{100 * t['success_ci95'][0]:.1f}, "
                f"{100 * t['success_ci95'][1]:.1f}] over {t['episodes']} episodes"
                for task, t in self.per_task.items()] if len(self.per_task) > 1 else []

    def summary(self) -> str:
        low, high = self.success_ci95
        steps = f"{self.mean_steps:.1f}" if self.mean_steps is not None else "-"
        jerk = "".join(f", jerk {where} {value:.4f}" for where, value in
                       (("at chunk boundaries", self.boundary_jerk), ("inside chunks", self.interior_jerk)) if value is not None)
        perturbed = "" if self.perturb is None else f" perturbed (shift {self.perturb['shift']} px, jitter {self.perturb['jitter']:g})"
        return (f"{self.env}{perturbed} {self.execution} d={self.inference_delay} s={self.replan_steps}: success "
                f"{100 * self.success_rate:.1f}% [{100 * low:.1f}, {100 * high:.1f}] over {self.episodes} episodes, "
                f"{steps} steps per success, policy {self.latency_ms:.0f} ms per call{jerk}"
                + ("" if self.complete else f" (incomplete: stopped by {self.stopped_by})"))


class EvaluationStopped(RuntimeError):
    """An evaluation that stopped before its last episode (the policy or an env failed, or Ctrl-C); the message
    says why and where the finished episodes were written. `result` summarizes them."""

    def __init__(self, message: str, result: EvalResult) -> None:
        super().__init__(message)
        self.result = result


class _GroupStopped(Exception):
    """A group of episodes interrupted by `cause`; `results` / `frames`: its episodes finished before."""

    def __init__(self, results: list[EpisodeResult], frames: dict[int, list[np.ndarray]], cause: BaseException) -> None:
        super().__init__(first_line(cause))
        self.results, self.frames, self.cause = results, frames, cause


def _hold_action(env: Any, observation: Mapping[str, Any], raw: Mapping[str, Any], action_dim: int) -> np.ndarray:
    """Standing still while the first chunk is computed (an inference delay): what the env says holds it
    (`hold_action(raw observation)`: the benchmark adapters), else the robot's state as a position target (envs
    whose actions are absolute targets of their state, as this package's envs and gym_pusht)."""
    if hasattr(env.unwrapped, "hold_action"):
        return np.asarray(env.unwrapped.hold_action(raw), np.float32).reshape(action_dim)
    state = np.asarray(observation["state"], np.float32)
    if state.shape != (action_dim,):
        raise ValueError(f"holding still needs actions shaped like the state; the env's state has {state.shape[0]} "
                         f"dims and its actions {action_dim}: use --execution naive/rtc with --inference-delay 0")
    return state


def _check_match(policy: ChunkPolicy, env: Any, observation: Mapping[str, Any], env_id: str) -> None:
    """Refuse a policy whose action or state dims, or cameras, differ from the env's (`env_id`, as given), naming both."""
    meta = policy.metadata
    action_dim = int(np.prod(env.action_space.shape))
    if meta.get("action_dim") not in (None, action_dim):
        raise ValueError(f"action dims differ: the policy acts in {meta['action_dim']} dims, the env {env_id} takes "
                         f"{action_dim}")
    state_dim = np.asarray(observation["state"]).shape[0]
    if meta.get("state_dim") not in (None, state_dim):
        raise ValueError(f"state dims differ: the policy expects {meta['state_dim']}, the env {env_id} gives {state_dim}")
    cameras, policy_cameras = sorted(observation["images"]), list(meta.get("camera_names", []))
    if policy_cameras and not set(cameras) <= set(policy_cameras):
        from pi0_torch.envs.tasks import TabletopEnv

        way_out = "map them with --obs-format"
        if isinstance(env.unwrapped, TabletopEnv):  # its wrist camera can be switched off
            way_out += """, or drop the wrist camera with --env-kwargs '{"wrist_camera": false}'"""
        raise ValueError(f"cameras differ: the env {env_id} gives {cameras}, the policy knows {policy_cameras} ({way_out})")
    unseen = [camera for camera in policy_cameras if camera not in cameras]
    if unseen:  # (once per evaluation) a policy trained with them acts blind on their side
        logger.warning("the env gives no frames for the policy's cameras %s: they are fed as absent (masked) in every "
                       "request; a policy trained with them may act worse than it can", unseen)


def _noise_seed(episode_seed: int, chunk: int) -> int:
    return int(np.random.SeedSequence([episode_seed, chunk]).generate_state(2, np.uint64)[0] >> np.uint64(1))


def default_obs_format(env_id: str, policy_metadata: Mapping[str, Any]) -> str:
    """The observation layout of an env's observations: a benchmark's preset (π0-FAST's cameras for a π0-FAST
    policy), a known simulator's, else `default`."""
    from pi0_torch.envs.benchmarks import benchmark_of

    benchmark = benchmark_of(env_id)
    if benchmark is not None:
        return benchmark.fast_obs_format if policy_metadata.get("model_type") == "pi0_fast" else benchmark.obs_format
    return KNOWN_ENVS.get(env_id, ({}, "default"))[1]


def check_eval_settings(settings: EvalSettings, horizon: int) -> int:
    """Refuse settings no evaluation can use (`ValueError` naming the `pi0-torch eval` option); returns the replan
    steps (default: the horizon in `sync`, else horizon - delay)."""
    check_int("--episodes", settings.episodes, 1, MAX_EPISODES)
    check_int("--num-envs", settings.num_envs, 1, MAX_NUM_ENVS)
    check_int("--seed", settings.seed, 0, MAX_SEED - settings.episodes)
    if settings.execution not in EXECUTION_MODES:
        raise ValueError(f"--execution must be one of {EXECUTION_MODES}, got {settings.execution!r}")
    delay = check_int("--inference-delay", settings.inference_delay, 0, MAX_INFERENCE_DELAY)
    if settings.replan_steps is None:
        replan = horizon if settings.execution == "sync" else max(1, horizon - delay)
    else:
        replan = check_int("--replan-steps", settings.replan_steps, 1, horizon)
    if settings.max_steps is not None:
        check_int("--max-steps", settings.max_steps, 1, MAX_EPISODE_STEPS)
    check_int("--video", settings.video_episodes, 0, settings.episodes)
    if not isinstance(settings.env_kwargs, Mapping):
        raise ValueError(f"--env-kwargs must be a JSON object, got {type(settings.env_kwargs).__name__}")
    return replan


def check_eval_output(settings: EvalSettings, policy_source: str | Path | None) -> Path | None:
    """Refuse an output folder evaluation may not write, before any episode runs: see
    [`pi0_torch.utils.files.check_output_dir`]; never the evaluated policy's folder (nor one inside or around it);
    and one whose file system refuses a file there (read-only, full: `files.check_writable`), which used to surface
    only after every episode had run. A stopped evaluation's record there is never dropped unasked: `--resume`
    continues it (returned: its record file), `--overwrite` starts over."""
    if not settings.output_dir:
        if settings.resume:
            raise ValueError("--resume needs the --output-dir of the stopped evaluation")
        return None
    output = Path(settings.output_dir).expanduser().absolute()
    if policy_source is not None and Path(policy_source).is_dir():
        check_separate(policy_source, output)
    stopped = stopped_record(output)
    if settings.resume and stopped is None:
        raise ValueError(f"--resume: {output} holds no stopped evaluation (no {RECORD_FILE} of an incomplete one)")
    if stopped is not None and not (settings.resume or settings.overwrite):
        raise ValueError(f"{output}: a stopped evaluation's record is at {stopped}; --resume continues it, "
                         "--overwrite starts over")
    check_output_dir(output, settings.overwrite or settings.resume)
    check_writable(output, "--output-dir")
    return stopped if settings.resume else None


def evaluate(policy: ChunkPolicy, settings: EvalSettings) -> EvalResult:
    """Run `settings.episodes` closed-loop episodes and summarize them (see the module docstring).

    When the policy or an env fails part way, the finished episodes are summarized (and written to `output_dir`)
    and [`EvaluationStopped`] says why; when none had finished, the failure itself is raised."""
    horizon = int(policy.metadata["action_horizon"])
    replan = check_eval_settings(settings, horizon)
    resumed = check_eval_output(settings, getattr(policy, "source", None))
    mode, delay = settings.execution, settings.inference_delay
    schedule = ChunkSchedule(mode, horizon, replan, delay)
    if mode == "rtc-trained" and delay > policy.metadata.get("real_time_chunking", {}).get("rtc_max_delay", 0):
        raise ValueError(f"--execution rtc-trained needs a policy trained with --rtc-max-delay >= {delay}")
    kwargs = dict(settings.env_kwargs)
    if settings.max_steps is not None:
        kwargs["max_episode_steps"] = settings.max_steps
    if settings.video_episodes:
        require_extra("envs", "recording videos", modules=("av",))  # before the episodes run, not after
        kwargs.setdefault("render_mode", "rgb_array")
    envs = _make_envs(settings.env, min(settings.num_envs, settings.episodes), kwargs)
    max_seed = getattr(envs[0].unwrapped, "max_seed", None)  # (gym-aloha seeds numpy's RandomState: below 2^32)
    if max_seed is not None and settings.seed + settings.episodes - 1 > max_seed:
        for env in envs:
            env.close()
        raise ValueError(f"--seed must be an integer in [0, {max_seed - settings.episodes + 1}] for {settings.episodes} "
                         f"episodes of {settings.env} (its seeds stay below {max_seed + 1}), got {settings.seed}")
    try:
        if not settings.output_dir:
            result, stopped = _evaluate_in(policy, settings, replan, schedule, envs, None, None)
        else:
            output = Path(settings.output_dir).expanduser().absolute()
            if settings.overwrite and not settings.resume:
                shutil.rmtree(partial_folder(output), ignore_errors=True)  # (--overwrite: a stopped record starts over)
            try:
                # (published when the block ends without an exception)
                with resumable_output_dir(output, settings.overwrite or settings.resume) as folder:
                    record = EvalRecord.start(folder, _identity(policy, settings, replan), resumed)
                    try:
                        result, stopped = _evaluate_in(policy, settings, replan, schedule, envs, folder, record)
                    finally:
                        record.close()
            except _NothingFinished as nothing:  # (no record worth keeping: the next run starts afresh)
                shutil.rmtree(partial_folder(output), ignore_errors=True)
                raise nothing.cause from None
    finally:
        for env in envs:
            env.close()
    if stopped is not None:
        written = (f"; eval.json and {RECORD_FILE} in {settings.output_dir} hold them (--resume continues)"
                   if settings.output_dir else "")
        raise EvaluationStopped(f"{result.stopped_by} (stopped after {result.episodes} finished episodes of "
                                f"{settings.episodes}{written})", result) from stopped
    return result


def _make_envs(env_id: str, count: int, kwargs: Mapping[str, Any]) -> list[Any]:
    """`count` envs of `env_id`; beyond two, refused (`ValueError` naming `--num-envs`) when they would not fit in
    the memory this machine has available, as the second one measured (a Meta-World env holds about 84 MB)."""
    import psutil

    process = psutil.Process()
    envs = [make_env(env_id, **kwargs)]
    if count > 2:
        before = process.memory_info().rss
        envs.append(make_env(env_id, **kwargs))
        each = max(process.memory_info().rss - before, 2**20)  # (at least 1 MiB: RSS misses what reused freed memory)
        needed, available = each * (count - 2), psutil.virtual_memory().available
        if needed > 0.8 * available:
            for env in envs:
                env.close()
            raise ValueError(f"--num-envs {count}: each {env_id} env holds about {each / 2**20:.0f} MB here, "
                             f"{each * count / 2**30:.1f} GB for {count}; this machine has {available / 2**30:.1f} GB "
                             "available: use fewer")
    envs += [make_env(env_id, **kwargs) for _ in range(count - len(envs))]
    return envs


class Terminated(KeyboardInterrupt):
    """SIGTERM during `pi0-torch eval`: it stops the episodes as Ctrl-C does (the finished ones are kept)."""


def _terminate(signum: int, frame: Any) -> None:
    raise Terminated(f"signal {signal.Signals(signum).name}")


class _NothingFinished(Exception):
    """An evaluation that stopped before any episode finished (`cause`: why)."""

    def __init__(self, cause: BaseException) -> None:
        super().__init__(first_line(cause))
        self.cause = cause


def _identity(policy: ChunkPolicy, settings: EvalSettings, replan: int) -> dict[str, Any]:
    """What an evaluation's episodes depend on (the first line of its record): a resumed one must agree."""
    return {"env": settings.env, "policy": str(getattr(policy, "source", None) or policy.metadata.get("policy", "")),
            "episodes": settings.episodes, "seed": settings.seed, "execution": settings.execution,
            "inference_delay": settings.inference_delay, "replan_steps": replan, "max_steps": settings.max_steps,
            "obs_format": settings.obs_format, "env_kwargs": settings.env_kwargs, "prompt": settings.prompt,
            "perturb": None if settings.perturb is None else asdict(settings.perturb)}


def _evaluate_in(policy: ChunkPolicy, settings: EvalSettings, replan: int, schedule: ChunkSchedule, envs: list[Any],
                 folder: Path | None, record: EvalRecord | None) -> tuple[EvalResult, BaseException | None]:
    """The episodes of `evaluate` not in `record` yet (each recorded as it ends), then the summary, written into
    `folder` (published as the output folder when this returns); and what stopped the episodes early (None: they
    all ran). A failure before any episode finished raises (`_NothingFinished` around it where there is a record)."""
    mode, delay = settings.execution, settings.inference_delay
    obs_format = ObservationFormat.from_preset(settings.obs_format or default_obs_format(settings.env, policy.metadata))
    action_dim = int(np.prod(envs[0].action_space.shape))

    perturbations: dict[int, Callable[[Mapping[str, Any]], dict[str, Any]]] = {}  # episode seed -> its perturbation

    def observe(raw: Mapping[str, Any], seed: int) -> dict[str, Any]:
        observation = obs_format.to_default(raw)
        if observation["prompt"] is None and settings.prompt is not None:
            observation["prompt"] = settings.prompt
        if settings.perturb is not None:  # (`--perturb`: the episode's camera shift and light, from its seed)
            if seed not in perturbations:
                perturbations[seed] = settings.perturb.for_episode(seed)
            observation["images"] = perturbations[seed](observation["images"])
        return observation

    first_raw = envs[0].reset(seed=settings.seed)[0]
    first_observation = observe(first_raw, settings.seed)
    _check_match(policy, envs[0], first_observation, settings.env)
    if delay:
        _hold_action(envs[0], first_observation, first_raw, action_dim)
    results = [EpisodeResult(**episode) for episode in record.episodes] if record is not None else []
    latencies: list[float] = list(record.calls_ms) if record is not None else []
    recorded = {result.seed for result in results}
    remaining = [settings.seed + i for i in range(settings.episodes) if settings.seed + i not in recorded]
    if results:
        print(f"resuming: {len(results)} of {settings.episodes} episodes recorded, {len(remaining)} to run")
    progress = None
    if settings.progress:
        from pi0_torch.utils.progress import tqdm

        progress = tqdm(total=settings.episodes, initial=len(results), desc=f"eval {settings.env}", unit="episode")
    frames: dict[int, list[np.ndarray]] = {}  # episode seed -> its rendered frames
    stopped: BaseException | None = None
    try:
        for first in range(0, len(remaining), len(envs)):
            seeds = remaining[first : first + len(envs)]
            try:
                wave, wave_frames = _run_group(policy, envs[: len(seeds)], seeds, schedule, observe, action_dim,
                                               latencies, record=max(0, settings.video_episodes - len(frames)),
                                               log=record)
            except _GroupStopped as interrupted:
                wave, wave_frames, stopped = interrupted.results, interrupted.frames, interrupted.cause
            results += wave
            frames.update(wave_frames)
            if progress is not None:
                progress.update(len(wave))
                if results:
                    progress.set_postfix(success=f"{np.mean([r.success for r in results]):.0%}")
            if stopped is not None:
                break
    finally:
        if progress is not None:
            progress.close()
    if stopped is not None and not results:
        raise _NothingFinished(stopped) if folder is not None else stopped
    results.sort(key=lambda r: r.seed)
    successes = sum(r.success for r in results)
    boundary = [j for r in results for j in r.boundary_jerk]
    interior = [j for r in results for j in r.interior_jerk]
    result = EvalResult(
        env=settings.env, episodes=len(results), seed=settings.seed, execution=mode, inference_delay=delay,
        replan_steps=replan, success_rate=successes / len(results),
        success_ci95=wilson_interval(successes, len(results)),
        mean_steps=float(np.mean([r.steps for r in results if r.success])) if successes else None,
        latency_ms=float(np.mean(latencies)) if latencies else 0.0,
        boundary_jerk=float(np.mean(boundary)) if boundary else None,
        interior_jerk=float(np.mean(interior)) if interior else None,
        policy={k: v for k, v in policy.metadata.items() if isinstance(v, (str, int, float, list))},
        episodes_detail=[{"seed": r.seed, "success": r.success, "steps": r.steps, **({"task": r.task} if r.task else {})}
                         for r in results],
        per_task=_per_task(results),
        perturb=None if settings.perturb is None else asdict(settings.perturb),
        complete=stopped is None,
        stopped_by=None if stopped is None else f"{type(stopped).__name__}: {first_line(stopped)}",
    )
    if folder is not None:
        try:
            write_outputs(result, frames, folder, fps=_control_hz(envs[0]))
        except OSError as error:  # (the disk filled up, or the folder went read-only, while the episodes ran)
            raise EvaluationStopped(f"the episodes ran, but {settings.output_dir} could not be written "
                                    f"({first_line(error)}); the summary above is all there is, and --resume "
                                    f"writes it from the record ({record.path})", result) from error
    return result, stopped


def _per_task(results: Sequence[EpisodeResult]) -> dict[str, dict[str, Any]]:
    """Success per task (in order of first appearance), for episodes that name their task."""
    tasks: dict[str, list[bool]] = {}
    for r in results:
        if r.task:
            tasks.setdefault(r.task, []).append(r.success)
    return {task: {"episodes": len(outcomes), "success_rate": sum(outcomes) / len(outcomes),
                   "success_ci95": wilson_interval(sum(outcomes), len(outcomes))} for task, outcomes in tasks.items()}


def _control_hz(env: Any) -> int:
    return int(getattr(env.unwrapped, "control_hz", None) or env.metadata.get("render_fps") or 10)


def _run_group(
    policy: ChunkPolicy,
    envs: Sequence[Any],
    seeds: Sequence[int],
    schedule: ChunkSchedule,
    observe: Any,
    action_dim: int,
    latencies: list[float],
    record: int,
    log: EvalRecord | None = None,
) -> tuple[list[EpisodeResult], dict[int, list[np.ndarray]]]:
    """Episodes of one group of environments in lockstep (they share the chunk schedule): their results and the
    frames of the first `record` episodes (by seed); each episode and policy call is appended to `log` as it ends. A
    failure part way raises [`_GroupStopped`] holding the episodes finished before it."""
    done = [False] * len(envs)
    success = [False] * len(envs)
    executed: list[list[np.ndarray]] = [[] for _ in envs]
    switches: list[list[int]] = [[] for _ in envs]  # steps at which a new chunk took over
    frames: list[list[np.ndarray]] = [[] for _ in envs]

    def episode(i: int) -> EpisodeResult:
        motion = np.stack(executed[i])  # jerk of the motion dims where the env names them (not a gripper switch)
        dims = getattr(envs[i].unwrapped, "motion_action_dims", None)
        motion = motion if dims is None else motion[:, list(dims)]
        jerk = second_differences(motion)  # index t - 1 is the second difference centred at t
        at_switch = {t - 1 for t in switches[i] if 2 <= t <= len(executed[i]) - 1}  # centred on the last old action
        return EpisodeResult(
            seed=seeds[i], success=success[i], steps=len(executed[i]),
            task=str(getattr(envs[i].unwrapped, "task_name", "") or ""),  # (the env's episode is not reset yet)
            boundary_jerk=[float(jerk[t - 1]) for t in sorted(at_switch)],
            interior_jerk=[float(j) for t, j in enumerate(jerk, start=1) if t not in at_switch],
        )

    def finished(indices: Sequence[int]) -> tuple[list[EpisodeResult], dict[int, list[np.ndarray]]]:
        return [episode(i) for i in indices], {seeds[i]: frames[i] for i in indices if frames[i]}

    def ended(i: int) -> None:
        if log is not None:
            log.add_episode(episode(i))

    try:
        _step_group(policy, envs, seeds, schedule, observe, action_dim, latencies, record,
                    done, success, executed, switches, frames, ended, None if log is None else log.add_call)
    except (Exception, KeyboardInterrupt) as error:
        raise _GroupStopped(*finished([i for i in range(len(envs)) if done[i]]), error) from error
    return finished(range(len(envs)))


def _step_group(
    policy: ChunkPolicy,
    envs: Sequence[Any],
    seeds: Sequence[int],
    schedule: ChunkSchedule,
    observe: Any,
    action_dim: int,
    latencies: list[float],
    record: int,
    done: list[bool],
    success: list[bool],
    executed: list[list[np.ndarray]],
    switches: list[list[int]],
    frames: list[list[np.ndarray]],
    ended: Callable[[int], None],
    called: Callable[[float], None] | None,
) -> None:
    """The closed loop of [`_run_group`], filling its per-episode lists as it goes; `ended(i)` as episode `i` ends,
    `called(ms)` after each policy call."""
    raws = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds)]
    observations = [observe(raw, seed) for raw, seed in zip(raws, seeds)]
    holds = [_hold_action(env, o, raw, action_dim) if schedule.inference_delay else None
             for env, o, raw in zip(envs, observations, raws)]
    stitchers = [ChunkStitcher(schedule.mode, schedule.replan_steps) for _ in envs]
    pending: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in envs]  # (arrival, anchor, chunk)
    if hasattr(policy, "start_group"):
        policy.start_group(envs, seeds, done)
    for i in range(min(record, len(envs))):
        frames[i].append(envs[i].render())
    chunk_count, step = 0, 0

    def deliver(i: int) -> None:  # chunks that have arrived by this step take over
        while pending[i] and pending[i][0][0] <= step:
            _, anchor, chunk = pending[i].pop(0)
            stitchers[i].add(chunk, anchor)
            switches[i].append(step)

    while not all(done):
        for i in range(len(envs)):
            deliver(i)  # before observing: a request continues the newest chunk
        if schedule.observes(step):
            active = [i for i in range(len(envs)) if not done[i]]
            requests = [
                {**observations[i], **continuation_fields(schedule.mode, stitchers[i], step, schedule.inference_delay),
                 "noise_seed": _noise_seed(seeds[i], chunk_count)}
                for i in active
            ]
            start = time.monotonic()
            chunks = policy(requests)
            latencies.append((time.monotonic() - start) * 1000)
            if called is not None:
                called(latencies[-1])
            for i, chunk in zip(active, chunks):
                pending[i].append((schedule.arrival(step), schedule.anchor(step), chunk))
            chunk_count += 1
        for i, env in enumerate(envs):
            if done[i]:
                continue
            deliver(i)  # (with no delay, the chunk observed now)
            hold = executed[i][-1] if executed[i] else holds[i]
            action = stitchers[i].action(step, hold)
            executed[i].append(np.asarray(action, np.float32))
            raw, _, terminated, truncated, info = env.step(action)
            observations[i] = observe(raw, seeds[i])
            if i < record:
                frames[i].append(env.render())
            if terminated or truncated:
                done[i], success[i] = True, bool(info.get("is_success", False))
                ended(i)
        step += 1


def write_outputs(result: EvalResult, frames: Mapping[int, list[np.ndarray]], folder: Path, fps: int) -> None:
    """`eval.json` and `success.png`, and for recorded episodes (`frames`: seed -> frames) `rollout_<seed>.mp4` plus one
    `rollout_<seed>.png` strip, into `folder` (the output folder's partial folder, published when the evaluation
    ends: [`pi0_torch.utils.files.resumable_output_dir`])."""
    from PIL import Image

    from pi0_torch.data.video import encode_video

    (folder / "eval.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
    success_chart(result).save(folder / SUCCESS_PLOT_FILE)
    for seed, frames_of_episode in frames.items():
        name = f"rollout_{seed}"
        encode_video(folder / f"{name}.mp4", [_even(f) for f in frames_of_episode], fps, "libx264")
        picks = np.linspace(0, len(frames_of_episode) - 1, num=min(8, len(frames_of_episode))).round().astype(int)
        Image.fromarray(np.concatenate([frames_of_episode[i] for i in picks], axis=1)).save(folder / f"{name}.png")


def success_chart(result: EvalResult) -> Any:
    """`success.png`: the success rate with its 95% interval, per task where the episodes ran several, then overall."""
    percent = lambda rate, interval: (100 * rate, 100 * interval[0], 100 * interval[1])  # noqa: E731
    rows = [(f"{task} ({t['episodes']})", *percent(t["success_rate"], t["success_ci95"]))
            for task, t in result.per_task.items()] if len(result.per_task) > 1 else []
    rows.append((f"all ({result.episodes})" if rows else f"{result.env} ({result.episodes})",
                 *percent(result.success_rate, result.success_ci95)))
    perturbed = "" if result.perturb is None else f" (perturbed: shift {result.perturb['shift']} px, jitter {result.perturb['jitter']:g})"
    title = (f"{result.env}{perturbed}: success with 95% intervals, {result.episodes} episodes, {result.execution} "
             f"d={result.inference_delay} s={result.replan_steps}, policy {result.policy.get('policy', '?')}"
             + ("" if result.complete else " (incomplete)"))
    return bar_chart(rows, title, "%", upper=100.0)


def _even(frame: np.ndarray) -> np.ndarray:
    """H.264 with yuv420p needs even sides."""
    return frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]


def load_policy(spec: str, connections: int, api_key: str | None = None, device: str | None = None,
                num_steps: int | None = None, noise_scale: float | None = None, rtc_schedule: str = "exp",
                timeout: float = DEFAULT_TIMEOUT_S, threads: int | None = None) -> ChunkPolicy:
    """A folder (loaded here; `demo`: the demo policy shipped with the package; an exported folder of `pi0-torch
    export` runs its graph), `ws://host:port` (a running server; `timeout`: seconds to wait for each reply), or
    `expert` / `random` ([`ScriptedPolicy`]). `device`, `num_steps`, `noise_scale` and `rtc_schedule` apply to a
    folder (a server samples with its own settings); None takes the folder's recommended setting
    (`policy_settings.json`). `threads`: an exported folder's runtime threads (a model folder's are set by the
    caller, `set_threads`)."""
    if spec.startswith(("ws://", "wss://")):
        return RemotePolicy(spec, connections, api_key=api_key, timeout=timeout)
    if spec in ("expert", "random"):
        return ScriptedPolicy(spec)
    folder = policy_location(spec)
    from pi0_torch.deploy.policy import ExportedPolicy, is_export_folder

    if is_export_folder(folder):  # (`pi0-torch export`: its graph fixes the steps; no real-time chunking)
        if rtc_schedule != "exp":
            raise ValueError(f"--rtc-schedule: {folder} is an exported policy, which takes no real-time chunking")
        policy = ExportedPolicy.from_folder(folder, provider=device or "cpu", threads=threads, noise_scale=noise_scale)
        if num_steps is not None and num_steps != policy.num_steps:
            raise ValueError(f"--num-steps {num_steps}: {folder} is exported with {policy.num_steps} steps, fixed in its "
                             "graph (export it again with --num-steps)")
        return LocalPolicy(policy, source=folder)
    from pi0_torch.runtime.policy import PI0Policy

    return LocalPolicy(PI0Policy.from_pretrained(folder, device=device, num_steps=num_steps, noise_scale=noise_scale,
                                                   rtc_schedule=rtc_schedule), source=folder)


# ----------------------------------------------------------------------------------------------------------------
# pi0-torch eval
# ----------------------------------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `pi0-torch eval`."""
    parser.add_argument("--policy", required=True, help="a model folder, an exported folder (pi0-torch export), demo "
                        "(the policy shipped with the package), ws://HOST:PORT of pi0-torch serve, or 'expert' / 'random' (references: the env's scripted "
                        "expert, for pi0_torch/... and metaworld/... envs; uniform random actions)")
    parser.add_argument("--env", required=True, help="gymnasium id, e.g. pi0_torch/PickPlace-v0 or gym_pusht/PushT-v0, "
                        "or a public benchmark: metaworld/<task>-v3, aloha/AlohaTransferCube-v0, libero/libero_spatial "
                        "(docs/benchmarks.md)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--num-envs", type=int, default=8, help="environments stepped together (one batched call)")
    parser.add_argument("--seed", type=int, default=1_000_000, help="seed of the first episode (demos use 0, 1, ...)")
    parser.add_argument("--replan-steps", type=int, help="actions executed per chunk before the next observation "
                        "(default: a benchmark's published protocol, else the policy's recommended setting, else the "
                        "whole horizon; with an asynchronous execution, horizon - delay)")
    parser.add_argument("--execution", choices=EXECUTION_MODES, default="sync",
                        help="how chunks are stitched under inference delay (see docs/closed_loop.md)")
    parser.add_argument("--inference-delay", type=int, default=0, metavar="D",
                        help="simulated inference time in control steps")
    parser.add_argument("--max-steps", type=int, help="override the env's step limit")
    parser.add_argument("--obs-format", help="observation layout of the env (a pi0-torch serve preset or .json; "
                        "default: from the env id)")
    parser.add_argument("--env-kwargs", type=json_object, default={}, metavar="JSON",
                        help="a JSON object passed to gymnasium.make")
    parser.add_argument("--prompt", help="instruction for envs whose observations hold none")
    parser.add_argument("--num-steps", type=int, help="Euler steps per chunk (local policy)")
    parser.add_argument("--noise-scale", type=float, help="standard deviation of the noise each chunk's flow starts "
                        "from (local policy; default: the policy's recommended setting, else 1, openpi's sampler; the "
                        "demo policy recommends 0.1)")
    parser.add_argument("--rtc-schedule", default="exp", help="soft mask of --execution rtc over the previous "
                        "chunk: exp (default, the paper's), linear, ones or hard (local policy)")
    parser.add_argument("--device", help="local policy device (default: CUDA if available)")
    add_threads_argument(parser)
    parser.add_argument("--api-key", help="for a server started with --api-key")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="SECONDS",
                        help=f"seconds to wait for each reply of a policy server (default {DEFAULT_TIMEOUT_S:g})")
    parser.add_argument("--output-dir", help="write eval.json (and videos) here: a new or empty folder (see --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir that pi0-torch "
                        "wrote (a folder with files of others is never replaced)")
    parser.add_argument("--perturb", nargs="?", const="4,0.2", metavar="SHIFT[,JITTER]", help="see every episode through "
                        "a camera shifted by up to SHIFT pixels (non-wrist cameras) and colours jittered by factors in "
                        "[1-JITTER, 1+JITTER] (every camera), drawn from the episode's seed: what training-time "
                        "augmentation should make a policy robust to (bare flag: 4,0.2)")
    parser.add_argument("--resume", action="store_true", help="continue the evaluation into --output-dir that was "
                        f"stopped (Ctrl-C, SIGTERM, a failure) or killed, from its record ({RECORD_FILE}): the same "
                        "settings, the episodes it lacks")
    parser.add_argument("--video", nargs="?", type=int, const=1, default=0, metavar="N",
                        help="record the first N episodes (default 1) as mp4 and PNG strips (needs --output-dir)")


def run(args: argparse.Namespace) -> int:
    settings = EvalSettings(
        env=args.env, episodes=args.episodes, num_envs=args.num_envs, seed=args.seed,
        replan_steps=args.replan_steps, execution=args.execution, inference_delay=args.inference_delay,
        max_steps=args.max_steps, obs_format=args.obs_format, env_kwargs=args.env_kwargs, prompt=args.prompt,
        video_episodes=args.video, output_dir=args.output_dir, overwrite=args.overwrite, resume=args.resume,
        progress=True,
    )
    try:
        settings = replace(settings, perturb=None if args.perturb is None else parse_perturbation(args.perturb))
    except ValueError as error:
        print(f"pi0-torch eval: error: {error}", file=sys.stderr)
        return 2
    try:
        if settings.video_episodes and not settings.output_dir:
            raise ValueError("--video needs --output-dir")
        check_eval_output(settings, policy_location(args.policy))  # before the policy loads and the episodes run
        if args.device is not None:
            usable_device(args.device, "--device")
        if args.policy == "expert":
            from pi0_torch.envs import has_scripted_expert

            if not has_scripted_expert(settings.env):
                raise ValueError(f"--policy expert: {settings.env} has no scripted expert here (the pi0_torch/... "
                                 "tabletop envs and metaworld/... have one); --policy random gives a floor")
        probe = make_env(settings.env, **settings.env_kwargs)  # an unknown id or setting fails before the policy loads
        protocol_replan_steps = getattr(probe.unwrapped, "replan_steps", None)  # a benchmark's published protocol
        probe.close()
        policy = load_policy(args.policy, min(args.num_envs, args.episodes), args.api_key, args.device, args.num_steps,
                             args.noise_scale, args.rtc_schedule, args.timeout, args.threads)
        if isinstance(policy, LocalPolicy) and hasattr(policy.policy, "model"):  # (an exported policy chose its own)
            set_threads(args.threads, policy.policy.model)
        recommended = policy.recommended_replan_steps
        if settings.replan_steps is None and protocol_replan_steps is not None:
            settings = replace(settings, replan_steps=min(protocol_replan_steps, int(policy.metadata["action_horizon"])))
            print(f"replan steps {settings.replan_steps}: the benchmark's protocol for {settings.env} (--replan-steps to change)")
        elif settings.replan_steps is None and recommended is not None:
            horizon = int(policy.metadata["action_horizon"])
            if not 1 <= recommended <= horizon:  # (named as the file's setting: no --replan-steps was given)
                where = (f"{policy.source}/{SETTINGS_FILE}" if isinstance(policy, LocalPolicy)
                         else f"the policy server's {SETTINGS_FILE}")
                raise ValueError(f"replan_steps {recommended} in {where} is beyond the policy's {horizon}-action chunks; "
                                 "fix the file, or give --replan-steps")
            settings = replace(settings, replan_steps=recommended)
            print(f"replan steps {recommended}: the policy's recommended setting ({SETTINGS_FILE}; --replan-steps to change)")
        previous = signal.signal(signal.SIGTERM, _terminate)  # (SIGTERM stops the episodes as Ctrl-C does)
        try:
            result = evaluate(policy, settings)
        finally:
            signal.signal(signal.SIGTERM, previous)
            if isinstance(policy, RemotePolicy):
                policy.close()
    except KeyboardInterrupt as error:  # (outside an episode group: the record holds every finished episode)
        where = f"; --resume continues from {settings.output_dir}'s record" if settings.output_dir else ""
        print(f"pi0-torch eval: stopped ({type(error).__name__}){where}", file=sys.stderr)
        return 2
    except (ValueError, OSError, EvaluationStopped) as error:  # settings, files, the server: one line
        if isinstance(error, EvaluationStopped):  # the finished episodes' result first, whatever became of the files
            print("\n".join([error.result.summary(), *error.result.task_lines()]))
        print(f"pi0-torch eval: error: {first_line(error)}", file=sys.stderr)
        return 2
    print("\n".join([result.summary(), *result.task_lines()]))
    if settings.output_dir:
        print(f"wrote {Path(settings.output_dir) / 'eval.json'}")
    return 0
