"""Closed-loop evaluation: a policy acting in gymnasium environments, success rates with 95% intervals.

`pi0-torch eval --policy DIR|ws://HOST:PORT --env ID --episodes N` runs N episodes (seeds S, S+1, ...) in groups of
`--num-envs` environments stepped in lockstep, so a local policy computes one batched chunk for the whole group.
Inference delay is simulated in control steps ([`ChunkSchedule`]): the numbers do not depend on the machine's
speed, and every chunk's noise comes from `noise_seed` (episode seed, chunk number), so the same seeds give the same
episodes locally, through `pi0-torch serve`, and with any `--num-envs`.

```python
>>> [round(bound, 3) for bound in wilson_interval(45, 50)]  # 95% interval of a 90% success rate over 50 episodes
[0.786, 0.957]

```
"""

from __future__ import annotations

import argparse
import concurrent.futures
import importlib
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
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
from pi0_torch.runtime.observation_formats import ObservationFormat

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
    """A [`PI0Policy`] running in this process; a group of observations is one batched model call."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.metadata = policy.metadata

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        prepared = [self.policy.prepare(observation) for observation in observations]
        return [result["actions"] for result in self.policy.infer_prepared(prepared)]


class RemotePolicy:
    """A `pi0-torch serve` (or any openpi-protocol server) reached over websockets: one connection per environment,
    a group's requests sent concurrently so that the server can batch them."""

    def __init__(self, url: str, connections: int, api_key: str | None = None, timeout: float = 600.0) -> None:
        from websockets.exceptions import WebSocketException
        from websockets.sync.client import connect

        from pi0_torch.runtime.serving import pack_message, unpack_message

        self._pack, self._unpack = pack_message, unpack_message
        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        try:
            self.sockets = [connect(url, max_size=None, additional_headers=headers, open_timeout=timeout)
                            for _ in range(connections)]
        except (OSError, WebSocketException) as error:  # refused, unreachable, or a handshake the server rejected
            raise ConnectionError(f"cannot reach the policy server at {url}: {error}") from None
        self.metadata = [self._unpack(socket.recv(timeout)) for socket in self.sockets][0]
        self.timeout = timeout
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=connections)

    def _ask(self, socket: Any, observation: Mapping[str, Any]) -> np.ndarray:
        socket.send(self._pack(dict(observation)))
        reply = socket.recv(self.timeout)
        if isinstance(reply, str):  # the server's one-line error
            raise ValueError(f"policy server: {reply}")
        return np.asarray(self._unpack(reply)["actions"], np.float32)

    def __call__(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        futures = [self.pool.submit(self._ask, socket, obs) for socket, obs in zip(self.sockets, observations)]
        return [future.result() for future in futures]

    def close(self) -> None:
        for socket in self.sockets:
            socket.close()
        self.pool.shutdown()


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
    an unknown id is a `ValueError` listing the known ones."""
    import gymnasium

    namespace = env_id.split("/")[0] if "/" in env_id else None
    if namespace == "pi0_torch":
        importlib.import_module("pi0_torch.envs")
    elif namespace is not None and env_id not in gymnasium.registry:
        try:
            importlib.import_module(namespace)
        except ImportError:
            pass
    if env_id not in gymnasium.registry:
        importlib.import_module("pi0_torch.envs")
        known = sorted(i for i in gymnasium.registry if i.startswith("pi0_torch/")) + sorted(KNOWN_ENVS)
        raise ValueError(f"unknown environment id {env_id!r}; known: {', '.join(known)} (a third-party id needs its "
                         "package installed, e.g. pip install gym-pusht)")
    return gymnasium.make(env_id, **{**KNOWN_ENVS.get(env_id, ({}, ""))[0], **kwargs})


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
    progress: bool = False


@dataclass
class EpisodeResult:
    seed: int
    success: bool
    steps: int
    boundary_jerk: list[float]  # per chunk switch
    interior_jerk: list[float]


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

    def summary(self) -> str:
        low, high = self.success_ci95
        steps = f"{self.mean_steps:.1f}" if self.mean_steps is not None else "-"
        jerk = "".join(f", jerk {where} {value:.4f}" for where, value in
                       (("at chunk boundaries", self.boundary_jerk), ("inside chunks", self.interior_jerk)) if value is not None)
        return (f"{self.env} {self.execution} d={self.inference_delay} s={self.replan_steps}: success "
                f"{100 * self.success_rate:.1f}% [{100 * low:.1f}, {100 * high:.1f}] over {self.episodes} episodes, "
                f"{steps} steps per success, policy {self.latency_ms:.0f} ms per call{jerk}")


def _hold_action(observation: Mapping[str, Any], action_dim: int) -> np.ndarray:
    """Standing still before the first chunk: the robot's state as a position target (envs whose actions are
    absolute targets of their state, as this package's envs and gym_pusht)."""
    state = np.asarray(observation["state"], np.float32)
    if state.shape != (action_dim,):
        raise ValueError(f"holding still needs actions shaped like the state; the env's state has {state.shape[0]} "
                         f"dims and its actions {action_dim}: use --execution naive/rtc with --inference-delay 0")
    return state


def _check_match(policy: ChunkPolicy, env: Any, observation: Mapping[str, Any]) -> None:
    meta = policy.metadata
    action_dim = int(np.prod(env.action_space.shape))
    if meta.get("action_dim") not in (None, action_dim):
        raise ValueError(f"action dims differ: the policy acts in {meta['action_dim']} dims, the env "
                         f"{env.spec.id if env.spec else env} takes {action_dim}")
    state_dim = np.asarray(observation["state"]).shape[0]
    if meta.get("state_dim") not in (None, state_dim):
        raise ValueError(f"state dims differ: the policy expects {meta['state_dim']}, the env gives {state_dim}")
    cameras, policy_cameras = sorted(observation["images"]), list(meta.get("camera_names", []))
    if policy_cameras and not set(cameras) <= set(policy_cameras):
        from pi0_torch.envs.tasks import TabletopEnv

        way_out = "map them with --obs-format"
        if isinstance(env.unwrapped, TabletopEnv):  # its wrist camera can be switched off
            way_out += """, or drop the wrist camera with --env-kwargs '{"wrist_camera": false}'"""
        raise ValueError(f"cameras differ: the env gives {cameras}, the policy knows {policy_cameras} ({way_out})")


def _noise_seed(episode_seed: int, chunk: int) -> int:
    return int(np.random.SeedSequence([episode_seed, chunk]).generate_state(2, np.uint64)[0] >> np.uint64(1))


def evaluate(policy: ChunkPolicy, settings: EvalSettings) -> EvalResult:
    """Run `settings.episodes` closed-loop episodes and summarize them (see the module docstring)."""
    horizon = int(policy.metadata["action_horizon"])
    mode, delay = settings.execution, settings.inference_delay
    if mode not in EXECUTION_MODES:
        raise ValueError(f"execution must be one of {EXECUTION_MODES}, got {mode!r}")
    if settings.episodes < 1 or settings.num_envs < 1:
        raise ValueError(f"episodes and num_envs must be >= 1, got {settings.episodes} and {settings.num_envs}")
    replan = settings.replan_steps or (horizon if mode == "sync" else max(1, horizon - delay))
    schedule = ChunkSchedule(mode, horizon, replan, delay)
    if mode == "rtc-trained" and delay > policy.metadata.get("real_time_chunking", {}).get("rtc_max_delay", 0):
        raise ValueError(f"--execution rtc-trained needs a policy trained with --rtc-max-delay >= {delay}")
    kwargs = dict(settings.env_kwargs)
    if settings.max_steps is not None:
        kwargs["max_episode_steps"] = settings.max_steps
    if settings.video_episodes:
        kwargs.setdefault("render_mode", "rgb_array")
    envs = [make_env(settings.env, **kwargs) for _ in range(min(settings.num_envs, settings.episodes))]
    obs_format = ObservationFormat.from_preset(
        settings.obs_format or KNOWN_ENVS.get(settings.env, ({}, "default"))[1])
    action_dim = int(np.prod(envs[0].action_space.shape))

    def observe(raw: Mapping[str, Any]) -> dict[str, Any]:
        observation = obs_format.to_default(raw)
        if observation["prompt"] is None and settings.prompt is not None:
            observation["prompt"] = settings.prompt
        return observation

    first_observation = observe(envs[0].reset(seed=settings.seed)[0])
    _check_match(policy, envs[0], first_observation)
    if mode == "sync" or delay:
        _hold_action(first_observation, action_dim)
    progress = None
    if settings.progress:
        from tqdm.auto import tqdm

        progress = tqdm(total=settings.episodes, desc=f"eval {settings.env}", unit="episode")
    results: list[EpisodeResult] = []
    latencies: list[float] = []
    frames: list[list[np.ndarray]] = []
    try:
        for first in range(0, settings.episodes, len(envs)):
            seeds = [settings.seed + i for i in range(first, min(first + len(envs), settings.episodes))]
            group = envs[: len(seeds)]
            wave, wave_frames = _run_group(policy, group, seeds, schedule, observe, action_dim, latencies,
                                           record=max(0, settings.video_episodes - len(frames)))
            results += wave
            frames += wave_frames
            if progress is not None:
                progress.update(len(seeds))
                progress.set_postfix(success=f"{np.mean([r.success for r in results]):.0%}")
    finally:
        if progress is not None:
            progress.close()
        for env in envs:
            env.close()
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
        episodes_detail=[{"seed": r.seed, "success": r.success, "steps": r.steps} for r in results],
    )
    if settings.output_dir:
        write_outputs(result, frames, Path(settings.output_dir), fps=_control_hz(envs[0]))
    return result


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
) -> tuple[list[EpisodeResult], list[list[np.ndarray]]]:
    """Episodes of one group of environments in lockstep (they share the chunk schedule)."""
    observations = [observe(env.reset(seed=seed)[0]) for env, seed in zip(envs, seeds)]
    holds = [_hold_action(o, action_dim) if schedule.mode == "sync" or schedule.inference_delay else None
             for o in observations]
    stitchers = [ChunkStitcher(schedule.mode, schedule.replan_steps) for _ in envs]
    pending: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in envs]  # (arrival, anchor, chunk)
    executed: list[list[np.ndarray]] = [[] for _ in envs]
    switches: list[list[int]] = [[] for _ in envs]  # steps at which a new chunk took over
    done = [False] * len(envs)
    success = [False] * len(envs)
    if hasattr(policy, "start_group"):
        policy.start_group(envs, seeds, done)
    frames: list[list[np.ndarray]] = [[envs[i].render()] if i < record else [] for i in range(len(envs))]
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
            observations[i] = observe(raw)
            if i < record:
                frames[i].append(env.render())
            if terminated or truncated:
                done[i], success[i] = True, bool(info.get("is_success", False))
        step += 1
    results = []
    for i, seed in enumerate(seeds):
        motion = np.stack(executed[i])  # jerk of the motion dims where the env names them (not a gripper switch)
        dims = getattr(envs[i].unwrapped, "motion_action_dims", None)
        motion = motion if dims is None else motion[:, list(dims)]
        jerk = second_differences(motion)  # index t - 1 is the second difference centred at t
        at_switch = {t - 1 for t in switches[i] if 2 <= t <= len(executed[i]) - 1}  # centred on the last old action
        results.append(EpisodeResult(
            seed=seed, success=success[i], steps=len(executed[i]),
            boundary_jerk=[float(jerk[t - 1]) for t in sorted(at_switch)],
            interior_jerk=[float(j) for t, j in enumerate(jerk, start=1) if t not in at_switch],
        ))
    return results, [f for f in frames if f]


def write_outputs(result: EvalResult, frames: list[list[np.ndarray]], output_dir: Path, fps: int) -> None:
    """`eval.json`, and for recorded episodes `rollout_<seed>.mp4` plus one `rollout_<seed>.png` strip, written
    aside and moved into place."""
    from PIL import Image

    from pi0_torch.data.lerobot_writer import encode_video
    from pi0_torch.utils.files import atomic_output_dir

    with atomic_output_dir(output_dir, overwrite=True) as staging:
        (staging / "eval.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
        for frames_of_episode, detail in zip(frames, result.episodes_detail):
            name = f"rollout_{detail['seed']}"
            encode_video(staging / f"{name}.mp4", [_even(f) for f in frames_of_episode], fps, "libx264")
            picks = np.linspace(0, len(frames_of_episode) - 1, num=min(8, len(frames_of_episode))).round().astype(int)
            Image.fromarray(np.concatenate([frames_of_episode[i] for i in picks], axis=1)).save(staging / f"{name}.png")


def _even(frame: np.ndarray) -> np.ndarray:
    """H.264 with yuv420p needs even sides."""
    return frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]


def load_policy(spec: str, connections: int, api_key: str | None = None, device: str | None = None,
                num_steps: int | None = None, noise_scale: float = 1.0, rtc_schedule: str = "exp") -> ChunkPolicy:
    """A folder (loaded here), `ws://host:port` (a running server), or `expert` / `random` ([`ScriptedPolicy`]).
    `device`, `num_steps`, `noise_scale` and `rtc_schedule` apply to a folder (a server samples with its own
    settings)."""
    if spec.startswith(("ws://", "wss://")):
        return RemotePolicy(spec, connections, api_key=api_key)
    if spec in ("expert", "random"):
        return ScriptedPolicy(spec)
    from pi0_torch.runtime.policy import PI0Policy

    return LocalPolicy(PI0Policy.from_pretrained(spec, device=device, num_steps=num_steps, noise_scale=noise_scale,
                                                   rtc_schedule=rtc_schedule))


# ----------------------------------------------------------------------------------------------------------------
# pi0-torch eval
# ----------------------------------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `pi0-torch eval`."""
    parser.add_argument("--policy", required=True, help="a model folder, ws://HOST:PORT of pi0-torch serve, or "
                        "'expert' / 'random' (references: the env's scripted expert, uniform random actions)")
    parser.add_argument("--env", required=True, help="gymnasium id, e.g. pi0_torch/PickPlace-v0 or gym_pusht/PushT-v0")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--num-envs", type=int, default=8, help="environments stepped together (one batched call)")
    parser.add_argument("--seed", type=int, default=1_000_000, help="seed of the first episode (demos use 0, 1, ...)")
    parser.add_argument("--replan-steps", type=int, help="actions executed per chunk before the next observation "
                        "(default: the whole horizon; with an asynchronous execution, horizon - delay)")
    parser.add_argument("--execution", choices=EXECUTION_MODES, default="sync",
                        help="how chunks are stitched under inference delay (see docs/closed_loop.md)")
    parser.add_argument("--inference-delay", type=int, default=0, metavar="D",
                        help="simulated inference time in control steps")
    parser.add_argument("--max-steps", type=int, help="override the env's step limit")
    parser.add_argument("--obs-format", help="observation layout of the env (a pi0-torch serve preset or .json; "
                        "default: from the env id)")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, metavar="JSON", help="passed to gymnasium.make")
    parser.add_argument("--prompt", help="instruction for envs whose observations hold none")
    parser.add_argument("--num-steps", type=int, help="Euler steps per chunk (local policy)")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="standard deviation of the noise each chunk's "
                        "flow starts from (local policy; default 1, openpi's sampler; the demo policy uses 0.1)")
    parser.add_argument("--rtc-schedule", default="exp", help="soft mask of --execution rtc over the previous "
                        "chunk: exp (default, the paper's), linear, ones or hard (local policy)")
    parser.add_argument("--device", help="local policy device (default: CUDA if available)")
    parser.add_argument("--api-key", help="for a server started with --api-key")
    parser.add_argument("--output-dir", help="write eval.json (and videos) here")
    parser.add_argument("--video", nargs="?", type=int, const=1, default=0, metavar="N",
                        help="record the first N episodes (default 1) as mp4 and PNG strips (needs --output-dir)")


def run(args: argparse.Namespace) -> int:
    settings = EvalSettings(
        env=args.env, episodes=args.episodes, num_envs=args.num_envs, seed=args.seed,
        replan_steps=args.replan_steps, execution=args.execution, inference_delay=args.inference_delay,
        max_steps=args.max_steps, obs_format=args.obs_format, env_kwargs=args.env_kwargs, prompt=args.prompt,
        video_episodes=args.video, output_dir=args.output_dir, progress=True,
    )
    try:
        if settings.video_episodes and not settings.output_dir:
            raise ValueError("--video needs --output-dir")
        make_env(settings.env).close()  # an unknown id fails before the policy loads
        policy = load_policy(args.policy, min(args.num_envs, args.episodes), args.api_key, args.device, args.num_steps,
                             args.noise_scale, args.rtc_schedule)
        try:
            result = evaluate(policy, settings)
        finally:
            if isinstance(policy, RemotePolicy):
                policy.close()
    except (ValueError, FileNotFoundError, ConnectionError) as error:
        print(f"pi0-torch eval: error: {error}", file=sys.stderr)
        return 2
    print(result.summary())
    if settings.output_dir:
        print(f"wrote {Path(settings.output_dir) / 'eval.json'}")
    return 0
