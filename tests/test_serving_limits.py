"""`pi0-torch serve` under hostile or careless clients (issue 17, items 4-7; issue 38, items 12-15), against a real
server process.

One `pi0-torch serve` process (a random `pi0_small`, 1 Euler step, an API key from the environment, a small connection
cap and idle timeout, the default frame / prompt / image limits) serves most tests of this module over loopback. Its
memory is read with psutil; a well-behaved client measures its latency while others send oversized requests. Every
loop is bounded, and the numbers are printed (`-s`) for docs/reliability.md. The refusal budget and the displacement of
idle connections are checked on servers in this process, with a clock the test moves (counted, not timed); the
latency they keep is measured by `benchmarks/bench_serving.py --flood`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import re
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import psutil
import pytest
import websockets
import websockets.sync.client
from test_serving import (  # noqa: F401  (client_python, model_dir, policy are fixtures)
    ACTION_DIM,
    REPO_ROOT,
    STATE_DIM,
    _numpy_text,
    client_python,
    model_dir,
    policy,
    run_client,
    save_random_model,
)
from websockets.exceptions import InvalidStatus

from conftest import HANG_S
from pi0_torch.runtime import serving
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.serving import (
    MessageError,
    PolicyServer,
    RefusalBudget,
    ServerLimits,
    pack_message,
    unpack_message,
)

# websockets >= 17 warns when connect() is not used as a context manager; these clients are closed explicitly
pytestmark = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used as a context manager:DeprecationWarning")

API_KEY = "test-key-7f3a"
MAX_CONNECTIONS = 6
IDLE_TIMEOUT_S = 8.0  # long enough that a loaded CI machine does not idle out the other tests' clients


class ServeProcess:
    """A running `pi0-torch serve`; its output is drained into `lines` (a full pipe would block the server)."""

    def __init__(self, process: subprocess.Popen[str], port: int, lines: list[str]) -> None:
        self.process, self.port, self.lines = process, port, lines
        self.url = f"ws://127.0.0.1:{port}"

    @property
    def rss_mib(self) -> float:
        return psutil.Process(self.process.pid).memory_info().rss / 2**20

    def log(self) -> str:
        return "".join(self.lines)

    def connect(self, api_key: str | None = API_KEY, **options: Any) -> websockets.sync.client.ClientConnection:
        """A client as openpi's (no compression, no size limit, the key as openpi-client sends it); metadata read."""
        headers = {"Authorization": f"Api-Key {api_key}"} if api_key is not None else None
        ws = websockets.sync.client.connect(self.url, compression=None, max_size=None, additional_headers=headers,
                                            open_timeout=HANG_S, **options)
        unpack_message(ws.recv(timeout=HANG_S))
        return ws


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServeProcess]:
    model = save_random_model(tmp_path_factory.mktemp("served_with_limits"), "pi0_small")
    env = {**os.environ, "PI0_TORCH_API_KEY": API_KEY}
    process = subprocess.Popen(
        [sys.executable, "-m", "pi0_torch.cli", "serve", "--model", str(model), "--port", "0", "--device", "cpu",
         "--num-steps", "1", "--max-connections", str(MAX_CONNECTIONS), "--idle-timeout", str(IDLE_TIMEOUT_S)],
        cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    lines: list[str] = []
    port: list[int] = []
    listening = threading.Event()

    def drain() -> None:
        for line in process.stdout:
            lines.append(line)
            found = re.search(r"on ws://127\.0\.0\.1:(\d+)", line)
            if found:
                port.append(int(found.group(1)))
                listening.set()
        listening.set()  # the process ended

    threading.Thread(target=drain, daemon=True).start()
    try:
        assert listening.wait(HANG_S) and port, "the server did not start:\n" + "".join(lines)
        yield ServeProcess(process, port[0], lines)
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)  # a grace period before the kill, not a limit a test can fail on
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def good_observation(seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    return {
        "images": {"base_0_rgb": rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)},
        "state": rng.standard_normal(STATE_DIM).astype(np.float32),
        "prompt": "pick up the fork",
    }


def ask(ws: websockets.sync.client.ClientConnection, frame: bytes) -> Any:
    """Send one frame; the reply: a dict of actions, or the server's error text."""
    ws.send(frame)
    reply = ws.recv(timeout=HANG_S)
    return reply if isinstance(reply, str) else unpack_message(reply)


# --------------------------------------------------------------------------------------------- access control


def test_api_key_is_checked_in_the_handshake(server: ServeProcess, client_python: Path, tmp_path: Path) -> None:  # noqa: F811
    for key, label in ((None, "no"), ("wrong-key", "wrong")):
        with pytest.raises(InvalidStatus) as refused:
            server.connect(api_key=key)
        assert refused.value.response.status_code == 401
        assert b"Api-Key" in refused.value.response.body
        assert f"refused: {label} API key" in server.log()
    with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=HANG_S) as response:
        assert response.status == 200  # health checks need no key
    # openpi's own client sends the header when given api_key=...
    result = run_client(client_python, tmp_path, mode="infer", port=server.port, api_key=API_KEY)
    assert result["replies"][0]["shape"] == [50, ACTION_DIM]


def test_api_keys_no_client_could_send_are_refused_and_wrong_keys_are_held_off(monkeypatch: pytest.MonkeyPatch) -> None:
    class Policy:  # what PolicyServer reads before serving
        metadata: ClassVar[dict[str, Any]] = {}
        camera_names: ClassVar[list[str]] = ["base_0_rgb"]

    for key, message in (("", "non-empty"), ("a-long-enough-key ", "whitespace around it"), (" " * 20, "whitespace"),
                         ("short-key", "at least 12 characters, got 9"), ("a-long-enough-k\u00e9y", "printable ASCII")):
        with pytest.raises(ValueError, match=message):
            PolicyServer(Policy(), api_key=key)  # type: ignore[arg-type]

    class Connection:  # what the handshake's gate reads of a connection
        state = websockets.protocol.State.OPEN

        def __init__(self, address: str) -> None:
            self.remote_address = (address, 50_000)

        def respond(self, status: int, body: str) -> tuple[int, str]:
            return status, body

    def handshake(address: str, key: str | None) -> int | None:
        headers = websockets.datastructures.Headers({"Authorization": f"Api-Key {key}"} if key else {})
        response = server._admit(Connection(address), websockets.http11.Request("/", headers))  # type: ignore[arg-type]
        return None if response is None else response[0]

    clock = [1000.0]
    monkeypatch.setattr(serving.time, "monotonic", lambda: clock[0])
    server = PolicyServer(Policy(), api_key=API_KEY, limits=ServerLimits(key_failures=3, key_hold_off_s=60))  # type: ignore[arg-type]
    assert [handshake("10.0.0.1", "guess") for _ in range(3)] == [401, 401, 401]
    assert handshake("10.0.0.1", API_KEY) == 429  # held off: not even the right key is checked
    assert handshake("10.0.0.2", API_KEY) is None  # another address is not
    clock[0] += 61
    assert handshake("10.0.0.1", "guess") == 401 and handshake("10.0.0.1", API_KEY) == 429  # one guess a minute
    clock[0] += 61
    assert handshake("10.0.0.1", API_KEY) is None  # the right key resets the count
    assert handshake("10.0.0.1", None) == 401


def test_listening_on_all_interfaces_without_a_key_warns(caplog: pytest.LogCaptureFixture) -> None:
    class Policy:  # what PolicyServer reads before serving
        metadata: ClassVar[dict[str, Any]] = {}
        camera_names: ClassVar[list[str]] = ["base_0_rgb"]

    with caplog.at_level(logging.WARNING, logger="pi0_torch.runtime.serving"):
        PolicyServer(Policy(), host="127.0.0.1")  # type: ignore[arg-type]
        PolicyServer(Policy(), host="0.0.0.0", api_key="a-long-enough-key")  # type: ignore[arg-type]
        assert not caplog.records
        PolicyServer(Policy(), host="0.0.0.0")  # type: ignore[arg-type]
    assert "without an API key" in caplog.text and "PI0_TORCH_API_KEY" in caplog.text
    with pytest.raises(ValueError, match="max_connections must be an integer >= 1, got 0"):
        ServerLimits(max_connections=0)


# --------------------------------------------------------------------------------------------- connections


def test_connection_cap_and_idle_timeout(server: ServeProcess) -> None:
    with contextlib.ExitStack() as stack:
        opened = [stack.enter_context(server.connect()) for _ in range(MAX_CONNECTIONS)]
        with pytest.raises(InvalidStatus) as refused:
            server.connect()
        assert refused.value.response.status_code == 503
        assert f"limit of {MAX_CONNECTIONS} connections" in refused.value.response.body.decode()
        opened[0].close()
        time.sleep(0.2)  # the server sees the close
        with server.connect() as again:  # a freed slot is usable at once
            assert ask(again, pack_message(good_observation()))["actions"].shape == (50, ACTION_DIM)

    idle = server.connect()
    start = time.monotonic()
    with pytest.raises(websockets.ConnectionClosed) as closed:
        idle.recv(timeout=HANG_S)
    waited = time.monotonic() - start
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1000
    assert "idle timeout" in closed.value.rcvd.reason
    assert waited > IDLE_TIMEOUT_S - 0.5  # not before the idle timeout (after it: as late as the machine's load makes it)
    print(f"\nidle connection closed after {waited:.1f} s (--idle-timeout {IDLE_TIMEOUT_S:g})")


# --------------------------------------------------------------------------------------------- requests


def test_error_replies_are_one_line_naming_the_field(server: ServeProcess) -> None:
    cases = {  # observation change -> words the reply must hold
        "empty frame": ({"images": {"base_0_rgb": np.zeros((0, 0, 3), np.uint8)}}, "images['base_0_rgb']: a frame of 0x0 pixels"),
        "huge state": ({"state": np.full(STATE_DIM, 1e308)}, "state: has values beyond float32's range"),
        "long list": ({"state": [0.0] * 20_000}, "holds more than 10000 items"),
        "big frame": ({"images": {"base_0_rgb": np.zeros((1500, 2000, 3), np.uint8)}},
                      "images['base_0_rgb']: a frame of 1500x2000 = 3000000 pixels; this server's limit is 2073600"),
        "prompt no text": ({"prompt": _numpy_text([0xFFFFFFFF])},  # issue 38.15: a traceback before
                           "prompt: expected Unicode text (code points up to U+10FFFF, surrogates excluded), got a "
                           "numpy string array (dtype <U1, shape ()) holding 0xFFFFFFFF"),
    }
    with server.connect() as ws:
        for name, (change, words) in cases.items():
            reply = ask(ws, pack_message({**good_observation(), **change}))
            assert isinstance(reply, str) and reply.startswith("invalid request: ") and words in reply, (name, reply)
            assert "\n" not in reply and "Traceback" not in reply and 'File "' not in reply, (name, reply)
        # a strip of 1x20000 pixels is a valid frame
        strip = {"images": {"base_0_rgb": np.zeros((1, 20_000, 3), np.uint8)}}
        assert ask(ws, pack_message({**good_observation(), **strip}))["actions"].shape == (50, ACTION_DIM)
        # a client that sends without waiting is answered in order (the server buffers one frame and stops reading)
        prompts = ["pick up the fork", "x" * 2_001, "open the drawer"]
        for prompt in prompts:
            ws.send(pack_message({**good_observation(), "prompt": prompt}))
        replies = [ws.recv(timeout=HANG_S) for _ in prompts]
        assert [type(reply) for reply in replies] == [bytes, str, bytes] and "prompt: 2001 characters" in replies[1]


def _hostile(server: ServeProcess, frames: list[bytes], rounds: int, outcomes: list[str]) -> None:
    """Send oversized frames `rounds` times; record how each ended (refusal text, or the close code)."""
    ws = server.connect()
    try:
        for _ in range(rounds):
            for frame in frames:
                try:
                    reply = ask(ws, frame)
                    outcomes.append(reply if isinstance(reply, str) else "answered")
                except (websockets.ConnectionClosed, OSError) as error:
                    code = getattr(getattr(error, "rcvd", None), "code", None)
                    outcomes.append(f"closed {code}")
                    ws = server.connect()
    finally:
        ws.close()


def test_oversized_requests_cost_neither_memory_nor_other_clients_latency(server: ServeProcess) -> None:
    """The issue's attack (prompts of 95 MB and 29 MB) and its near-misses, from two clients, while a good client
    measures its latency; the server's peak RSS is sampled meanwhile."""
    good = pack_message(good_observation())
    base = good_observation(1)
    frames = [
        pack_message({**base, "prompt": "x" * 95_000_000}),  # over the frame limit: closed after the header
        pack_message({**base, "prompt": "pick " * 3_000_000}),  # 15 MB, under the frame limit: refused by length
        pack_message({**base, "images": {"base_0_rgb": np.zeros((1500, 2000, 3), np.uint8)}}),  # over the pixel limit
    ]

    server_ms: list[float] = []  # the server's own time for each good request (frame received -> reply ready)

    def latencies(ws: websockets.sync.client.ClientConnection, count: int) -> list[float]:
        times = []
        for _ in range(count):
            start = time.monotonic()
            reply = ask(ws, good)
            times.append(time.monotonic() - start)
            assert reply["actions"].shape == (50, ACTION_DIM)
            server_ms.append(reply["server_timing"]["infer_ms"])
        return times

    with server.connect() as ws:
        good_peer = f"{ws.local_address[0]}:{ws.local_address[1]}: actions "  # how the server log names its replies
        latencies(ws, 2)  # first allocations
        quiet = latencies(ws, 8)
        del server_ms[:]
        rss_before = server.rss_mib
        peak = [rss_before]
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                with contextlib.suppress(psutil.Error):
                    peak[0] = max(peak[0], server.rss_mib)
                time.sleep(0.02)

        outcomes: list[str] = []
        threads = [threading.Thread(target=sample)]
        threads += [threading.Thread(target=_hostile, args=(server, frames, 3, outcomes)) for _ in range(2)]
        for thread in threads:
            thread.start()
        try:
            attacked = latencies(ws, 8)
        finally:
            for thread in threads[1:]:
                thread.join(timeout=HANG_S)
            stop.set()
            threads[0].join()

    assert len(outcomes) == 2 * 3 * len(frames), outcomes
    for outcome in outcomes:
        assert outcome.startswith(("closed", "invalid request: ")), outcome[:200]
    assert sum(o.startswith("closed") for o in outcomes) >= 6  # the 95 MB frames (close code 1009 when it arrives)
    assert sum("prompt: 15000000 characters; this server's limit is 2000" in o for o in outcomes) == 6
    assert sum("3000000 pixels" in o for o in outcomes) == 6
    growth = peak[0] - rss_before
    # where the server spent the good client's time (its log line for each reply): quiet, then under attack
    timings = [[float(x) for x in re.search(r"prepare ([\d.]+) ms, queued ([\d.]+) ms, model ([\d.]+) ms", line).groups()]
               for line in server.lines if good_peer in line]
    quiet_split, attacked_split = (np.median(part, axis=0) for part in (timings[2:10], timings[-8:]))
    quiet_ms, attacked_ms = 1000 * np.median(quiet), 1000 * np.median(attacked)
    print(f"\ngood client p50 {quiet_ms:.0f} ms quiet, {attacked_ms:.0f} ms (max {1000 * max(attacked):.0f} ms) while two "
          f"clients sent 18 oversized requests (server time p50 {np.median(server_ms):.0f} ms, max "
          f"{max(server_ms):.0f} ms); server p50 prepare / queued / model {quiet_split.round().tolist()} ms quiet, "
          f"{attacked_split.round().tolist()} ms under attack; server RSS {rss_before:.0f} MiB, peak +{growth:.0f} MiB")
    assert growth < 400, f"server RSS grew by {growth:.0f} MiB"
    # generous (CPU is shared with the attack and, on CI, with other jobs); before: 33 ms -> 21 s (issue 17)
    assert max(attacked) < 3 * max(quiet) + 10.0, (quiet, attacked)


def amplifying_frame(outer: int = 10_000, inner: int = 1_600) -> bytes:
    """Issue 28.3's frame: a map whose `images` is a msgpack array of `outer` arrays of `inner` empty arrays. Every
    container is under the 10,000-item limit and the frame (15.3 MiB) under the 16 MiB one, but it decodes into 16
    million lists: 13 s with the event loop blocked and +1.0 GB before."""
    inner_array = b"\xdc" + inner.to_bytes(2, "big") + b"\x90" * inner
    return b"\x81\xa6images" + b"\xdd" + outer.to_bytes(4, "big") + inner_array * outer


def test_a_frame_that_decodes_into_millions_of_objects_stalls_nobody(server: ServeProcess) -> None:
    """Three clients send the amplifying frame while `/healthz` is polled and a good client measures its latency:
    each is refused naming the bound, the health check and the good client do not wait behind them, and the server's
    memory does not grow by the decoded size (before: 12.8 s health check, 13.7 s good client, +1.0 GB; three clients
    +2.3 GB and 38.7 s). The refusals themselves are paced by the refusal budget (each decoding stops at the bound,
    about 100,000 hook calls; the budget lets them take a tenth of a core), so their times are printed, not bounded."""
    frame = amplifying_frame()
    assert 15 * 2**20 < len(frame) < 16 * 2**20
    good = pack_message(good_observation())
    health_s: list[float] = []
    refusals: list[tuple[float, str]] = []
    stop = threading.Event()

    def poll_health() -> None:
        while not stop.is_set():
            start = time.monotonic()
            with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=HANG_S) as response:
                assert response.status == 200
            health_s.append(time.monotonic() - start)
            time.sleep(0.01)

    def attack() -> None:
        with server.connect() as ws:
            start = time.monotonic()
            reply = ask(ws, frame)
            refusals.append((time.monotonic() - start, reply))

    with server.connect() as ws:
        ask(ws, good)
        quiet = []
        for _ in range(4):
            start = time.monotonic()
            ask(ws, good)
            quiet.append(time.monotonic() - start)
        rss_before, peak = server.rss_mib, [server.rss_mib]

        def sample() -> None:
            while not stop.is_set():
                with contextlib.suppress(psutil.Error):
                    peak[0] = max(peak[0], server.rss_mib)
                time.sleep(0.02)

        helpers = [threading.Thread(target=poll_health), threading.Thread(target=sample)]
        attackers = [threading.Thread(target=attack) for _ in range(3)]
        for thread in helpers + attackers:
            thread.start()
        attacked = []
        try:
            while any(thread.is_alive() for thread in attackers) or not attacked:
                start = time.monotonic()
                assert ask(ws, good)["actions"].shape == (50, ACTION_DIM)
                attacked.append(time.monotonic() - start)
        finally:
            for thread in attackers:
                thread.join(timeout=HANG_S)
            stop.set()
            for thread in helpers:
                thread.join(timeout=HANG_S)
    assert len(refusals) == 3
    for seconds, reply in refusals:
        assert isinstance(reply, str) and reply.startswith("invalid request: the message holds more than 100000 objects")
    refused_s = sorted(seconds for seconds, _ in refusals)
    growth = peak[0] - rss_before
    print(f"\namplifying 15.3 MiB frames from 3 clients at once: refused in {1000 * refused_s[1]:.0f} ms p50 (max "
          f"{1000 * refused_s[-1]:.0f} ms, round trip of the 15 MiB upload included); /healthz p50 "
          f"{1000 * np.median(health_s):.0f} ms max {1000 * max(health_s):.0f} ms over {len(health_s)} checks; good client "
          f"{1000 * np.median(quiet):.0f} ms quiet, {1000 * np.median(attacked):.0f} ms (max {1000 * max(attacked):.0f} ms) "
          f"under attack; server RSS {rss_before:.0f} MiB, peak +{growth:.0f} MiB")
    assert max(health_s) < 2.0  # generous for a loaded 2-core machine; before: 12.8 s
    assert growth < 200, f"server RSS grew by {growth:.0f} MiB"  # before: +1.0 GB (one client), +2.3 GB (three)
    assert max(attacked) < 3 * max(quiet) + 2.0, (quiet, attacked)  # before: 13.7 s


def test_two_authorization_headers_are_refused_in_one_line(server: ServeProcess) -> None:
    """Issue 28.8: two `Authorization` headers gave HTTP 500 and a traceback in the server's log."""
    with pytest.raises(InvalidStatus) as refused:
        websockets.sync.client.connect(server.url, additional_headers=[("Authorization", f"Api-Key {API_KEY}"),
                                                                       ("Authorization", f"Api-Key {API_KEY}")],
                                       open_timeout=HANG_S)
    assert refused.value.response.status_code == 401 and b"send one header" in refused.value.response.body
    assert "refused: 2 Authorization headers, not one: API key" in server.log() and "Traceback" not in server.log()


@pytest.mark.parametrize("shape", ["lists of empty lists", "lists of small ints", "maps of empty maps", "lists of maps of lists"])
def test_the_object_bound_stops_any_amplifying_shape_at_the_bound(shape: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every way of making a frame within the per-container limits decode into millions of objects stops at the
    total bound, whatever the nesting: the decoding ends at the first container past it, having built at most one
    more container of `max_items` (counted, not timed); an openpi observation stays far below it."""
    count = 2_000
    if shape == "lists of empty lists":
        frame = amplifying_frame(outer=count, inner=count)
    elif shape == "lists of small ints":
        frame = b"\xdd" + count.to_bytes(4, "big") + (b"\xdc" + count.to_bytes(2, "big") + b"\x01" * count) * count
    elif shape == "maps of empty maps":
        keys = [b"\xa4" + f"{i:04x}".encode() for i in range(count)]
        inner = b"\xde" + count.to_bytes(2, "big") + b"".join(key + b"\x80" for key in keys)
        frame = b"\xdf" + count.to_bytes(4, "big") + b"".join(key + inner for key in keys)
    else:  # lists of maps of lists
        keys = b"".join(b"\xa4" + f"{i:04x}".encode() + b"\x92\x90\x90" for i in range(100))
        frame = b"\xdc" + count.to_bytes(2, "big") + (b"\xde" + (100).to_bytes(2, "big") + keys) * count
    counted: list[int] = []
    add = serving._Decoding.add

    def counting(budget: serving._Decoding, items: int) -> None:
        counted.append(items)
        add(budget, items)

    monkeypatch.setattr(serving._Decoding, "add", counting)
    limits = ServerLimits()
    with pytest.raises(MessageError, match="more than 100000 objects in lists and maps"):
        unpack_message(frame, max_items=10_000, max_objects=limits.max_objects)
    assert sum(counted[:-1]) <= limits.max_objects and counted[-1] <= 2 * 10_000, (len(counted), sum(counted))
    monkeypatch.undo()
    observation = {**good_observation(), "previous_actions": np.zeros((50, ACTION_DIM), np.float32), "noise_seed": 3}
    assert unpack_message(pack_message(observation), max_items=10_000, max_objects=1_000)["noise_seed"] == 3


# --------------------------------------------------------------------------------------------- in-process servers


def _client(port: int, address: str = "127.0.0.1") -> websockets.sync.client.ClientConnection:
    """An openpi-like client of an in-process server, its metadata read; connecting from the loopback `address`."""
    import socket

    raw = socket.create_connection(("127.0.0.1", port), timeout=HANG_S, source_address=(address, 0))
    ws = websockets.sync.client.connect(f"ws://127.0.0.1:{port}", sock=raw, compression=None, max_size=None,
                                        open_timeout=HANG_S)
    unpack_message(ws.recv(timeout=HANG_S))
    return ws


def test_refused_frames_wait_for_the_refusal_budget_one_at_a_time(policy: PI0Policy) -> None:  # noqa: F811
    """Issue 38.12 (clients looping on refused frames slowed a good client from 33 ms to 1.6 s): the frames of a
    connection that is not trusted (its last request was refused, or it has had no actions yet) are decoded only while
    the refusal budget is out of debt, one at a time in arrival order, and each refusal is charged the CPU time it
    cost; a connection whose last request got actions is never held. Counted, with a budget clock that only the test
    moves (the latency this keeps: `benchmarks/bench_serving.py --flood`)."""
    now = [0.0]
    server = PolicyServer(policy, host="127.0.0.1", port=0)
    server._refusals = RefusalBudget(share=0.1, burst_s=1e-9, clock=lambda: now[0])  # any refusal puts it in debt
    good, newcomer_frame = pack_message(good_observation(0)), pack_message(good_observation(7))
    names = {good: "good", newcomer_frame: "newcomer", b"\xc1 1": "bad 1", b"\xc1 2": "bad 2", b"\xc1 3": "bad 3"}
    decoded: list[str] = []  # the frames the server decoded, in order
    prepare = server._prepare

    def counting(frame: bytes) -> Any:
        decoded.append(names[frame])
        return prepare(frame)

    server._prepare = counting  # type: ignore[method-assign]
    refused = "invalid request: not a valid msgpack message"
    with server.serve_in_thread() as port, _client(port) as trusted, _client(port) as attacker:
        assert ask(trusted, good)["actions"].shape == (50, ACTION_DIM)  # trusted from now on
        assert ask(attacker, b"\xc1 1").startswith(refused)  # no debt yet: decoded at once, then charged
        attacker.send(b"\xc1 2")  # in debt: held
        with _client(port) as newcomer:
            newcomer.send(newcomer_frame)  # no actions yet: its turn comes after the attacker's frame
            for _ in range(3):  # a trusted connection is never held, debt or not
                assert ask(trusted, good)["actions"].shape == (50, ACTION_DIM)
            assert decoded == ["good", "bad 1", "good", "good", "good"]
            now[0] += 1.0  # 0.1 s of budget: out of debt
            assert attacker.recv(timeout=HANG_S).startswith(refused)
            assert decoded[-1] == "bad 2"  # and its refusal put the budget in debt again: the newcomer still waits
            now[0] += 1.0
            assert unpack_message(newcomer.recv(timeout=HANG_S))["actions"].shape == (50, ACTION_DIM)
            assert ask(attacker, b"\xc1 3").startswith(refused)  # out of debt: decoded at once, in debt again
            assert ask(newcomer, newcomer_frame)["actions"].shape == (50, ACTION_DIM)  # trusted now: not held
    assert decoded == ["good", "bad 1", "good", "good", "good", "bad 2", "newcomer", "bad 3", "newcomer"]


def test_a_new_client_displaces_the_connection_longest_without_actions(
    policy: PI0Policy, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    """Issue 38.13 (sixteen idle sockets held every slot for the 3,600 s idle timeout): when all connections are
    taken, a new client displaces the one that has gone longest without actions, if longer than the grace period and
    it has no request with the model; otherwise it gets HTTP 503 as before. The grace is 1 ns here, then an hour."""
    server = PolicyServer(policy, host="127.0.0.1", port=0, limits=ServerLimits(max_connections=2, displace_idle_s=1e-9))
    entered, release = threading.Event(), threading.Event()
    infer = policy.infer_prepared

    def held(prepared: Any) -> list[dict[str, Any]]:  # the next model call waits for the test
        if not release.is_set():
            entered.set()
            release.wait(HANG_S)
        return infer(prepared)

    good = pack_message(good_observation())

    def displaced(ws: websockets.sync.client.ClientConnection) -> str:
        with pytest.raises(websockets.ConnectionClosed) as closed:
            ws.recv(timeout=HANG_S)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1000
        return closed.value.rcvd.reason

    with caplog.at_level(logging.WARNING, logger="pi0_torch.runtime.serving"), server.serve_in_thread() as port:
        with _client(port) as idle, _client(port) as busy:
            assert ask(busy, good)["actions"].shape == (50, ACTION_DIM)
            with _client(port) as third:  # all taken: `idle` (no actions since it opened) goes
                assert displaced(idle).startswith("displaced: no actions for 0 s while another client waited")
                assert ask(third, good)["actions"].shape == (50, ACTION_DIM)
                monkeypatch.setattr(policy, "infer_prepared", held)
                busy.send(good)
                assert entered.wait(HANG_S)  # `busy` has a request in the model: it is longest without actions,
                with _client(port) as fourth:  # but `third` is displaced instead
                    assert "displaced: " in displaced(third)
                    release.set()
                    assert unpack_message(busy.recv(timeout=HANG_S))["actions"].shape == (50, ACTION_DIM)
                    assert ask(fourth, good)["actions"].shape == (50, ACTION_DIM)
                    server.limits = dataclasses.replace(server.limits, displace_idle_s=3600.0)
                    with pytest.raises(InvalidStatus) as refused:  # nobody idle for an hour: HTTP 503
                        _client(port)
    assert refused.value.response.status_code == 503
    assert refused.value.response.body.decode() == ("the server holds its limit of 2 connections and none has gone "
                                                   "3600 s without actions; try again later\n")
    assert caplog.text.count("displaced by 127.0.0.1:") == 2 and "(--displace-idle-after 1e-09)" in caplog.text


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--max-message-mib", "inf"], "--max-message-mib must be a finite number > 0 and <= 4096, got inf (float)"),
        (["--max-message-mib", "nan"], "--max-message-mib must be a finite number > 0 and <= 4096, got nan (float)"),
        (["--idle-timeout", "nan"], "--idle-timeout must be a finite number >= 0, got nan (float)"),
        (["--displace-idle-after", "-1"], "--displace-idle-after must be a finite number >= 0, got -1"),
        (["--refused-share", "1.5"], "--refused-share must be a finite number > 0 and <= 1, got 1.5 (float)"),
        (["--seed", str(2**70)], f"--seed must be an integer in [0, {2**63 - 1}], got {2**70} (int)"),
        (["--max-connections", "0"], "--max-connections must be an integer >= 1, got 0 (int)"),
    ],
)
def test_unusable_serve_settings_are_refused_in_one_line_before_loading(
    flags: list[str], words: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 38.14: `--max-message-mib inf` was an OverflowError traceback, nan an unnamed error, a seed of 2**70 a
    traceback after loading the model. Each is refused by its flag's name before the model loads (a missing folder
    here: it would be named if it were read)."""
    with caplog.at_level(logging.ERROR, logger="pi0_torch.runtime.serving"):
        assert serving.main(["--model", "/nonexistent/model", "--port", "0", "--device", "cpu", *flags]) == 1
    errors = [record.getMessage() for record in caplog.records if record.levelno >= logging.ERROR]
    assert len(errors) == 1 and words in errors[0] and "\n" not in errors[0], errors


def test_absurd_thread_counts_are_refused_by_argparse(capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 38.14: `serve --threads 1000000` crashed torch's thread pool (a segfault)."""
    with pytest.raises(SystemExit) as exited:
        serving.main(["--model", "/nonexistent/model", "--threads", "1000000"])
    assert exited.value.code == 2
    assert "argument --threads: expected a number of threads in [1, 1024] or auto, got 1000000" in capsys.readouterr().err


def test_metadata_that_clients_cannot_trust_is_refused_by_name(policy: PI0Policy) -> None:  # noqa: F811
    """Issue 38.14-15: `--metadata` may add keys (openpi's ALOHA client reads `reset_pose`), never replace one the
    server sends itself (clients read the cameras and horizon from there), and holds only values that can be sent
    (integers within 64 bits: a bigger one was an OverflowError traceback)."""
    own = sorted(PolicyServer(policy).metadata)
    for extra in ({"camera_names": ["top"]}, {"action_horizon": 5, "reset_pose": [0]},
                  {key: 1 for key in own}):  # every key the server sends is its own
        with pytest.raises(ValueError) as refused:
            PolicyServer(policy, extra_metadata=extra)
        taken = sorted(set(extra) & set(own))
        assert str(refused.value).startswith(f"extra metadata (serve --metadata): {taken} are the server's own keys")
    with pytest.raises(ValueError, match=r"'reset_pose' cannot be sent to clients \(a 71-bit integer does not fit msgpack's 64 bits\); "
                                         "expected JSON values with integers within 64 bits"):
        PolicyServer(policy, extra_metadata={"reset_pose": [0, 2**70]})
    served = PolicyServer(policy, extra_metadata={"reset_pose": [0, 2**64 - 1], "site": "lab"}).metadata
    assert served["reset_pose"] == [0, 2**64 - 1] and served["camera_names"] == policy.camera_names


def test_one_address_recycling_every_socket_cannot_lock_others_out(policy: PI0Policy,  # noqa: F811
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    """Issue 63, round 5 item 1: 16 held connections, each replaced before it was 30 s old, locked every new client
    out (HTTP 503 at 10, 35, 50 and 65 s: no socket got old enough to be displaced). Now, when all are taken, a new
    client of another address displaces the connection longest without actions of the address holding the most; an
    address never displaces connections of one holding fewer than it plus two."""
    server = PolicyServer(policy, host="127.0.0.1", port=0, limits=ServerLimits(max_connections=4, displace_idle_s=3600.0))
    good = pack_message(good_observation())
    with caplog.at_level(logging.WARNING, logger="pi0_torch.runtime.serving"), server.serve_in_thread() as port:
        held = [_client(port, "127.0.0.2") for _ in range(4)]
        for _ in range(3):  # the holder recycles its sockets; each new one is let in only by displacing one of its own
            held.pop(0).close()
            held.append(_client(port, "127.0.0.2"))
        with _client(port, "127.0.0.1") as newcomer:  # another address: gets its share
            assert ask(newcomer, good)["actions"].shape == (50, ACTION_DIM)
            open_held = [ws for ws in held if _is_open(ws)]
            assert len(open_held) == 3
            with _client(port, "127.0.0.3") as second:  # 127.0.0.2 still holds 3 > 0 + 2: it gives another one up
                assert ask(second, good)["actions"].shape == (50, ACTION_DIM)
                with pytest.raises(InvalidStatus) as refused:  # 2, 1, 1 held: none two more than 127.0.0.1 holds
                    _client(port, "127.0.0.1")
                assert refused.value.response.status_code == 503
                assert ask(newcomer, good)["actions"].shape == (50, ACTION_DIM)  # never displaced by the flood
        for ws in held:
            ws.close()
    assert "displaced by 127.0.0.1:" in caplog.text and "(fair shares)" in caplog.text


def _is_open(ws: websockets.sync.client.ClientConnection) -> bool:
    try:
        ws.ping().wait(HANG_S)
        return True
    except websockets.ConnectionClosed:
        return False


def test_an_address_opening_connections_too_fast_is_held_unread_then_reset(policy: PI0Policy,  # noqa: F811
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 63, round 5 item 2: a connect-upgrade-reset flood starved the model (a good client's median 7.7 to 496
    ms; benchmarks/bench_serving.py --flood-kind reset). An address may open `handshakes_per_s` connections a second
    (a burst of `handshake_burst`); the ones beyond are held unread, then reset (a looping attacker waits instead of
    costing the server an accept after another); other addresses are not affected."""
    monkeypatch.setattr(serving, "HOLD_S", 0.5)
    limits = ServerLimits(handshakes_per_s=0.01, handshake_burst=3)
    with PolicyServer(policy, host="127.0.0.1", port=0, limits=limits).serve_in_thread() as port:
        clients = [_client(port, "127.0.0.2") for _ in range(3)]
        start = time.monotonic()
        with pytest.raises((ConnectionError, websockets.InvalidHandshake, websockets.ConnectionClosed, TimeoutError)):
            _client(port, "127.0.0.2")
        assert time.monotonic() - start >= 0.4  # (held, not answered)
        with _client(port, "127.0.0.1") as other:
            assert ask(other, pack_message(good_observation()))["actions"].shape == (50, ACTION_DIM)
        for ws in clients:
            ws.close()


def test_connection_log_lines_are_limited_per_address() -> None:
    """A flood of 56k connections wrote 15 MB of log (two lines each): at most 5 lines per address, kind and minute;
    the next one logged says how many were left out."""
    now = [0.0]
    budget = serving.LogBudget(lines=5, window_s=60.0, clock=lambda: now[0])
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    serving.logger.addHandler(handler)
    try:
        for _ in range(1000):
            budget.log(logging.WARNING, "10.0.0.9", "opened", "connection from %s opened", "10.0.0.9:1")
        budget.log(logging.WARNING, "10.0.0.8", "opened", "connection from %s opened", "10.0.0.8:1")
        now[0] = 61.0
        budget.log(logging.WARNING, "10.0.0.9", "opened", "connection from %s opened", "10.0.0.9:2")
    finally:
        serving.logger.removeHandler(handler)
    assert records[:5] == ["connection from 10.0.0.9:1 opened"] * 5 and records[5] == "connection from 10.0.0.8:1 opened"
    assert records[6] == "connection from 10.0.0.9:2 opened (and 995 more such lines from 10.0.0.9 left out of the log)"
    assert len(records) == 7
