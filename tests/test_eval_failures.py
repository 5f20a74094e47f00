"""Issue 28, classes 7-9 on `pi0-torch eval`: a policy server that drops the connection, stays silent, replies
without actions or with bad metadata gives one line (and the finished episodes are kept in `eval.json`); settings
that cannot run are refused by name before the first episode."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path


import numpy as np
import pytest
from websockets.sync.server import ServerConnection, serve

from pi0_torch.cli import main
from pi0_torch.runtime.rollout import EvalSettings, LocalPolicy, RemotePolicy, ScriptedPolicy, evaluate
from pi0_torch.runtime.serving import pack_message, unpack_message

HORIZON = 4
METADATA = {"policy": "fake", "action_horizon": HORIZON, "action_dim": 3, "state_dim": 3,
            "camera_names": ["base_0_rgb", "left_wrist_0_rgb"]}


@contextlib.contextmanager
def fake_server(mode: str, serve_first: int = 0, closed: threading.Semaphore | None = None) -> Iterator[str]:
    """An openpi-protocol server that answers `serve_first` requests with a still chunk, then misbehaves per `mode`:
    "drop" closes every connection, "silent" never replies, "no actions" replies without them, "bad metadata"
    sends metadata without an action horizon. `closed` is released once per connection its client closed."""
    served = [0]
    lock = threading.Lock()
    release = threading.Event()

    def handle(ws: ServerConnection) -> None:
        ws.send(pack_message({"policy": "fake"} if mode == "bad metadata" else METADATA))
        for frame in ws:
            observation = unpack_message(frame)
            with lock:
                served[0] += 1
                misbehave = served[0] > serve_first
            if not misbehave:
                ws.send(pack_message({"actions": np.repeat(np.asarray(observation["state"], np.float32)[None], HORIZON, 0)}))
            elif mode == "drop":
                ws.close()
                return
            elif mode == "silent":
                release.wait(30)
                return
            else:
                ws.send(pack_message({"policy_timing": {"infer_ms": 1.0}}))
        if closed is not None:
            closed.release()

    with serve(handle, "127.0.0.1", 0) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
        finally:
            release.set()
            server.shutdown()
            thread.join(30)


def run_eval(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """`pi0-torch eval` in this process: its status and its last line on stderr (the progress bar writes there too),
    checked to be the only error line and no traceback."""
    status = main(["eval", "--env", "pi0_torch/Reach-v0", "--max-steps", "8", *args])
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("error:") <= 1, err
    return status, err.strip().splitlines()[-1] if err.strip() else ""


def test_a_server_that_drops_mid_evaluation_keeps_the_finished_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 28.8: `ConnectionClosedError` gave a traceback and no eval.json. Two episodes (4 requests) finish, then
    the server closes every connection."""
    with fake_server("drop", serve_first=4) as url:
        status, err = run_eval(capsys, "--policy", url, "--episodes", "4", "--num-envs", "2",
                               "--output-dir", str(tmp_path / "out"))
    assert status == 2 and "\n" not in err, err
    assert err.startswith(f"pi0-torch eval: error: ConnectionError: the policy server at {url} closed the connection"), err
    assert "(stopped after 2 finished episodes of 4; eval.json and episodes.jsonl in " in err, err
    written = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert written["complete"] is False and written["episodes"] == 2 and "closed the connection" in written["stopped_by"]
    assert [episode["seed"] for episode in written["episodes_detail"]] == [1_000_000, 1_000_001]


@pytest.mark.parametrize(("mode", "message"), [
    ("silent", "sent no reply within 1 s (--timeout)"),  # waited 600 s per call, with no option
    ("no actions", r"a reply without 'actions' (got ['policy_timing'])"),  # KeyError
    ("bad metadata", "metadata lacks 'action_horizon' (got ['policy'])"),  # KeyError
])
def test_a_misbehaving_server_is_one_line(mode: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with fake_server(mode) as url:
        status, err = run_eval(capsys, "--policy", url, "--episodes", "1", "--num-envs", "1", "--timeout", "1",
                               "--output-dir", str(tmp_path / "out"))
    assert status == 2 and err.startswith("pi0-torch eval: error: ") and message in err and "\n" not in err, err
    assert not (tmp_path / "out").exists()  # no episode finished: nothing to write


def test_a_refused_server_is_left_with_no_connection_open() -> None:
    """A server whose metadata is refused has every connection closed by the client at once (they stayed open until
    the process ended)."""
    closed = threading.Semaphore(0)
    with fake_server("bad metadata", closed=closed) as url:
        with pytest.raises(ValueError, match="lacks 'action_horizon'"):
            RemotePolicy(url, connections=2, timeout=5)
        assert closed.acquire(timeout=10) and closed.acquire(timeout=10)


@pytest.mark.parametrize(("args", "message"), [
    (("--replan-steps", "0"), r"--replan-steps must be an integer in [1, 16], got 0"),  # became 16
    (("--inference-delay", "-1"), r"--inference-delay must be an integer in [0, 10000], got -1"),  # 'replan_steps ... 17'
    (("--seed", "-1"), "--seed must be an integer in [0, "),
    (("--episodes", "0"), "--episodes must be an integer in [1, "),
    (("--env-kwargs", '{"no_such_setting": 1}'), "cannot be made with the settings ['no_such_setting']"),
    (("--timeout", "0"), "--timeout must be a finite number > 0"),
    (("--env-kwargs", '{"render_mode": 5}'), "--env-kwargs: render_mode must be a string such as 'rgb_array', got 5"),
])
def test_settings_that_cannot_run_are_named_before_the_first_episode(args: tuple[str, ...], message: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    policy = "ws://127.0.0.1:9" if args[0] == "--timeout" else "demo"
    status, err = run_eval(capsys, "--policy", policy, "--episodes", "1", *args)
    assert status == 2 and err.startswith("pi0-torch eval: error: ") and message in err and "\n" not in err, err


def test_env_kwargs_must_be_a_json_object(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["eval", "--policy", "expert", "--env", "pi0_torch/Reach-v0", "--env-kwargs", "[1, 2]"])
    err = capsys.readouterr().err
    assert "argument --env-kwargs: expected a JSON object, got a JSON list" in err and "Traceback" not in err


def test_json_options_beyond_pythons_integer_limit_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["eval", "--policy", "expert", "--env", "pi0_torch/Reach-v0", "--env-kwargs", '{"n": ' + "9" * 5000 + "}"])
    err = capsys.readouterr().err
    # (Python 3.10 words it "Exceeds the limit (4300) for integer string conversion", 3.11+ "... (4300 digits) ...")
    assert "argument --env-kwargs: not valid JSON: Exceeds the limit (4300" in err and "9999" not in err, err


def test_a_policy_camera_the_env_does_not_give_is_a_warning_once(caplog: pytest.LogCaptureFixture) -> None:
    """Issue 28.9: a two-camera policy evaluated with `{"wrist_camera": false}` silently masked the missing camera."""
    from conftest import tiny_policy

    with caplog.at_level(logging.WARNING, logger="pi0_torch.runtime.rollout"):
        evaluate(LocalPolicy(tiny_policy()), EvalSettings(env="pi0_torch/Reach-v0", episodes=2, num_envs=1, max_steps=4,
                                                          env_kwargs={"wrist_camera": False}))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "no frames for the policy's cameras ['left_wrist_0_rgb']" in warnings[0], warnings
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pi0_torch.runtime.rollout"):
        evaluate(ScriptedPolicy("expert"), EvalSettings(env="pi0_torch/Reach-v0", episodes=1, max_steps=4))
    assert not caplog.records




EXPERT_EVAL = ("--policy", "expert", "--episodes", "10", "--num-envs", "2")


def _details(folder: Path) -> list[dict]:
    return json.loads((folder / "eval.json").read_text())["episodes_detail"]


def _signal_on_call(number: int, signum: int) -> str:
    """Source that makes the scripted policy send this process `signum` on its `number`-th call."""
    return (f"import os\nfrom pi0_torch.runtime import rollout\ncall = rollout.ScriptedPolicy.__call__\ncalls = [0]\n"
            f"def counting(self, observations):\n    calls[0] += 1\n    if calls[0] == {number}:\n"
            f"        os.kill(os.getpid(), {int(signum)})\n    return call(self, observations)\n"
            "rollout.ScriptedPolicy.__call__ = counting\n")


def test_sigterm_and_sigkill_keep_the_finished_episodes_and_resume_continues(tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 63, round 5 item 6: TERM at 12 s of 400 episodes exited 143 and the 208 finished episodes were gone.
    Each episode is recorded as it ends (`episodes.jsonl`); SIGTERM stops like Ctrl-C (eval.json of the finished
    episodes, marked incomplete); after SIGKILL the record is in the partial folder; `--resume` runs the episodes it
    lacks, and the result equals an uninterrupted evaluation's."""
    reference = tmp_path / "reference"
    assert run_eval(capsys, *EXPERT_EVAL, "--output-dir", str(reference))[0] == 0

    terminated = tmp_path / "terminated"
    namespace: dict = {}
    exec(_signal_on_call(40, signal.SIGTERM), namespace)  # (in this process: its handler is the CLI's)
    try:
        status, err = run_eval(capsys, *EXPERT_EVAL, "--output-dir", str(terminated))
    finally:
        from pi0_torch.runtime import rollout
        rollout.ScriptedPolicy.__call__ = namespace["call"]
    assert status == 2 and "Terminated: signal SIGTERM (stopped after " in err, err
    stopped = json.loads((terminated / "eval.json").read_text())
    assert stopped["complete"] is False and 0 < stopped["episodes"] < 10
    assert len((terminated / "episodes.jsonl").read_text().splitlines()) > stopped["episodes"]  # (+ identity, calls)
    assert run_eval(capsys, *EXPERT_EVAL, "--output-dir", str(terminated))[1].endswith(
        "--resume continues it, --overwrite starts over")  # (never dropped unasked)
    assert run_eval(capsys, *EXPERT_EVAL, "--output-dir", str(terminated), "--resume")[0] == 0
    assert _details(terminated) == _details(reference)

    killed = tmp_path / "killed"
    script = _signal_on_call(40, signal.SIGKILL) + (
        "from pi0_torch.cli import main\n"
        f"main(['eval', '--env', 'pi0_torch/Reach-v0', '--max-steps', '8', *{list(EXPERT_EVAL)!r}, '--output-dir', {str(killed)!r}])\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert run.returncode == -signal.SIGKILL, run.stderr[-2000:]
    assert not killed.exists()
    partial = tmp_path / ".killed.partial-resumable" / "episodes.jsonl"
    assert sum('"episode"' in line for line in partial.read_text().splitlines()) > 0
    status, err = run_eval(capsys, *EXPERT_EVAL[:3], "12", *EXPERT_EVAL[4:], "--output-dir", str(killed), "--resume")
    assert status == 2 and "records another evaluation (episodes 10 there, 12 now)" in err, err  # (never mixed)
    assert run_eval(capsys, *EXPERT_EVAL, "--output-dir", str(killed), "--resume")[0] == 0
    assert _details(killed) == _details(reference) and not partial.exists()


def test_expert_is_refused_in_one_line_where_the_env_has_none(capsys: pytest.CaptureFixture[str],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 63, first hour 3: `eval --env aloha/AlohaTransferCube-v0 --policy expert` printed a `TypeError` traceback
    and six dm_control atexit tracebacks, though `--help` offered `expert`. Refused in one line, before any env is
    made."""
    from pi0_torch.runtime import rollout

    monkeypatch.setattr(rollout, "make_env", lambda *args, **kwargs: pytest.fail("an env was made"))
    status = main(["eval", "--env", "aloha/AlohaTransferCube-v0", "--policy", "expert", "--episodes", "1"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and err == ("pi0-torch eval: error: --policy expert: aloha/AlohaTransferCube-v0 has no scripted "
                                   "expert here (the pi0_torch/... tabletop envs and metaworld/... have one); --policy "
                                   "random gives a floor")


def test_an_aloha_evaluation_exits_without_dm_control_noise() -> None:
    """Issue 63, first hour 3: dm_control freed gym-aloha's rendering contexts at exit, after its render thread had
    stopped, printing a traceback each. `AlohaSimEnv.close` frees them."""
    pytest.importorskip("gym_aloha")
    script = ("from pi0_torch.cli import main\nfrom pi0_torch.runtime import rollout\n"
              "def fails(self, observations):\n    raise RuntimeError('a policy bug')\n"
              "rollout.ScriptedPolicy.__call__ = fails\n"  # (the traceback keeps the envs alive until exit)
              "raise SystemExit(main(['eval', '--env', 'aloha/AlohaTransferCube-v0', '--policy', 'random', "
              "'--episodes', '1', '--max-steps', '2']))\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    if "RuntimeError: a policy bug" not in run.stderr:
        pytest.skip(f"the ALOHA env did not run here: {run.stderr.strip().splitlines()[-1:]}")
    assert "Exception ignored" not in run.stderr, run.stderr[-2000:]


def test_a_recommended_replan_steps_beyond_the_chunk_names_its_file(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 63, round 5 item 11: `replan_steps: 17` in policy_settings.json was reported as "--replan-steps must be
    ...", a flag never given."""
    import shutil

    from pi0_torch import demo_policy_dir

    folder = tmp_path / "policy"
    shutil.copytree(demo_policy_dir(), folder)
    (folder / "policy_settings.json").write_text('{"replan_steps": 17}')
    status, err = run_eval(capsys, "--policy", str(folder), "--episodes", "1")
    assert status == 2 and err == (f"pi0-torch eval: error: replan_steps 17 in {folder}/policy_settings.json is beyond "
                                   "the policy's 16-action chunks; fix the file, or give --replan-steps"), err


def test_seeds_an_env_cannot_take_and_too_many_envs_for_the_memory_are_refused(capsys: pytest.CaptureFixture[str],
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 63, round 5 item 11: ALOHA accepted `--seed` up to 2^63-2 but needs < 2^32; `--num-envs 1024` was
    allowed though each Meta-World env takes about 84 MB. Both refused before the first episode, naming the bound."""
    import psutil

    class Tight:  # (what psutil says of a machine with 1 MiB available)
        available = 2**20

    monkeypatch.setattr(psutil, "virtual_memory", lambda: Tight())
    status, err = run_eval(capsys, "--policy", "expert", "--episodes", "64", "--num-envs", "64")
    assert status == 2 and re.search(r"--num-envs 64: each pi0_torch/Reach-v0 env holds about \d+ MB here, [\d.]+ GB "
                                      r"for 64; this machine has 0.0 GB available: use fewer", err), err
    monkeypatch.undo()
    pytest.importorskip("gym_aloha")
    status, err = main(["eval", "--env", "aloha/AlohaTransferCube-v0", "--policy", "random", "--episodes", "2",
                        "--seed", str(2**32 - 1)]), capsys.readouterr().err.strip().splitlines()[-1]
    if "render" in err.lower() and "seed" not in err:
        pytest.skip(f"MuJoCo cannot render here: {err}")
    assert status == 2 and err == ("pi0-torch eval: error: --seed must be an integer in [0, 4294967294] for 2 episodes "
                                   f"of aloha/AlohaTransferCube-v0 (its seeds stay below 4294967296), got {2**32 - 1}"), err


def test_a_gl_error_is_one_line_without_mujocos_renderer_noise(tmp_path: Path) -> None:
    """Issue 63, round 5 item 9: after the one-line GL error, MuJoCo's `Renderer.__del__` printed an AttributeError
    (its GL context never opened, so it has no MuJoCo context to free)."""
    pytest.importorskip("mujoco")
    script = ("from pi0_torch.envs import rendering\n"
              "rendering.configure_mujoco_gl()\nrendering._load_triton_first()\n"  # (as the check orders them)
              "import mujoco.renderer\n"
              "class Broken:\n    def __init__(self, *args):\n        raise RuntimeError('cannot initialize EGL display')\n"
              "mujoco.renderer.gl_context.GLContext = Broken\n"
              "try:\n    rendering.check_mujoco_rendering()\nexcept rendering.RenderingError as error:\n"
              "    print(error)\nimport gc\ngc.collect()\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "MuJoCo cannot render offscreen" in run.stdout, run.stdout + run.stderr
    assert "Exception ignored" not in run.stderr and "AttributeError" not in run.stderr, run.stderr
