"""`pi0-torch serve`: a websocket policy server that speaks openpi's protocol.

Robot code written against openpi's client (`openpi-client`, `WebsocketClientPolicy`) talks to this server
unchanged:

- Frames are msgpack; numpy arrays travel as maps `{b"__ndarray__": True, b"data": raw bytes, b"dtype": dtype.str,
  b"shape": [...]}` and numpy scalars as `{b"__npgeneric__": True, b"data": item, b"dtype": dtype.str}`, exactly as
  `openpi_client.msgpack_numpy` packs them ([`pack_message`], [`unpack_message`]).
- On connect the server sends one binary frame: the metadata dict. Then each binary frame in (an observation dict)
  gets one binary frame out: `{"actions": float32 [horizon, robot action dims], "policy_timing": {"infer_ms"},
  "server_timing": {"infer_ms", "prev_total_ms"}}`.
- A request that fails gets one *text* frame instead: `WebsocketClientPolicy.infer` raises
  `RuntimeError("Error in inference server:\\n<text>")` on text frames. The text is one line: bad requests
  (undecodable msgpack, missing fields, wrong shapes or dtypes, NaN/inf, fields over the limits) get the reason,
  naming the field; unexpected server errors get their type and message, and the traceback goes to the server log
  only. Unlike openpi's server, the connection then stays open, so the same client may send its next observation;
  other clients are never affected.
- `GET /healthz` answers `200 OK`, like openpi's server.

Limits ([`ServerLimits`], each a `pi0-torch serve` flag): every request is bounded before any work is done on it
(frame size, list lengths, the total count of decoded objects, prompt characters, image pixels), connections are
capped (a new client displaces a connection of an address that holds two or more more than its own, or the connection
longest without actions once that is idle past a grace period; else it gets HTTP 503) and closed after an idle time,
each address may open only so many connections a second (the ones beyond are reset as they are accepted, before any
handshake work), log lines about connections are limited per address and minute, and with an API key the handshake
needs exactly one
`Authorization: Api-Key <key>` header, as `WebsocketClientPolicy(api_key=...)` sends it (others get HTTP 401 before
reaching the model). Refusing costs CPU too: the frames the server refuses may take a bounded share of one core
([`RefusalBudget`]), and a client whose last request was refused waits for it, so clients looping on bad frames
never starve the model. Numpy strings that are no Unicode text are refused while decoding, naming the field.

A policy never hands back NaN or inf actions: a request whose chunk is not finite gets the one-line reason instead
(`no actions: ...`, see `pi0_torch.runtime.action_safety`); the other requests of its batch get theirs.

Before it listens, the server runs a warm-up chunk on a blank observation, on the thread that will run the model
(with `--compile`, one per batch size up to `max_batch_size`: this is when compilation and CUDA graph capture
happen), so the robot's first request is not slow.

Concurrency: any number of clients may connect. Decoding and preprocessing run in a small thread pool; the model
runs on one dedicated thread, so inference is serialized and the event loop keeps answering pings, health checks and
new connections meanwhile. With `max_batch_size > 1` the observations that queued up while the model was busy are
run together as one batch (each gets its own noise); the default 1 runs them one by one in arrival order. A client
that disconnects while its request is queued is dropped from the queue; one that disconnects while its request runs
just never gets the reply. SIGINT/SIGTERM close the listener and all connections (close code 1001), fail requests
still queued, let a running inference finish, and exit with status 0.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import contextlib
import dataclasses
import hmac
import http
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from pi0_torch.utils.extras import require_extra

require_extra("serve", __name__)
import msgpack
import websockets
from websockets.asyncio.server import Request, Response, ServerConnection, serve
from websockets.protocol import State

from pi0_torch.cli import json_object
from pi0_torch.runtime.action_safety import UnsafeActionsError
from pi0_torch.runtime.observation_formats import ObservationError, ObservationFormat
from pi0_torch.shipped_policy import policy_location
from pi0_torch.utils.limits import MAX_BATCH_SIZE
from pi0_torch.utils.threads import add_threads_argument, set_threads
from pi0_torch.utils.validation import MAX_SEED, check_float, check_int, first_line, one_line

logger = logging.getLogger(__name__)

API_KEY_ENV = "PI0_TORCH_API_KEY"
MAX_MESSAGE_MIB = 4_096  # `--max-message-mib`: more than eight 4K float32 camera frames
ALL_INTERFACES = ("0.0.0.0", "::", "")
MIN_API_KEY_CHARS = 12
HOLD_S = 5.0  # a connection over its address's rate is held unread this long, then reset (`_hold_then_reset`)
MAX_HELD = 256  # connections held so at once; beyond, they are reset at once
MAX_TRACKED_ADDRESSES = 10_000  # addresses whose wrong keys are counted (`ServerLimits.key_failures`)
_ARRAY_KINDS = "biufUS"  # bool, ints, floats, strings; object/void/complex arrays are refused both ways


# --- wire format -------------------------------------------------------------------------------------------------


class MessageError(ValueError):
    """A frame that is not a msgpack message in openpi-client's format."""


def _pack_numpy(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind not in _ARRAY_KINDS:
        raise TypeError(f"cannot send numpy dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    if isinstance(obj, int):  # msgpack packs the others itself
        raise OverflowError(f"a {obj.bit_length()}-bit integer does not fit msgpack's 64 bits")
    raise TypeError(f"cannot pack {type(obj).__name__}")


def _unpack_numpy(obj: dict[Any, Any]) -> Any:
    if b"__ndarray__" in obj:
        dtype = _wire_dtype(obj.get(b"dtype"))
        shape = obj.get(b"shape")
        data = obj.get(b"data")
        if not isinstance(shape, (list, tuple)) or not all(isinstance(n, int) and n >= 0 for n in shape):
            raise MessageError(f"array shape must be a list of non-negative ints, got {shape!r}")
        if not isinstance(data, bytes):
            raise MessageError(f"array data must be bytes, got {type(data).__name__}")
        expected = math.prod(shape) * dtype.itemsize
        if len(data) != expected:
            raise MessageError(f"array of shape {tuple(shape)} and dtype {dtype.str} needs {expected} bytes, "
                               f"got {len(data)}")
        if dtype.kind == "U":
            _check_code_points(data, dtype, tuple(shape))
        return np.frombuffer(data, dtype=dtype).reshape(shape)
    if b"__npgeneric__" in obj:
        dtype = _wire_dtype(obj.get(b"dtype"))
        try:
            return dtype.type(obj.get(b"data"))
        except (TypeError, ValueError) as error:
            raise MessageError(f"bad numpy scalar of dtype {dtype.str}: {error}") from None
    return obj


class _NotText(MessageError):
    """A numpy string array holding values that are no Unicode characters (numpy itself fails on them with a
    SystemError wherever they are read, printed included); the decoder adds where in the message it was."""


def _check_code_points(data: bytes, dtype: np.dtype, shape: tuple[int, ...]) -> None:
    """Refuse UTF-32 string data holding a surrogate or a value past U+10FFFF ([`_NotText`])."""
    code_points = np.frombuffer(data, dtype=np.dtype(np.uint32).newbyteorder(dtype.byteorder))
    bad = (code_points > 0x10FFFF) | ((code_points >= 0xD800) & (code_points <= 0xDFFF))
    if bad.any():
        more = f" and {int(bad.sum()) - 1} more such values" if bad.sum() > 1 else ""
        raise _NotText(f"expected Unicode text (code points up to U+10FFFF, surrogates excluded), got a numpy string "
                       f"array (dtype {dtype.str}, shape {shape}) holding 0x{int(code_points[bad][0]):X}{more}")


def _wire_dtype(spec: Any) -> np.dtype:
    try:
        dtype = np.dtype(spec) if isinstance(spec, str) else None
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in _ARRAY_KINDS:
        raise MessageError(f"unsupported array dtype {spec!r}")
    return dtype


def pack_message(obj: Any) -> bytes:
    """Encode `obj` (dicts, lists, scalars, strings, numpy arrays) as openpi-client's `msgpack_numpy.packb` does.

    ```python
    >>> import numpy as np
    >>> message = unpack_message(pack_message({"actions": np.arange(6, dtype=np.float32).reshape(2, 3)}))
    >>> message["actions"].dtype, message["actions"].shape
    (dtype('float32'), (2, 3))

    ```
    """
    return msgpack.packb(obj, default=_pack_numpy)


class _Decoding:
    """msgpack's hooks for decoding one message: numpy maps become arrays, the objects of every finished list and map
    are counted, and a numpy string that is no text is located.

    Counting stops the decoding once there are more than `limit` objects: nesting can make a small frame decode into
    millions of objects (10,000 lists of 1,600 empty lists fit in 15 MiB), which per-container limits do not catch.
    A numpy string that is no text ([`_NotText`]) is replaced by a marker that each enclosing container passes up,
    adding its key, so that the refusal names the field."""

    def __init__(self, limit: int | None) -> None:
        self.limit, self.count = limit, 1  # the message itself
        self.not_text: _NotText | None = None  # the first numpy string that is no text
        self.path: list[str] = []  # where it is, outermost first
        self.marker = object()  # what stands in for it, then for each container holding it

    def add(self, items: int) -> None:
        self.count += items
        if self.limit is not None and self.count > self.limit:
            raise MessageError(f"the message holds more than {self.limit} objects in lists and maps; send long or "
                               "nested sequences as numpy arrays")

    def on_list(self, items: list[Any]) -> Any:
        self.add(len(items))
        return self.marker if self.not_text is not None and self._holds_marker(enumerate(items), "[{}]") else items

    def on_map(self, items: dict[Any, Any]) -> Any:
        self.add(2 * len(items))
        if self.not_text is not None and self._holds_marker(items.items(), "/{}"):
            return self.marker
        try:
            return _unpack_numpy(items)
        except _NotText as error:
            if self.not_text is not None:
                return None  # a second one: the message is refused for the first
            self.not_text = error
            return self.marker

    def _holds_marker(self, entries: Any, form: str) -> bool:
        for key, value in entries:
            if value is self.marker or key is self.marker:
                self.path.insert(0, form.format(key.decode(errors="replace") if isinstance(key, bytes) else key))
                return True
        return False

    def result(self, message: Any) -> Any:
        """The decoded message, or a [`MessageError`] naming the field of its numpy string that is no text."""
        if self.not_text is None:
            return message
        raise MessageError(f"{''.join(self.path).lstrip('/') or 'the message'}: {self.not_text}")


def unpack_message(data: bytes, max_items: int | None = None, max_objects: int | None = None) -> Any:
    """Decode a frame packed by openpi-client (or [`pack_message`]); raises [`MessageError`] if it is malformed.

    Arrays come back read-only, backed by the frame's bytes. Object, void and complex dtypes are refused, and so are
    string arrays holding values that are no Unicode characters (naming the field). `max_items` bounds the length of
    every list and map before it is built (numpy arrays are not lists); `max_objects` bounds the total count of list
    items, map keys and values while decoding (a message beyond it stops within milliseconds, holding at most one
    more container of `max_items`).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(f"expected a binary frame, got {type(data).__name__}")
    bounds = {} if max_items is None else {"max_array_len": max_items, "max_map_len": max_items}
    decoding = _Decoding(max_objects)
    try:
        message = msgpack.unpackb(data, object_hook=decoding.on_map, list_hook=decoding.on_list, **bounds)
    except MessageError:
        raise
    except Exception as error:  # msgpack raises several unrelated types for corrupt input
        if max_items is not None and "exceeds max_" in str(error):  # "20000 exceeds max_array_len(10000)"
            raise MessageError(f"a list or map holds more than {max_items} items ({error}); send long "
                               "sequences as numpy arrays") from None
        detail = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
        raise MessageError(f"not a valid msgpack message ({one_line(detail, 200)})") from None
    return decoding.result(message)


# --- limits -------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ServerLimits:
    """What one client may ask of the server. Each bound is checked before any work is spent on what it bounds.

    Args:
        max_message_bytes: a larger frame closes its connection with code 1009 (message too big), as soon as its
            header arrives. The default (16 MiB) holds three 1280x720 uint8 camera frames; float frames, bigger
            frames or more cameras need more (`--max-message-mib`).
        max_prompt_chars: a longer prompt is refused before it is tokenized (π0.5 reads at most 200 tokens, a few
            hundred characters of instruction).
        max_image_pixels: a frame with more pixels (height x width) is refused before it is resized (default: 1080p).
        max_items: lists and maps in a message hold at most this many items (checked while decoding; numpy arrays,
            the way frames and states travel, are bounded by `max_message_bytes` instead).
        max_objects: a message decodes into at most this many objects in lists and maps, all nesting levels
            together (an openpi observation holds a few dozen; numpy arrays count as one map each).
        max_connections: connections beyond this many get HTTP 503 in the handshake (the websocket never opens),
            unless one can be displaced (`displace_idle_s`).
        idle_timeout_s: a connection that sends no request for this long is closed (code 1000, reason "idle
            timeout"); None: never. Time spent waiting for the server's own reply does not count.
        displace_idle_s: when all `max_connections` are taken, a new client displaces the connection that has gone
            longest without being sent actions (counted from its last actions, or from its opening), if that is more
            than this many seconds and it has no request with the model; the displaced one is closed (code 1000,
            reason "displaced: ..."). None: never (new clients get HTTP 503 until a slot frees).
        refused_share: the share of one CPU core that decoding and checking the frames the server refuses may take,
            all clients together, on average ([`RefusalBudget`]). The frames of a connection whose last request was
            refused, or that has had no actions yet, wait for this budget and are decoded one at a time, in arrival
            order; connections whose last request got actions are never held.
        refused_burst_s: how much refused work the budget allows at once before it holds frames (seconds of CPU).
        key_failures: with an API key, an address whose handshakes brought a missing or wrong key this many times in a
            row is held off: its handshakes get HTTP 429, unchecked, until `key_hold_off_s` after its last failure
            (guessing keys runs at a few per minute instead of about a thousand a second). A right key resets its
            count.
        key_hold_off_s: see `key_failures`.
        handshakes_per_s: connections one address may open per second, on average (`handshake_burst` at once); the
            ones beyond are reset as they are accepted, before their handshake is read, so a flood of connections
            (connect, upgrade, a large frame begun, reset) costs the server little of the CPU the model runs on.
        handshake_burst: see `handshakes_per_s` (an evaluation of `--num-envs 16` opens 16 at once).
    """

    max_message_bytes: int = 16 * 2**20
    max_prompt_chars: int = 2_000
    max_image_pixels: int = 1920 * 1080
    max_items: int = 10_000
    max_objects: int = 100_000
    max_connections: int = 16
    idle_timeout_s: float | None = 3600.0
    displace_idle_s: float | None = 30.0
    refused_share: float = 0.1
    refused_burst_s: float = 0.05
    key_failures: int = 10
    key_hold_off_s: float = 60.0
    handshakes_per_s: float = 20.0
    handshake_burst: int = 40

    def __post_init__(self) -> None:
        for name in ("max_message_bytes", "max_prompt_chars", "max_image_pixels", "max_items", "max_objects",
                     "max_connections", "key_failures", "handshake_burst"):
            check_int(name, getattr(self, name), minimum=1)
        for name in ("idle_timeout_s", "displace_idle_s"):
            if getattr(self, name) is not None:
                check_float(name, getattr(self, name), minimum=0.0, exclusive_minimum=True)
        check_float("refused_share", self.refused_share, minimum=0.0, maximum=1.0, exclusive_minimum=True)
        check_float("refused_burst_s", self.refused_burst_s, minimum=0.0, exclusive_minimum=True)
        check_float("key_hold_off_s", self.key_hold_off_s, minimum=0.0)
        check_float("handshakes_per_s", self.handshakes_per_s, minimum=0.0, exclusive_minimum=True)

    def check(self, observation: Mapping[str, Any]) -> None:
        """Refuse (with [`ObservationError`]) a default-layout observation whose prompt or frames exceed the limits."""
        prompt = observation.get("prompt")
        if isinstance(prompt, str) and len(prompt) > self.max_prompt_chars:
            raise ObservationError(f"prompt: {len(prompt)} characters; this server's limit is {self.max_prompt_chars} "
                                   "(pi0-torch serve --max-prompt-chars)")
        images = observation.get("images")
        for camera, frame in (images.items() if isinstance(images, Mapping) else ()):
            shape = frame.shape if isinstance(frame, np.ndarray) else ()
            if len(shape) == 3 and 3 in (shape[0], shape[-1]):  # [H, W, 3] or [3, H, W]; others: the processor says
                height, width = shape[:2] if shape[-1] == 3 else shape[1:]
                if height * width > self.max_image_pixels:
                    raise ObservationError(f"images[{camera!r}]: a frame of {height}x{width} = {height * width} pixels; "
                                           f"this server's limit is {self.max_image_pixels} (pi0-torch serve "
                                           "--max-image-pixels)")


class RefusalBudget:
    """A token bucket of CPU seconds for the frames the server refuses, shared by all connections: it holds at most
    `burst_s`, refills at `share` seconds per second, and each refused frame takes what its decoding and checking
    cost. A frame that may be refused waits until the bucket is no longer in debt, so refusing takes at most `share`
    of one core on average, however many clients loop on refused frames, and the model's thread keeps the rest.

    ```python
    >>> now = [0.0]
    >>> budget = RefusalBudget(share=0.1, burst_s=0.05, clock=lambda: now[0])
    >>> budget.delay()  # a full bucket: no wait
    0.0
    >>> budget.charge(0.06)  # a refusal that cost 60 ms of CPU: 10 ms in debt
    >>> round(budget.delay(), 6)  # 10 ms at 0.1 s per second
    0.1
    >>> now[0] = 0.1
    >>> budget.delay()
    0.0

    ```
    """

    def __init__(self, share: float, burst_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.share, self.burst_s, self.clock = share, burst_s, clock
        self._level, self._at = burst_s, clock()
        self._lock = threading.Lock()  # charged from the prepare threads, read on the event loop

    def _refill(self) -> None:
        now = self.clock()
        self._level, self._at = min(self.burst_s, self._level + (now - self._at) * self.share), now

    def charge(self, seconds: float) -> None:
        """Take the CPU seconds one refused frame cost."""
        with self._lock:
            self._refill()
            self._level -= seconds

    def delay(self) -> float:
        """Seconds until the bucket is out of debt (0: a frame may be decoded now)."""
        with self._lock:
            self._refill()
            return max(0.0, -self._level / self.share)


class AddressBuckets:
    """A token bucket per address: `take(address)` is True while that address has spent fewer than `burst` tokens
    refilled at `rate` per second. Bounded memory: beyond `MAX_TRACKED_ADDRESSES` the fullest buckets (addresses that
    have been quiet longest) are forgotten first.

    ```python
    >>> now = [0.0]
    >>> buckets = AddressBuckets(rate=1.0, burst=2, clock=lambda: now[0])
    >>> [buckets.take("10.0.0.1") for _ in range(3)], buckets.take("10.0.0.2")
    ([True, True, False], True)
    >>> now[0] = 1.0
    >>> buckets.take("10.0.0.1")
    True

    ```
    """

    def __init__(self, rate: float, burst: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate, self.burst, self.clock = rate, burst, clock
        self._buckets: dict[str, tuple[float, float]] = {}  # address -> (tokens, when)

    def take(self, address: str) -> bool:
        now = self.clock()
        tokens, when = self._buckets.get(address, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - when) * self.rate)
        allowed = tokens >= 1.0
        self._buckets[address] = (tokens - 1.0 if allowed else tokens, now)
        if len(self._buckets) > MAX_TRACKED_ADDRESSES:
            quiet = sorted(self._buckets, key=lambda key: now - self._buckets[key][1])[-MAX_TRACKED_ADDRESSES // 10:]
            for key in quiet:
                del self._buckets[key]
        return allowed


class LogBudget:
    """At most `lines` log lines a minute per address and kind of event; the others are counted, and the next line
    logged for that address and kind says how many were left out (a flood of 56k connections wrote 15 MB of log)."""

    def __init__(self, lines: int = 5, window_s: float = 60.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.lines, self.window_s, self.clock = lines, window_s, clock
        self._counts: dict[tuple[str, str], tuple[float, int, int]] = {}  # (address, kind) -> (start, logged, left out)

    def log(self, level: int, address: str, kind: str, message: str, *args: Any) -> None:
        now = self.clock()
        start, logged, left_out = self._counts.get((address, kind), (now, 0, 0))
        if now - start >= self.window_s:
            start, logged = now, 0
        if logged >= self.lines:
            self._counts[(address, kind)] = (start, logged, left_out + 1)
            return
        if left_out:
            message += f" (and {left_out} more such lines from %s left out of the log)"
            args = (*args, address)
        logger.log(level, message, *args)
        self._counts[(address, kind)] = (start, logged + 1, 0)
        if len(self._counts) > MAX_TRACKED_ADDRESSES:
            del self._counts[min(self._counts, key=lambda key: self._counts[key][0])]


# --- the server --------------------------------------------------------------------------------------------------


class ServedPolicy(Protocol):
    """What the server needs from a policy ([`pi0_torch.runtime.policy.PI0Policy`] is one)."""

    @property
    def metadata(self) -> dict[str, Any]: ...

    @property
    def camera_names(self) -> Sequence[str]: ...

    def prepare(self, observation: dict[str, Any]) -> Any:
        """Validate one default-layout observation and turn it into model inputs; raises ObservationError."""

    def infer_prepared(self, prepared: Sequence[Any]) -> list[dict[str, Any]]:
        """Run the model on prepared observations (a batch) and return one action dict per observation."""

    def warmup(self, max_batch_size: int) -> float:
        """Run on a blank observation, for the batch sizes up to `max_batch_size` that need it (compilation, first
        allocations); returns its seconds."""


class _ShuttingDown(RuntimeError):
    pass


@dataclasses.dataclass
class _Client:
    """What the server keeps of an admitted connection."""

    last_served: float  # when it was last sent actions, or opened (time.monotonic())
    trusted: bool = False  # its last request got actions: its frames are decoded at once
    with_model: bool = False  # a request of it is queued for or running in the model


@dataclasses.dataclass
class _Job:
    prepared: Any
    future: asyncio.Future[dict[str, Any]]
    started: float = 0.0
    finished: float = 0.0
    batch_size: int = 0


class PolicyServer:
    """Serves a policy over openpi's websocket protocol (see the module docstring for the protocol).

    Args:
        policy: what to serve, e.g. a [`PI0Policy`].
        host, port: where to listen (port 0 picks a free port).
        obs_format: the observation layout clients send (default: pi0-torch's own).
        max_batch_size: run up to this many queued observations as one batch (1: strictly one at a time).
        extra_metadata: merged into the metadata sent on connect (openpi's ALOHA client reads `reset_pose`).
        limits: bounds on messages, prompts, frames, connections and idle time ([`ServerLimits`]).
        api_key: when set, the websocket handshake must carry `Authorization: Api-Key <api_key>` (what
            `WebsocketClientPolicy(api_key=...)` sends); others get HTTP 401. `/healthz` stays open. Without a key,
            listening on all interfaces logs a warning.

    ```python
    server = PolicyServer(PI0Policy.from_pretrained("converted/pi0_libero"),
                          obs_format=ObservationFormat.from_preset("libero"))
    server.serve_forever()  # until SIGINT/SIGTERM
    ```
    """

    def __init__(
        self,
        policy: ServedPolicy,
        host: str = "127.0.0.1",
        port: int = 8000,
        obs_format: ObservationFormat | None = None,
        max_batch_size: int = 1,
        extra_metadata: dict[str, Any] | None = None,
        limits: ServerLimits | None = None,
        api_key: str | None = None,
    ) -> None:
        check_int("max_batch_size", max_batch_size, minimum=1, maximum=MAX_BATCH_SIZE)  # (a compiled warm-up runs each)
        check_int("port", port, minimum=0, maximum=65_535)
        if api_key is not None:
            check_api_key(api_key)
        self.policy = policy
        self.host = host
        self.port = port
        self.obs_format = obs_format or ObservationFormat.from_preset("default")
        self.obs_format.check_cameras(policy.camera_names)
        self.max_batch_size = max_batch_size
        self.limits = limits or ServerLimits()
        self._expected_authorization = f"Api-Key {api_key}".encode() if api_key is not None else None
        if api_key is None and host in ALL_INTERFACES:
            logger.warning("listening on all interfaces (%r) without an API key: anyone who reaches port %d can run "
                           "the policy; set --api-key or %s", host, port, API_KEY_ENV)
        own = {**policy.metadata, "observation_format": self.obs_format.describe(), "max_batch_size": max_batch_size}
        self.metadata = {**own, **_checked_extra_metadata(extra_metadata or {}, own)}
        self._packed_metadata = pack_message(self.metadata)
        self._queue: asyncio.Queue[_Job] | None = None
        self._stopping = False
        self._requests_served = 0
        self._clients: dict[ServerConnection, _Client] = {}  # handshakes let through, until their connection closes
        self._key_failures: dict[str, tuple[int, float]] = {}  # address -> (wrong keys in a row, time of the last)
        self._closing: set[asyncio.Task[None]] = set()  # displaced connections being closed
        self._refusals = RefusalBudget(self.limits.refused_share, self.limits.refused_burst_s)
        self._untrusted_turn: asyncio.Lock | None = None  # one untrusted frame decoded at a time (FIFO)
        self._handshakes = AddressBuckets(self.limits.handshakes_per_s, self.limits.handshake_burst)
        self._held: set[asyncio.BaseTransport] = set()  # connections over their address's rate, held unread
        self._log = LogBudget()

    @contextlib.contextmanager
    def serve_in_thread(self, timeout: float = 600.0) -> Iterator[int]:
        """Serve from a background thread while the `with` block runs; yields the bound port (use port 0 for a free
        one) once the policy's warm-up ran and the socket listens, waiting at most `timeout` seconds for that. For
        notebooks, tests and benchmarks; signals are left to the caller.

        ```python
        with PolicyServer(policy, port=0).serve_in_thread() as port:
            client = WebsocketClientPolicy("127.0.0.1", port)
        ```
        """
        loop = asyncio.new_event_loop()
        stop = asyncio.Event()
        ready = threading.Event()
        bound: list[int] = []
        failure: list[BaseException] = []

        def on_ready(port: int) -> None:
            bound.append(port)
            ready.set()

        def target() -> None:
            try:
                loop.run_until_complete(self.serve(stop, on_ready))
            except BaseException as error:  # surfaced in the caller's thread below
                failure.append(error)
                ready.set()

        thread = threading.Thread(target=target, name="pi0-policy-server", daemon=True)
        thread.start()
        if not ready.wait(timeout) or failure:
            raise RuntimeError(f"policy server did not start on {self.host}:{self.port}") from (failure or [None])[0]
        try:
            yield bound[0]
        finally:
            loop.call_soon_threadsafe(stop.set)
            thread.join(timeout)
            if not thread.is_alive():
                loop.close()

    def serve_forever(self) -> int:
        """Serve until SIGINT or SIGTERM, then shut down cleanly; returns the exit status (0)."""
        return asyncio.run(self._serve_until_signal())

    async def _serve_until_signal(self) -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await self.serve(stop)
        return 0

    async def serve(self, stop: asyncio.Event, on_ready: Callable[[int], None] | None = None) -> None:
        """Serve until `stop` is set. `on_ready(port)` is called once the socket listens (useful with port 0)."""
        self._queue = asyncio.Queue()
        self._untrusted_turn = asyncio.Lock()
        self._stopping = False
        prepare_pool = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="pi0-prepare")
        model_thread = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="pi0-model")
        worker: asyncio.Task[None] | None = None
        try:
            # on the model thread, where every later inference runs (CUDA graphs are recorded per thread)
            seconds = await asyncio.get_running_loop().run_in_executor(model_thread, self.policy.warmup, self.max_batch_size)
            graphs = ""
            if getattr(self.policy, "captured", False):
                rtc_method = getattr(self.policy, "rtc_method", None)  # (a policy that continues chunks)
                rtc_too = rtc_method is not None and self.policy.model.replays_graphs(rtc_method)
                continued = f" (plain and continued by RTC {rtc_method})" if rtc_too else ""
                graphs = f"; CUDA graphs captured for batch sizes 1 to {self.max_batch_size}{continued}"
            logger.info("warm-up in %.1f s%s", seconds, graphs)
            worker = asyncio.create_task(self._run_model(model_thread))
            async with serve(
                lambda ws: self._handle(ws, prepare_pool),
                self.host,
                self.port,
                compression=None,
                max_size=self.limits.max_message_bytes,
                max_queue=1,  # one request at a time per connection: never buffer a pipelining client's frames
                process_request=self._admit,
                create_connection=_gated_connection(self),
            ) as server:
                port = next(iter(server.sockets)).getsockname()[1]
                logger.info("serving %s on ws://%s:%d (health check: http://%s:%d/healthz)",
                            self.metadata.get("model_type", "policy"), self.host, port, self.host, port)
                if on_ready is not None:
                    on_ready(port)
                await stop.wait()
                logger.info("shutting down: closing connections")
                self._stopping = True
                for transport in list(self._held):  # (connections held unread: `_hold_then_reset`)
                    transport.abort()
                self._held.clear()
                self._fail_queued(_ShuttingDown("server is shutting down"))
                server.close()
                await server.wait_closed()
        finally:
            if worker is not None:
                worker.cancel()
                await asyncio.gather(worker, return_exceptions=True)
            model_thread.shutdown(wait=True)  # a running inference finishes before we return
            prepare_pool.shutdown(wait=True)
            logger.info("server stopped after %d requests", self._requests_served)

    def _admit(self, connection: ServerConnection, request: Request) -> Response | None:
        """The handshake's gate: `/healthz` answers 200; a missing or wrong API key gets 401, a full server 503."""
        if request.path == "/healthz":  # as openpi's server; open to all (load balancers carry no key)
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        peer = _peer(connection)
        if self._expected_authorization is not None:
            address = connection.remote_address[0] if connection.remote_address else "?"
            failures, last = self._key_failures.get(address, (0, 0.0))
            now = time.monotonic()
            if failures >= self.limits.key_failures and now - last < self.limits.key_hold_off_s:
                return connection.respond(http.HTTPStatus.TOO_MANY_REQUESTS, f"{failures} handshakes in a row from "
                                          f"this address had no or a wrong API key; try again in "
                                          f"{self.limits.key_hold_off_s - (now - last):.0f} s\n")
            headers = request.headers.get_all("Authorization")
            given = headers[0].encode() if len(headers) == 1 else b""
            if not hmac.compare_digest(given, self._expected_authorization):
                self._key_failures[address] = (failures + 1, now)
                if len(self._key_failures) > MAX_TRACKED_ADDRESSES:  # (forget the oldest: bounded memory)
                    del self._key_failures[min(self._key_failures, key=lambda key: self._key_failures[key][1])]
                problem = "wrong" if given else "no" if not headers else f"{len(headers)} Authorization headers, not one:"
                if failures + 1 == self.limits.key_failures:
                    logger.warning("%s: refused: %s API key; %d in a row from %s: held off for %g s", peer, problem,
                                   failures + 1, address, self.limits.key_hold_off_s)
                elif failures < self.limits.key_failures:
                    self._log.log(logging.WARNING, address, "key", "%s: refused: %s API key", peer, problem)
                return connection.respond(http.HTTPStatus.UNAUTHORIZED, "missing or wrong API key: send one header "
                                          "'Authorization: Api-Key <key>' (WebsocketClientPolicy(api_key=...))\n")
            self._key_failures.pop(address, None)
        self._clients = {c: client for c, client in self._clients.items() if c.state is not State.CLOSED}
        full = len(self._clients) >= self.limits.max_connections
        if full and not self._displace_crowding(connection, peer) and not self._displace_idle(peer):
            self._log.log(logging.WARNING, _address(connection), "full", "%s: refused: %d connections open "
                          "(--max-connections)", peer, len(self._clients))
            idle = (f" and none has gone {self.limits.displace_idle_s:g} s without actions"
                    if self.limits.displace_idle_s is not None else "")
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, f"the server holds its limit of "
                                      f"{self.limits.max_connections} connections{idle}; try again later\n")
        self._clients[connection] = _Client(last_served=time.monotonic())
        return None

    def _hold_then_reset(self, transport: asyncio.BaseTransport) -> None:
        """A connection over its address's rate: read nothing of it and reset it after `HOLD_S` (a client looping on
        connect-and-send waits for the reply meanwhile, instead of costing the server one accept after another), or
        at once when `MAX_HELD` are held already or the server stops."""
        if len(self._held) >= MAX_HELD or self._stopping:
            transport.abort()
            return
        transport.pause_reading()  # type: ignore[attr-defined]
        self._held.add(transport)

        def reset() -> None:
            self._held.discard(transport)
            transport.abort()

        asyncio.get_running_loop().call_later(HOLD_S, reset)

    def _displace_crowding(self, newcomer: ServerConnection, peer: str) -> bool:
        """Fair shares when every connection is taken: a new client whose address holds fewer connections than
        another address by two or more displaces that address's connection longest without actions (that has no
        request with the model). One address recycling all the sockets before any is idle long enough to be displaced
        (`displace_idle_s`) locked every other client out; now it keeps at most its share. True if one was displaced."""
        held: dict[str, list[tuple[float, ServerConnection]]] = {}
        now = time.monotonic()
        for connection, client in self._clients.items():
            if connection.state is State.OPEN or connection.state is State.CONNECTING:
                held.setdefault(_address(connection), []).append((now - client.last_served, connection))
        crowded = max(held, key=lambda address: len(held[address]), default=None)
        mine = len(held.get(_address(newcomer), []))
        if crowded is None or len(held[crowded]) < mine + 2:
            return False
        candidates = [(seconds, connection) for seconds, connection in held[crowded]
                      if not self._clients[connection].with_model]
        if not candidates:
            return False
        seconds, victim = max(candidates, key=lambda entry: entry[0])
        self._displace(victim, peer, f"displaced: this address held {len(held[crowded])} of the server's "
                       f"{self.limits.max_connections} connections while another address waited",
                       f"its address held {len(held[crowded])} of the {self.limits.max_connections} connections, "
                       f"{peer}'s {mine} (fair shares)")
        return True

    def _displace(self, victim: ServerConnection, peer: str, reason: str, note: str) -> None:
        """Drop `victim` from the clients (its slot is free at once) and close it with code 1000 and `reason` (sent
        to it); `note`: why, for the log."""
        del self._clients[victim]
        self._log.log(logging.WARNING, _address(victim), "displaced", "%s: displaced by %s: %s", _peer(victim), peer, note)
        closing = asyncio.get_running_loop().create_task(victim.close(1000, reason[:123]))  # (at most 123 bytes)
        self._closing.add(closing)
        closing.add_done_callback(self._closing.discard)

    def _displace_idle(self, peer: str) -> bool:
        """Close the open connection that has gone longest without actions, if longer than `displace_idle_s` and
        it has no request with the model; True if one was displaced (its slot is free at once)."""
        if self.limits.displace_idle_s is None:
            return False
        now = time.monotonic()
        idle = [(now - client.last_served, connection) for connection, client in self._clients.items()
                if connection.state is State.OPEN and not client.with_model]
        if not idle:
            return False
        seconds, victim = max(idle, key=lambda entry: entry[0])
        if seconds <= self.limits.displace_idle_s:
            return False
        self._displace(victim, peer, f"displaced: no actions for {seconds:.0f} s while another client waited for one "
                       f"of the server's {self.limits.max_connections} connections",
                       f"no actions for {seconds:.0f} s while all {self.limits.max_connections} connections were "
                       f"taken (--displace-idle-after {self.limits.displace_idle_s:g})")
        return True

    async def _handle(self, ws: ServerConnection, prepare_pool: concurrent.futures.Executor) -> None:
        peer = _peer(ws)
        self._log.log(logging.INFO, _address(ws), "opened", "connection from %s opened", peer)
        prev_total_ms: float | None = None
        idle_timeout = self.limits.idle_timeout_s
        try:
            await ws.send(self._packed_metadata)
            while True:
                try:
                    frame = await asyncio.wait_for(ws.recv(), idle_timeout)  # cancelling recv() loses no data
                except asyncio.TimeoutError:
                    logger.info("%s: no request for %g s: closing (--idle-timeout)", peer, idle_timeout)
                    await ws.close(1000, f"idle timeout: no request for {idle_timeout:g} s")
                    break
                received = time.monotonic()
                reply = await self._answer(frame, ws, peer, prepare_pool)
                if reply is None:  # the client went away while its request waited
                    break
                if isinstance(reply, dict):
                    reply["server_timing"] = {"infer_ms": (time.monotonic() - received) * 1000}
                    if prev_total_ms is not None:
                        reply["server_timing"]["prev_total_ms"] = prev_total_ms
                    await ws.send(pack_message(reply))
                else:
                    await ws.send(reply)
                prev_total_ms = (time.monotonic() - received) * 1000
        except websockets.ConnectionClosed:
            pass
        self._log.log(logging.INFO, _address(ws), "closed", "connection from %s closed", peer)

    async def _answer(
        self, frame: Any, ws: ServerConnection, peer: str, prepare_pool: concurrent.futures.Executor
    ) -> dict[str, Any] | str | None:
        """The reply to one frame: an action dict, an error text, or None when the client disconnected meanwhile."""
        received = time.monotonic()
        loop = asyncio.get_running_loop()
        client = self._clients.get(ws) or _Client(last_served=received)  # (none: displaced meanwhile)
        try:
            prepared = await self._decode(frame, client.trusted, prepare_pool)
            prepared_at = time.monotonic()
            if self._stopping or self._queue is None:
                raise _ShuttingDown("server is shutting down")
            job = _Job(prepared, loop.create_future())
            self._queue.put_nowait(job)
            client.with_model = True
            closed = asyncio.ensure_future(ws.wait_closed())
            try:
                await asyncio.wait({job.future, closed}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                closed.cancel()
                client.with_model = False
            if not job.future.done():
                job.future.cancel()  # still queued: the model worker skips it
                logger.info("%s: disconnected before its actions were ready", peer)
                return None
            reply = job.future.result()
        except (MessageError, ObservationError) as error:
            client.trusted = False
            reason = one_line(str(error))
            logger.warning("%s: bad request: %s", peer, reason)
            return f"invalid request: {reason}"
        except UnsafeActionsError as error:  # withheld by the policy: the reason, no traceback
            reason = one_line(str(error))
            logger.error("%s: no actions: %s", peer, reason)
            return f"no actions: {reason}"
        except _ShuttingDown as error:
            return str(error)
        except Exception as error:  # the traceback stays in the server log
            logger.exception("%s: request failed", peer)
            return f"internal server error: {type(error).__name__}: {one_line(first_line(error))} (see the server log)"
        self._requests_served += 1
        client.trusted, client.last_served = True, time.monotonic()
        logger.info(
            "%s: actions %s in %.1f ms (prepare %.1f ms, queued %.1f ms, model %.1f ms, batch %d)",
            peer, "x".join(map(str, np.shape(reply.get("actions")))), (job.finished - received) * 1000,
            (prepared_at - received) * 1000, (job.started - prepared_at) * 1000,
            (job.finished - job.started) * 1000, job.batch_size,
        )
        return reply

    async def _decode(self, frame: Any, trusted: bool, prepare_pool: concurrent.futures.Executor) -> Any:
        """Decode and check one frame on the prepare threads. The frame of a connection that is not trusted (its last
        request was refused, or it has had no actions yet) may well be refused: it waits its turn (one at a time, in
        arrival order) and the refusal budget first, so that refusing never takes the model's CPU."""
        loop = asyncio.get_running_loop()
        if trusted:
            return await loop.run_in_executor(prepare_pool, self._prepare, frame)
        assert self._untrusted_turn is not None
        async with self._untrusted_turn:
            while (delay := self._refusals.delay()) > 0:
                if self._stopping:
                    raise _ShuttingDown("server is shutting down")
                await asyncio.sleep(delay)
            return await loop.run_in_executor(prepare_pool, self._prepare, frame)

    def _prepare(self, frame: Any) -> Any:
        """One frame to model inputs (on a prepare thread); a refused frame's CPU time is charged to the budget."""
        started = time.thread_time()
        try:
            if isinstance(frame, str):
                raise MessageError("expected a binary msgpack frame, got a text frame")
            message = unpack_message(frame, max_items=self.limits.max_items, max_objects=self.limits.max_objects)
            observation = self.obs_format.to_default(message)
            self.limits.check(observation)
            return self.policy.prepare(observation)
        except (MessageError, ObservationError):
            self._refusals.charge(time.thread_time() - started)
            raise

    async def _run_model(self, model_thread: concurrent.futures.Executor) -> None:
        """The only place the model runs: takes queued jobs (up to max_batch_size at once) in arrival order."""
        assert self._queue is not None
        loop = asyncio.get_running_loop()
        while True:
            jobs = [await self._queue.get()]
            while len(jobs) < self.max_batch_size and not self._queue.empty():
                jobs.append(self._queue.get_nowait())
            jobs = [job for job in jobs if not job.future.done()]  # their clients went away
            if not jobs:
                continue
            started = time.monotonic()
            try:
                replies = await loop.run_in_executor(
                    model_thread, self.policy.infer_prepared, [job.prepared for job in jobs]
                )
            except UnsafeActionsError as error:  # only the requests whose chunks were withheld fail
                outcomes: list[dict[str, Any] | BaseException] = list(error.outcomes) or [error] * len(jobs)
            except Exception as error:
                outcomes = [error] * len(jobs)
            else:
                outcomes = list(replies)
            finished = time.monotonic()
            for job, outcome in zip(jobs, outcomes):
                job.started, job.finished, job.batch_size = started, finished, len(jobs)
                if job.future.done():
                    continue
                if isinstance(outcome, BaseException):
                    job.future.set_exception(outcome)
                else:
                    job.future.set_result(outcome)

    def _fail_queued(self, error: BaseException) -> None:
        assert self._queue is not None
        while not self._queue.empty():
            job = self._queue.get_nowait()
            if not job.future.done():
                job.future.set_exception(error)


def _checked_extra_metadata(extra: Mapping[Any, Any], own: Mapping[str, Any]) -> dict[str, Any]:
    """`extra_metadata` if no key is one the server sends itself (clients read those: a model's cameras or horizon
    must not be overridden) and every value can be sent; else `ValueError` naming the key."""
    taken = sorted(str(key) for key in extra if key in own)
    if taken:
        raise ValueError(f"extra metadata (serve --metadata): {taken} are the server's own keys, which clients read "
                         f"from the model and the server's settings; expected other keys (the server's: {sorted(own)})")
    for key, value in extra.items():
        try:
            pack_message(value)
        except (OverflowError, TypeError, ValueError) as error:
            raise ValueError(f"extra metadata (serve --metadata): {key!r} cannot be sent to clients ({error}); "
                             "expected JSON values with integers within 64 bits") from None
    return dict(extra)


def check_api_key(key: str) -> None:
    """Refuse, in one line, a key no client could send or that is easy to guess: empty, shorter than
    `MIN_API_KEY_CHARS`, with whitespace around it (an HTTP header loses it), or not printable ASCII."""
    if not isinstance(key, str) or not key:
        raise ValueError("--api-key must be a non-empty string (or unset for no access control)")
    if key != key.strip():
        raise ValueError("--api-key has whitespace around it, which an HTTP header drops: no client could send it; "
                         "remove it (a shell variable with a trailing newline or space is the usual cause)")
    if not all(" " <= char <= "~" for char in key):
        raise ValueError("--api-key must be printable ASCII (an HTTP header carries nothing else)")
    if len(key) < MIN_API_KEY_CHARS:
        raise ValueError(f"--api-key must be at least {MIN_API_KEY_CHARS} characters, got {len(key)} (e.g. "
                         "python -c 'import secrets; print(secrets.token_urlsafe(24))')")


def _peer(connection: ServerConnection) -> str:
    return "%s:%s" % connection.remote_address[:2] if connection.remote_address else "?"


def _address(connection: ServerConnection) -> str:
    """The connection's IP address (its peer without the port)."""
    return str(connection.remote_address[0]) if connection.remote_address else "?"


def _gated_connection(server: PolicyServer) -> type[ServerConnection]:
    """`ServerConnection` for `server`, whose connections from an address that opened more than its share lately
    (`ServerLimits.handshakes_per_s`) are reset as they are accepted: before the handshake is read or answered, at
    the least CPU a refusal can cost in Python."""

    class GatedConnection(ServerConnection):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            super().connection_made(transport)
            peer = transport.get_extra_info("peername")
            address = str(peer[0]) if peer else "?"
            if not server._handshakes.take(address):
                server._log.log(logging.WARNING, address, "flood", "%s: connections held unread, then reset: more "
                                "than %g a second from this address (--handshakes-per-s)", address,
                                server.limits.handshakes_per_s)
                server._hold_then_reset(transport)

    return GatedConnection


# --- the `pi0-torch serve` command -------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="folder written by save_pretrained / the converter "
                        "(model weights, config and processor files), an exported folder (pi0-torch export: its graph "
                        "runs on --device cpu or cuda), or demo (the policy shipped with the package)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; 0.0.0.0 for all)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (default 8000; 0 picks a free one)")
    parser.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    add_threads_argument(parser)
    parser.add_argument("--dtype", default=None, choices=("float32", "bfloat16"),
                        help="weights dtype (default: bfloat16 on cuda, float32 on cpu)")
    parser.add_argument("--num-steps", type=int, default=None, help="Euler steps per action chunk "
                        "(default: the model config's num_inference_steps)")
    parser.add_argument("--noise-scale", type=float, default=None, help="standard deviation of the noise each "
                        "chunk's flow starts from (default: the model folder's recommended setting, else 1, openpi's "
                        "sampler; below 1 nearer the most likely chunk)")
    parser.add_argument("--rtc-schedule", default="exp", help="soft mask of real-time chunking guidance over the "
                        "previous chunk: exp (default, the paper's), linear, ones (the whole overlap) or hard")
    parser.add_argument("--obs-format", type=_observation_format, default="default", metavar="default|libero|droid|aloha|PATH.json",
                        help="observation layout the robot sends (default: the pi0-torch layout)")
    parser.add_argument("--default-prompt", default=None, help="prompt used when an observation has none "
                        "(default: the processor's, if it was saved with one)")
    parser.add_argument("--max-batch-size", type=int, default=1, help="run up to this many queued observations "
                        "as one batch (default 1: one at a time)")
    parser.add_argument("--metadata", type=json_object, default=None, metavar="JSON",
                        help="extra metadata sent to clients, a JSON object (openpi's ALOHA client reads "
                        "'reset_pose' from it)")
    parser.add_argument("--seed", type=int, default=None, help=f"seed the sampling noise (reproducible actions), "
                        f"0 to {MAX_SEED}")
    parser.add_argument("--compile", action="store_true", help="torch.compile the model's repeated layers (on cuda the "
                        "sampling also replays as one CUDA graph); compiled during the warm-up, before the server listens")
    parser.add_argument("--cuda-graph", action=argparse.BooleanOptionalAction, default=None,
                        help="replay each chunk's sampling (π0-FAST: its prefill and each decoded token) as CUDA "
                        "graphs, captured during the warm-up for every batch size up to --max-batch-size (default: on "
                        "when the device is cuda)")
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    defaults = ServerLimits()
    access = parser.add_argument_group("access and limits (docs/serving.md, 'Limits and access')")
    access.add_argument("--api-key", default=os.environ.get(API_KEY_ENV) or None,
                        help=f"require the header 'Authorization: Api-Key KEY' (openpi-client: "
                        f"WebsocketClientPolicy(api_key=KEY)); default: ${API_KEY_ENV}, else no access control")
    access.add_argument("--max-connections", type=int, default=defaults.max_connections,
                        help=f"refuse more connections with HTTP 503 (default {defaults.max_connections}), unless one "
                        "can be displaced: a connection of an address holding two or more connections more than the "
                        "new client's, or one idle past --displace-idle-after")
    access.add_argument("--handshakes-per-s", type=float, default=defaults.handshakes_per_s, metavar="RATE",
                        help=f"connections one address may open per second (default {defaults.handshakes_per_s:g}, "
                        f"{defaults.handshake_burst} at once); the ones beyond are reset as they are accepted")
    access.add_argument("--idle-timeout", type=float, default=defaults.idle_timeout_s, metavar="SECONDS",
                        help=f"close connections without a request for this long (default {defaults.idle_timeout_s:g}; "
                        "0: never)")
    access.add_argument("--displace-idle-after", type=float, default=defaults.displace_idle_s, metavar="SECONDS",
                        help="when all connections are taken, a new client displaces the one longest without actions "
                        f"if that is longer than this (default {defaults.displace_idle_s:g}; 0: never, HTTP 503)")
    access.add_argument("--refused-share", type=float, default=defaults.refused_share, metavar="FRACTION",
                        help="share of one CPU core that decoding refused frames may take, all clients together "
                        f"(default {defaults.refused_share:g}); frames of clients whose last request was refused wait "
                        "for it")
    access.add_argument("--max-message-mib", type=float, default=defaults.max_message_bytes / 2**20,
                        help=f"largest frame in MiB, at most {MAX_MESSAGE_MIB} (default "
                        f"{defaults.max_message_bytes / 2**20:g}: three 720p uint8 cameras); larger frames close the "
                        "connection (code 1009)")
    access.add_argument("--max-prompt-chars", type=int, default=defaults.max_prompt_chars,
                        help=f"longest prompt in characters (default {defaults.max_prompt_chars})")
    access.add_argument("--max-image-pixels", type=int, default=defaults.max_image_pixels,
                        help=f"largest camera frame, height x width (default {defaults.max_image_pixels}: 1920x1080)")
    access.add_argument("--max-objects", type=int, default=defaults.max_objects,
                        help=f"most objects in the lists and maps of one message, all nesting levels together "
                        f"(default {defaults.max_objects}; numpy arrays count as one)")


def _server_limits(args: argparse.Namespace) -> ServerLimits:
    """The limit flags as [`ServerLimits`], each checked under its flag's name (0 turns the timeouts off)."""
    for flag in ("--max-prompt-chars", "--max-image-pixels", "--max-objects", "--max-connections"):
        check_int(flag, getattr(args, flag[2:].replace("-", "_")), minimum=1)
    mib = check_float("--max-message-mib", args.max_message_mib, 0.0, MAX_MESSAGE_MIB, exclusive_minimum=True)
    return ServerLimits(
        max_message_bytes=max(1, int(mib * 2**20)), max_prompt_chars=args.max_prompt_chars,
        max_image_pixels=args.max_image_pixels, max_objects=args.max_objects, max_connections=args.max_connections,
        idle_timeout_s=check_float("--idle-timeout", args.idle_timeout, minimum=0.0) or None,
        displace_idle_s=check_float("--displace-idle-after", args.displace_idle_after, minimum=0.0) or None,
        refused_share=check_float("--refused-share", args.refused_share, 0.0, 1.0, exclusive_minimum=True),
        handshakes_per_s=check_float("--handshakes-per-s", args.handshakes_per_s, 0.0, exclusive_minimum=True),
    )


def _observation_format(name_or_path: str) -> ObservationFormat:
    try:
        return ObservationFormat.resolve(name_or_path)
    except (ValueError, OSError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _cuda_graph(args: argparse.Namespace) -> bool:
    """--cuda-graph, by default on where the device is cuda."""
    if args.cuda_graph is not None:
        return args.cuda_graph
    import torch

    device = torch.device(args.device if args.device is not None else ("cuda" if torch.cuda.is_available() else "cpu"))
    return device.type == "cuda"


def _load(args: argparse.Namespace) -> ServedPolicy:
    """The policy of `--model`: a model folder (`PI0Policy`, torch) or an exported one (`ExportedPolicy`, its graph's
    runtime; `pi0-torch export`)."""
    folder = policy_location(args.model)
    from pi0_torch.deploy.policy import ExportedPolicy, is_export_folder

    if is_export_folder(folder):
        given = [flag for flag, value in (("--compile", args.compile), ("--cuda-graph", args.cuda_graph), ("--dtype", args.dtype),
                                          ("--num-steps", args.num_steps), ("--rtc-schedule", args.rtc_schedule != "exp"))
                 if value]
        if given:
            raise ValueError(f"{', '.join(given)}: {folder} is an exported policy, whose graph fixes these (export it again)")
        policy = ExportedPolicy.from_folder(folder, provider=args.device or "cpu", threads=args.threads, seed=args.seed,
                                            noise_scale=args.noise_scale, default_prompt=args.default_prompt)
        logger.info("exported %s graph on %s", policy.spec["artifact"]["format"], policy.provider)
        return policy
    from pi0_torch.runtime.policy import PI0Policy  # imports torch: only when the command runs

    policy = PI0Policy.from_pretrained(
        folder, device=args.device, dtype=args.dtype, num_steps=args.num_steps, seed=args.seed,
        default_prompt=args.default_prompt, compile=args.compile, noise_scale=args.noise_scale,
        rtc_schedule=args.rtc_schedule, cuda_graph=_cuda_graph(args),
    )
    logger.info("torch uses %d CPU threads (--threads)", set_threads(args.threads, policy.model))
    return policy


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("websockets").setLevel(max(logging.WARNING, logging.getLevelName(args.log_level)))  # we log connections
    try:
        limits = _server_limits(args)
        if args.seed is not None:
            check_int("--seed", args.seed, 0, MAX_SEED)
        logger.info("loading %s", args.model)
        policy = _load(args)
        server = PolicyServer(
            policy,
            host=args.host,
            port=args.port,
            obs_format=args.obs_format,
            max_batch_size=args.max_batch_size,
            extra_metadata=args.metadata,
            limits=limits,
            api_key=args.api_key,
        )
        return server.serve_forever()
    except (ValueError, OSError) as error:  # bad limits or model folder, cameras the format cannot map, port in use
        logger.error("%s", first_line(error))
        return 1


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m pi0_torch.runtime.serving ...`: the same as `pi0-torch serve ...`."""
    parser = argparse.ArgumentParser(prog="pi0-torch serve", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
