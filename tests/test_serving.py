"""The policy server against openpi's own client (`openpi-client` from PyPI, run from its own virtualenv).

openpi-client 0.1.2 pins numpy<2 and imports typing_extensions without declaring it, so it cannot live in the
project's environment: a session fixture builds a small virtualenv for it once (cached under
`~/.cache/pi0-torch-test/`, or `$PI0_TORCH_TEST_CACHE`) and every client runs as a subprocess of that interpreter.
The server runs the real model and processor (a random `pi0_small` saved with `save_pretrained`, a SentencePiece
tokenizer trained on the fly), in a thread of the test process, or as the `serve` command for the signal test.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import torch
import websockets.sync.client

from conftest import HANG_S
from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.processing.normalization import NormStats
from pi0_torch.runtime.observation_formats import ObservationError, ObservationFormat
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.runtime.serving import MessageError, PolicyServer, pack_message, unpack_message
from pi0_torch.processing.tokenization import build_test_tokenizer

OPENPI_CLIENT = "openpi-client==0.1.2"
STATE_DIM, ACTION_DIM = 8, 7  # LIBERO's robot dims
REPO_ROOT = Path(__file__).resolve().parents[1]

# --------------------------------------------------------------------------------------------- the real client

# Runs inside the openpi-client virtualenv: `python client.py '<json plan>'` prints one JSON result line.
CLIENT_SCRIPT = r'''
import json, sys, threading, time
import msgpack
import numpy as np
from openpi_client import msgpack_numpy
from openpi_client.websocket_client_policy import WebsocketClientPolicy

plan = json.loads(sys.argv[1])
HOST, PORT = "127.0.0.1", plan["port"]


def observation(meta, rng, layout="default"):
    base = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    wrist = rng.integers(0, 256, (3, 64, 64), dtype=np.uint8)  # channels first, as ALOHA clients send
    state = rng.standard_normal(meta["state_dim"]).astype(np.float32)
    if layout == "libero":
        return {"observation/image": base, "observation/wrist_image": wrist, "observation/state": state,
                "prompt": "pick up the fork", "extra/key": np.zeros(3)}
    return {"images": {"base_0_rgb": base, "left_wrist_0_rgb": wrist}, "state": state, "prompt": "pick up the fork"}


def summary(reply):
    actions = reply["actions"]
    return {"keys": sorted(reply), "shape": list(actions.shape), "dtype": str(actions.dtype),
            "finite": bool(np.isfinite(actions).all()), "actions": actions.tolist(),
            "server_timing": sorted(reply["server_timing"]),
            "policy_timing": reply["policy_timing"]}


def error_of(send):
    try:
        send()
    except RuntimeError as error:
        return str(error)
    return None


def run_infer():
    policy = WebsocketClientPolicy(host=HOST, port=PORT, api_key=plan.get("api_key"))
    meta = policy.get_server_metadata()
    rng = np.random.default_rng(0)
    replies = [summary(policy.infer(observation(meta, rng, plan.get("layout", "default"))))
               for _ in range(plan.get("requests", 1))]
    return {"metadata": meta, "replies": replies}


def run_bad():
    policy = WebsocketClientPolicy(host=HOST, port=PORT)
    meta = policy.get_server_metadata()
    rng = np.random.default_rng(1)
    good = lambda: observation(meta, rng)

    def with_changes(**changes):
        obs = good()
        for key, value in changes.items():
            if value is None:
                del obs[key]
            else:
                obs[key] = value
        return obs

    def raw(frame):
        policy._ws.send(frame)  # the client's own connection, for frames its infer() cannot produce
        reply = policy._ws.recv()
        if isinstance(reply, str):  # as WebsocketClientPolicy.infer reports it
            raise RuntimeError(f"Error in inference server:\n{reply}")
        return msgpack_numpy.unpackb(reply)

    def array_frame(dtype, shape, data):
        header = {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}
        return msgpack.packb({"images": {"base_0_rgb": header}, "state": [0.0] * meta["state_dim"], "prompt": "x"})

    state_nan = good()["state"]
    state_nan[2] = np.nan
    cases = {
        "state_length": lambda: policy.infer(with_changes(state=np.zeros(meta["state_dim"] + 1, np.float32))),
        "state_nan": lambda: policy.infer(with_changes(state=state_nan)),
        "state_text": lambda: policy.infer(with_changes(state="fast")),
        "image_2d": lambda: policy.infer(with_changes(images={"base_0_rgb": np.zeros((96, 128), np.uint8)})),
        "image_range": lambda: policy.infer(with_changes(images={"base_0_rgb": np.full((96, 128, 3), 7.0)})),
        "image_nan": lambda: policy.infer(with_changes(images={"base_0_rgb": np.full((96, 128, 3), np.nan)})),
        "unknown_camera": lambda: policy.infer(with_changes(images={"top_cam": np.zeros((96, 128, 3), np.uint8)})),
        "missing_prompt": lambda: policy.infer(with_changes(prompt=None)),
        "missing_images": lambda: policy.infer(with_changes(images=None)),
        "not_a_dict": lambda: policy.infer([1, 2, 3]),
        "garbage_bytes": lambda: raw(b"\xc1\x00\x01"),
        "text_frame": lambda: raw("hello"),
        "object_dtype": lambda: raw(array_frame("|O", [2], b"\x00" * 16)),
        "short_array": lambda: raw(array_frame("|u1", [96, 128, 3], b"\x00" * 10)),
    }
    errors, good_after = {}, {}
    for name, send in cases.items():
        errors[name] = error_of(send)
        good_after[name] = summary(policy.infer(good()))["shape"]  # the same connection still answers
    fresh = WebsocketClientPolicy(host=HOST, port=PORT, api_key="ignored")  # openpi sends it as a header
    return {"errors": errors, "good_after": good_after, "fresh": summary(fresh.infer(good()))["shape"]}


def run_retry():
    policy = WebsocketClientPolicy(host=HOST, port=PORT)
    meta = policy.get_server_metadata()
    rng = np.random.default_rng(2)
    error = error_of(lambda: policy.infer(observation(meta, rng)))
    return {"error": error, "then": summary(policy.infer(observation(meta, rng)))["shape"]}


def run_load():
    clients, requests, rude = plan["clients"], plan["requests"], plan.get("rude", 0)
    results, lock = [], threading.Lock()

    def client(index):
        rng = np.random.default_rng(100 + index)
        try:
            policy = WebsocketClientPolicy(host=HOST, port=PORT)
            meta = policy.get_server_metadata()
            for _ in range(requests):
                start = time.monotonic()
                reply = policy.infer(observation(meta, rng))
                ok = list(reply["actions"].shape) == [meta["action_horizon"], meta["action_dim"]]
                ok = ok and bool(np.isfinite(reply["actions"]).all())
                with lock:
                    results.append((ok, time.monotonic() - start, reply["policy_timing"]["batch_size"], None))
        except Exception as error:
            with lock:
                results.append((False, 0.0, 0, repr(error)))

    def rude_client(index):  # sends an observation and hangs up without reading the reply
        rng = np.random.default_rng(900 + index)
        policy = WebsocketClientPolicy(host=HOST, port=PORT)
        policy._ws.send(msgpack_numpy.packb(observation(policy.get_server_metadata(), rng)))
        policy._ws.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    threads += [threading.Thread(target=rude_client, args=(i,)) for i in range(rude)]
    start = time.monotonic()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    elapsed = time.monotonic() - start
    latencies = sorted(r[1] for r in results if r[0])
    return {"ok": sum(r[0] for r in results), "failed": [r for r in results if not r[0]],
            "max_batch": max((r[2] for r in results), default=0), "elapsed": elapsed,
            "p50_ms": 1000 * latencies[len(latencies) // 2] if latencies else None}


print(json.dumps({"infer": run_infer, "bad": run_bad, "retry": run_retry, "load": run_load}[plan["mode"]]()))
'''


def _cache_dir() -> Path:
    return Path(os.environ.get("PI0_TORCH_TEST_CACHE", Path.home() / ".cache" / "pi0-torch-test"))


def _pypi_reachable() -> bool:
    for host in ("pypi.org", "files.pythonhosted.org"):
        try:
            socket.create_connection((host, 443), timeout=3).close()
            return True
        except OSError:
            continue
    return False


@pytest.fixture(scope="session")
def client_python() -> Path:
    """The interpreter of a virtualenv holding the real openpi-client (built once, then reused)."""
    venv = _cache_dir() / "openpi-client-venv"
    python = venv / "bin" / "python"
    ready = venv / ".pi0-torch-ready"
    venv.parent.mkdir(parents=True, exist_ok=True)
    with open(venv.parent / "openpi-client-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # two test runs must not build it at once
        if ready.is_file() and ready.read_text() == OPENPI_CLIENT:
            return python
        shutil.rmtree(venv, ignore_errors=True)
        steps = [
            [sys.executable, "-m", "venv", str(venv)],
            [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", OPENPI_CLIENT,
             "typing_extensions"],
        ]
        for step in steps:
            done = subprocess.run(step, capture_output=True, text=True, timeout=HANG_S)
            if done.returncode != 0:
                shutil.rmtree(venv, ignore_errors=True)
                if not _pypi_reachable():
                    pytest.skip(f"no network: cannot install {OPENPI_CLIENT} from PyPI")
                pytest.fail(f"could not build the openpi-client virtualenv: {' '.join(step)} failed:\n"
                            f"{done.stdout}\n{done.stderr}")
        ready.write_text(OPENPI_CLIENT)
    return python


def run_client(client_python: Path, tmp_path: Path, **plan: Any) -> dict[str, Any]:
    script = tmp_path / "openpi_client_probe.py"
    script.write_text(CLIENT_SCRIPT)
    done = subprocess.run([str(client_python), str(script), json.dumps(plan)], capture_output=True, text=True,
                          timeout=HANG_S)
    assert done.returncode == 0, f"client failed:\n{done.stdout}\n{done.stderr}"
    return json.loads(done.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------- a real model


def save_random_model(directory: Path, preset: str) -> Path:
    """A random model with a LIBERO-sized processor (state 8, actions 7), saved as a converted model is."""
    torch.manual_seed(0)
    config = PI0Config.from_preset(preset, num_inference_steps=2)
    PI0ForActionGeneration(config).save_pretrained(directory)
    rng = np.random.default_rng(0)
    stats = {
        key: NormStats(mean=rng.normal(size=dim), std=rng.uniform(0.5, 2.0, size=dim), q01=-np.ones(dim), q99=np.ones(dim))
        for key, dim in (("state", STATE_DIM), ("actions", ACTION_DIM))
    }
    PI0Processor.from_config(config, tokenizer=build_test_tokenizer(), norm_stats=stats).save_pretrained(directory)
    return directory


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_random_model(tmp_path_factory.mktemp("pi0_small_served"), "pi0_small")


@pytest.fixture(scope="session")
def policy(model_dir: Path) -> PI0Policy:
    return PI0Policy.from_pretrained(model_dir, device="cpu", seed=0)


def running_server(policy: PI0Policy, **options: Any) -> contextlib.AbstractContextManager[int]:
    """Serve `policy` on 127.0.0.1 (a free port) from a background thread; yields the port."""
    return PolicyServer(policy, host="127.0.0.1", port=0, **options).serve_in_thread()


# --------------------------------------------------------------------------------------------- wire format


def test_codec_round_trips_what_openpi_client_sends() -> None:
    message = {
        "images": {"base_0_rgb": np.arange(24, dtype=np.uint8).reshape(2, 4, 3)},
        "state": np.array([0.5, -1.0], np.float64),
        "flags": np.array([True, False]),
        "scalar": np.float32(1.5),
        "prompt": "pick up the fork",
        "names": np.array(["a", "bc"]),
        "list": [1, 2.5, "x"],
    }
    decoded = unpack_message(pack_message(message))
    for path, value in (("state", message["state"]), ("flags", message["flags"]), ("names", message["names"]),
                        ("images", message["images"]["base_0_rgb"])):
        got = decoded[path] if path != "images" else decoded["images"]["base_0_rgb"]
        assert got.dtype == value.dtype and got.shape == value.shape and np.array_equal(got, value)
    assert decoded["scalar"] == np.float32(1.5) and decoded["scalar"].dtype == np.float32
    assert decoded["prompt"] == "pick up the fork" and decoded["list"] == [1, 2.5, "x"]
    # the exact bytes openpi's msgpack_numpy writes for an array: a map with bytes keys
    raw = msgpack.unpackb(pack_message(np.zeros((2, 3), np.float32)))
    assert raw == {b"__ndarray__": True, b"data": bytes(24), b"dtype": "<f4", b"shape": [2, 3]}


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (b"\xc1", "not a valid msgpack message"),
        (msgpack.packb({b"__ndarray__": True, b"data": bytes(16), b"dtype": "|O", b"shape": [2]}), "unsupported array dtype"),
        (msgpack.packb({b"__ndarray__": True, b"data": bytes(8), b"dtype": "|V8", b"shape": [1]}), "unsupported array dtype"),
        (msgpack.packb({b"__ndarray__": True, b"data": bytes(5), b"dtype": "<f4", b"shape": [2]}), "needs 8 bytes, got 5"),
        (msgpack.packb({b"__ndarray__": True, b"data": bytes(4), b"dtype": "<f4", b"shape": [-1]}), "non-negative"),
        (msgpack.packb({b"__ndarray__": True, b"data": "text", b"dtype": "<f4", b"shape": [1]}), "must be bytes"),
        ("a text frame", "expected a binary frame"),
    ],
)
def test_codec_refuses_malformed_frames(frame: Any, reason: str) -> None:
    with pytest.raises(MessageError, match=reason):
        unpack_message(frame)


def _numpy_text(code_points: list[int], byteorder: str = "<") -> np.ndarray:
    """A 0-d numpy string of raw UTF-32 code points, as any client can pack it (numpy cannot build it from text)."""
    dtype = np.dtype(f"{byteorder}U{len(code_points)}")
    return np.frombuffer(np.array(code_points, f"{byteorder}u4").tobytes(), dtype).reshape(())


@pytest.mark.parametrize(
    ("message", "field"),
    [
        ({"prompt": _numpy_text([0xFFFFFFFF]), "state": np.zeros(3)}, "prompt"),  # issue 38.15
        ({"images": {"cam_high": _numpy_text([0x61, 0xD800], ">")}}, "images/cam_high"),  # a surrogate, big-endian
        ({"steps": [1, {"rtc_method": _numpy_text([0x110000])}]}, "steps[1]/rtc_method"),
        ([_numpy_text([0x61]), _numpy_text([0xFFFFFFFF]), _numpy_text([0xFFFFFFFF])], "[1]"),  # the first is named
        (_numpy_text([0xFFFFFFFF]), "the message"),
    ],
)
def test_numpy_strings_that_are_no_text_are_refused_naming_the_field(message: Any, field: str) -> None:
    """numpy fails on such strings wherever they are read (`.item()`, `str()`, printing: a SystemError), so the
    decoder refuses them, naming the field, expected and actual; text numpy strings still pass."""
    frame = pack_message(message)
    with pytest.raises(MessageError) as refused:
        unpack_message(frame, max_items=100, max_objects=1_000)
    assert str(refused.value).startswith(f"{field}: expected Unicode text (code points up to U+10FFFF, surrogates "
                                         "excluded), got a numpy string array (dtype "), str(refused.value)
    assert " holding 0x" in str(refused.value) and "\n" not in str(refused.value)
    assert unpack_message(pack_message({"prompt": _numpy_text([0x10FFFF, 0xE9])}))["prompt"].item() == "\U0010ffffé"


def test_codec_refuses_to_send_object_arrays() -> None:
    with pytest.raises(TypeError, match="dtype object"):
        pack_message({"x": np.array([None, 1], dtype=object)})


# --------------------------------------------------------------------------------------------- observation formats


def _frame(shape: tuple[int, ...] = (96, 128, 3)) -> np.ndarray:
    return np.zeros(shape, np.uint8)


def test_presets_map_openpi_example_clients_to_the_default_layout() -> None:
    libero = ObservationFormat.from_preset("libero").to_default({
        "observation/image": _frame(), "observation/wrist_image": _frame(), "observation/state": np.arange(8.0),
        "prompt": "put the bowl on the plate", "unrelated": 1,
    })
    assert sorted(libero["images"]) == ["base_0_rgb", "left_wrist_0_rgb"]
    assert libero["state"].tolist() == list(range(8)) and libero["prompt"] == "put the bowl on the plate"

    droid = ObservationFormat.from_preset("droid").to_default({
        "observation/exterior_image_1_left": _frame(), "observation/wrist_image_left": _frame(),
        "observation/joint_position": np.arange(7.0), "observation/gripper_position": np.array([0.25]),
    })
    assert droid["state"].tolist() == [0, 1, 2, 3, 4, 5, 6, 0.25] and droid["prompt"] is None
    # the total (8) alone would let 1 joint + 7 gripper values through: each source has its length
    with pytest.raises(ObservationError, match=r"'observation/joint_position' must hold 7 values \(droid format\), got 1"):
        ObservationFormat.from_preset("droid").to_default({
            "observation/exterior_image_1_left": _frame(), "observation/wrist_image_left": _frame(),
            "observation/joint_position": np.arange(1.0), "observation/gripper_position": np.arange(7.0),
        })

    aloha = ObservationFormat.from_preset("aloha").to_default({
        "state": np.zeros(14), "images": {"cam_high": _frame((3, 224, 224)), "cam_low": _frame((3, 224, 224))},
    })
    assert list(aloha["images"]) == ["base_0_rgb"] and aloha["images"]["base_0_rgb"].shape == (3, 224, 224)


def test_format_errors_name_the_missing_field() -> None:
    libero = ObservationFormat.from_preset("libero")
    with pytest.raises(ObservationError, match="missing image 'observation/wrist_image'"):
        libero.to_default({"observation/image": _frame(), "observation/state": np.zeros(8)})
    with pytest.raises(ObservationError, match="missing state field 'observation/state'"):
        libero.to_default({"observation/image": _frame(), "observation/wrist_image": _frame()})
    with pytest.raises(ObservationError, match="must be 1-D"):
        ObservationFormat.from_preset("default").to_default({"images": {"base_0_rgb": _frame()}, "state": np.zeros((2, 4))})
    with pytest.raises(ObservationError, match="prompt 'prompt' must be a string"):
        ObservationFormat.from_preset("default").to_default({"images": {"x": _frame()}, "state": [0.0], "prompt": 3})
    with pytest.raises(ObservationError, match="must be a dict"):
        ObservationFormat.from_preset("default").to_default([1, 2])


def test_format_from_json_and_its_checks(tmp_path: Path) -> None:
    spec = {"images": {"base_0_rgb": ["obs", "front"], "left_wrist_0_rgb": "wrist"}, "optional_images": ["left_wrist_0_rgb"],
            "state": ["arm", ["obs", "gripper"]], "state_sizes": [None, 1], "prompt": "task"}
    path = tmp_path / "my_robot.json"
    path.write_text(json.dumps(spec))
    fmt = ObservationFormat.resolve(str(path))
    assert fmt.name == "my_robot" and fmt.describe()["state"] == ["arm", ["obs", "gripper"]]
    obs = fmt.to_default({"obs": {"front": _frame(), "gripper": 1.0}, "arm": [0.1, 0.2], "task": "fold"})
    assert list(obs["images"]) == ["base_0_rgb"] and obs["state"].tolist() == pytest.approx([0.1, 0.2, 1.0])
    fmt.check_cameras(["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"])
    with pytest.raises(ValueError, match="model does not have"):
        fmt.check_cameras(["base_0_rgb"])
    for bad, reason in (({"images": {}, "state": ["s"]}, "maps no camera"), ({"images": "i"}, "missing key 'state'"),
                        ({"images": "i", "state": "s"}, "non-empty list"), ({"images": "i", "state": ["s"], "x": 1}, "unknown keys"),
                        ({"images": {"a": "k"}, "state": ["s"], "optional_images": ["b"]}, "not mapped"),
                        ({"images": "i", "state": ["s", "t"], "state_sizes": [7]}, "2 state sources"),
                        ({"images": "i", "state": ["s"], "state_sizes": [0]}, "positive integers"),
                        ({"images": "i", "state": ["s"], "state_sizes": 7}, "list of lengths")):
        with pytest.raises(ValueError, match=reason):
            ObservationFormat.from_dict(bad)
    with pytest.raises(ValueError, match="unknown observation format 'bridge'"):
        ObservationFormat.resolve("bridge")


# --------------------------------------------------------------------------------------------- with the real client


def test_openpi_client_gets_metadata_and_actions(policy: PI0Policy, client_python: Path, tmp_path: Path) -> None:
    with running_server(policy) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port, requests=2)
    meta = result["metadata"]
    assert meta["model_type"] == "pi0" and meta["action_horizon"] == 50
    assert (meta["state_dim"], meta["action_dim"]) == (STATE_DIM, ACTION_DIM)
    assert meta["camera_names"] == ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"]
    assert meta["observation_format"]["name"] == "default"
    for reply in result["replies"]:
        assert reply["keys"] == ["actions", "policy_timing", "server_timing"]
        assert reply["shape"] == [50, ACTION_DIM] and reply["dtype"] == "float32" and reply["finite"]
        assert reply["policy_timing"]["batch_size"] == 1 and reply["policy_timing"]["infer_ms"] > 0
    assert result["replies"][0]["server_timing"] == ["infer_ms"]
    assert result["replies"][1]["server_timing"] == ["infer_ms", "prev_total_ms"]


def test_pi05_is_served_too(client_python: Path, tmp_path: Path) -> None:
    policy = PI0Policy.from_pretrained(save_random_model(tmp_path / "pi05", "pi05_small"), device="cpu", seed=0)
    with running_server(policy) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port)
    assert result["metadata"]["model_type"] == "pi05"
    assert result["replies"][0]["shape"] == [50, ACTION_DIM] and result["replies"][0]["finite"]


def in_process_first_reply(model_dir: Path, seed: int) -> np.ndarray:
    """The actions a fresh eager policy gives for the client script's first observation (rebuilt here)."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    wrist = rng.integers(0, 256, (3, 64, 64), dtype=np.uint8)
    state = rng.standard_normal(STATE_DIM).astype(np.float32)
    local = PI0Policy.from_pretrained(model_dir, device="cpu", seed=seed)
    return local.infer({"images": {"base_0_rgb": base, "left_wrist_0_rgb": wrist}, "state": state,
                        "prompt": "pick up the fork"})["actions"]


def test_served_actions_equal_in_process_actions(model_dir: Path, client_python: Path, tmp_path: Path) -> None:
    """Same seed, same observation: the actions through the websocket are the policy's own, bit for bit."""
    with running_server(PI0Policy.from_pretrained(model_dir, device="cpu", seed=123)) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port, requests=1)
    expected = in_process_first_reply(model_dir, seed=123)
    assert np.array_equal(np.asarray(result["replies"][0]["actions"], np.float32), expected)


def test_compiled_policy_is_warmed_up_before_serving_and_serves_the_same_actions(
    model_dir: Path, client_python: Path, tmp_path: Path
) -> None:
    """`compile=True` (`serve --compile`): every batch size up to max_batch_size is compiled during the warm-up;
    requests, single or batched, then compile nothing and get the eager policy's actions."""
    from torch._dynamo.utils import counters

    compiled = PI0Policy.from_pretrained(model_dir, device="cpu", seed=123, compile=True)
    graphs_before = counters["stats"]["unique_graphs"]
    with running_server(compiled, max_batch_size=2) as port:
        graphs_warm = counters["stats"]["unique_graphs"]
        result = run_client(client_python, tmp_path, mode="infer", port=port, requests=1)
        load = run_client(client_python, tmp_path, mode="load", port=port, clients=3, requests=2, rude=0)
    assert graphs_warm >= graphs_before + 2, "the warm-up did not compile batch sizes 1 and 2"
    assert counters["stats"]["unique_graphs"] == graphs_warm, "a request compiled again"
    assert load["failed"] == [] and load["ok"] == 6 and 1 <= load["max_batch"] <= 2  # batching is up to timing
    expected = in_process_first_reply(model_dir, seed=123)  # eager
    np.testing.assert_allclose(np.asarray(result["replies"][0]["actions"], np.float32), expected, rtol=1e-4, atol=1e-4)


def test_the_warm_up_log_says_which_graphs_were_captured(model_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A policy that replays CUDA graphs is warmed up for every batch size, plain and continued by its real-time
    chunking method where that replays a graph too, and the log says so (on the CPU, `capture_sampling` is set but
    sampling stays eager). Guided chunks replay graphs only on request (`capture_sampling(guidance=True)`)."""
    captured = PI0Policy.from_pretrained(model_dir, device="cpu", seed=0)
    for guidance, logged in ((False, "CUDA graphs captured for batch sizes 1 to 2\n"),
                             (True, "CUDA graphs captured for batch sizes 1 to 2 (plain and continued by RTC guidance)")):
        caplog.clear()
        captured.model.capture_sampling(guidance=guidance)
        with caplog.at_level(logging.INFO, logger="pi0_torch.runtime.serving"), running_server(captured, max_batch_size=2):
            pass
        assert logged in caplog.text, caplog.text


def test_bad_requests_get_an_error_reply_and_the_server_keeps_serving(
    policy: PI0Policy, client_python: Path, tmp_path: Path
) -> None:
    with running_server(policy) as port:
        result = run_client(client_python, tmp_path, mode="bad", port=port)
    expected = {  # case -> words the error must contain (it names the field and the problem)
        "state_length": ["state", "expected shape [8], got [9]"],
        "state_nan": ["state", "NaN", "[2]"],
        "state_text": ["state", "numeric"],
        "image_2d": ["base_0_rgb", "shape (96, 128)"],
        "image_range": ["base_0_rgb", "[0, 1]", "7"],
        "image_nan": ["base_0_rgb", "NaN"],
        "unknown_camera": ["unknown camera", "top_cam"],
        "missing_prompt": ["prompt", "required"],
        "missing_images": ["missing 'images'"],
        "not_a_dict": ["must be a dict", "list"],
        "garbage_bytes": ["not a valid msgpack message"],
        "text_frame": ["binary", "text frame"],
        "object_dtype": ["unsupported array dtype", "|O"],
        "short_array": ["needs 36864 bytes, got 10"],
    }
    assert sorted(result["errors"]) == sorted(expected)
    for case, words in expected.items():
        error = result["errors"][case]
        assert error is not None, f"{case}: the server answered instead of refusing"
        assert error.startswith("Error in inference server:\ninvalid request: "), f"{case}: {error}"
        for word in words:
            assert word in error, f"{case}: {word!r} not in {error!r}"
        assert result["good_after"][case] == [50, ACTION_DIM], case
    assert result["fresh"] == [50, ACTION_DIM]


def test_a_failing_model_run_sends_one_line_and_the_next_request_works(
    model_dir: Path, client_python: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Server-side failures (here an injected out-of-memory) reach the client as one line; the traceback, with its
    file paths, stays in the server log."""
    policy = PI0Policy.from_pretrained(model_dir, device="cpu", seed=0)
    generate = policy.model.generate_actions
    calls = []

    def fail_once(*args: Any, **kwargs: Any) -> torch.Tensor:
        calls.append(1)
        if len(calls) == 2:  # the first call is the server's warm-up
            raise RuntimeError("injected: CUDA out of memory")
        return generate(*args, **kwargs)

    monkeypatch.setattr(policy.model, "generate_actions", fail_once)
    with caplog.at_level(logging.ERROR, logger="pi0_torch.runtime.serving"), running_server(policy) as port:
        result = run_client(client_python, tmp_path, mode="retry", port=port)
    assert result["error"] == ("Error in inference server:\ninternal server error: RuntimeError: injected: CUDA out of "
                               "memory (see the server log)")
    assert "Traceback (most recent call last)" in caplog.text and "injected: CUDA out of memory" in caplog.text
    assert result["then"] == [50, ACTION_DIM] and len(calls) == 3


def test_a_policy_that_cannot_run_does_not_start_serving(model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The warm-up runs before the socket listens: a model that fails there fails the start, not the robot."""
    policy = PI0Policy.from_pretrained(model_dir, device="cpu")

    def broken(*args: Any, **kwargs: Any) -> torch.Tensor:
        raise RuntimeError("injected: weights on a missing device")

    monkeypatch.setattr(policy.model, "generate_actions", broken)
    with pytest.raises(RuntimeError, match="did not start") as failed:
        with running_server(policy):
            pass
    assert "injected: weights on a missing device" in str(failed.value.__cause__)


def test_libero_client_layout(policy: PI0Policy, client_python: Path, tmp_path: Path) -> None:
    with running_server(policy, obs_format=ObservationFormat.from_preset("libero")) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port, layout="libero")
    assert result["metadata"]["observation_format"]["images"]["base_0_rgb"] == "observation/image"
    assert result["replies"][0]["shape"] == [50, ACTION_DIM] and result["replies"][0]["finite"]


@pytest.mark.parametrize("max_batch_size", [1, 4])
def test_concurrent_clients_and_hang_ups(
    policy: PI0Policy, client_python: Path, tmp_path: Path, max_batch_size: int
) -> None:
    """4 clients x 3 requests plus 2 clients that hang up mid-request: every real request gets its actions."""
    with running_server(policy, max_batch_size=max_batch_size) as port:
        result = run_client(client_python, tmp_path, mode="load", port=port, clients=4, requests=3, rude=2)
        after = run_client(client_python, tmp_path, mode="infer", port=port)  # still serving afterwards
    assert result["failed"] == [] and result["ok"] == 12
    assert 1 <= result["max_batch"] <= max_batch_size
    assert after["replies"][0]["shape"] == [50, ACTION_DIM]


def test_serve_command_health_check_and_clean_sigterm(model_dir: Path) -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "pi0_torch.runtime.serving", "--model", str(model_dir), "--port", "0", "--device", "cpu",
         "--num-steps", "1", "--obs-format", "droid", "--default-prompt", "wipe the table",
         "--metadata", "{\"reset_pose\": [0, 1]}"],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        lines: list[str] = []
        port = None
        while port is None:  # a server that hangs before listening is stopped by pytest's --timeout
            line = process.stdout.readline()
            assert line, "server exited early:\n" + "".join(lines)
            lines.append(line)
            found = re.search(r"on ws://127\.0\.0\.1:(\d+)", line)
            port = int(found.group(1)) if found else None
        assert port is not None, "".join(lines)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=HANG_S) as response:
            assert response.status == 200 and response.read() == b"OK\n"
        with websockets.sync.client.connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
            metadata = unpack_message(ws.recv())
            assert metadata["num_steps"] == 1 and metadata["default_prompt"] == "wipe the table"
            assert metadata["observation_format"]["name"] == "droid" and metadata["reset_pose"] == [0, 1]
            ws.send(pack_message({  # DROID keys and no prompt: the default prompt is used
                "observation/exterior_image_1_left": _frame(), "observation/wrist_image_left": _frame(),
                "observation/joint_position": np.zeros(7), "observation/gripper_position": np.zeros(1),
            }))
            reply = unpack_message(ws.recv())
            assert reply["actions"].shape == (50, ACTION_DIM)
            process.send_signal(signal.SIGTERM)
            with pytest.raises(websockets.ConnectionClosed) as closed:
                ws.recv(timeout=HANG_S)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1001  # going away
        output, _ = process.communicate(timeout=HANG_S)
        lines.append(output)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    log = "".join(lines)
    assert process.returncode == 0, log
    assert "actions 50x7 in" in log and "shutting down" in log and "server stopped after 1 requests" in log
