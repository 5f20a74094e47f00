"""Load test of the policy server on loopback: requests/s and latency percentiles for N concurrent clients.

The server (`PolicyServer` around a `PI0Policy`) runs in this process; the clients run in a separate process, one
thread each, speaking the exact frames of openpi-client's `WebsocketClientPolicy` (the same `websockets` sync client
with `compression=None, max_size=None`, and msgpack-numpy frames). Each client connects, reads the metadata, sends
`--warmup` untimed requests, waits for the others, then sends `--requests` observations back to back. Latency is
measured client side (send to reply decoded); requests/s = all timed replies / wall time of the timed phase.

    python benchmarks/bench_serving.py                         # random pi0_small, CPU
    python benchmarks/bench_serving.py --model converted/pi0_libero --device cuda --clients 1,4,8 --max-batch-size 1,8

With `--flood 0,1,3,6` it measures instead one good client's latency while that many other clients loop on a frame the
server refuses (issue 38.12: a 98 KiB msgpack array of lists of small ints, one object past `--max-objects`, refused
after 1-10 ms of decoding, by machine): the good client sends `--warmup` untimed, then `--requests` timed observations back to
back; the attackers run in a third process, each sending its next frame as soon as its refusal arrives, and their
refusals per second are counted.

    python benchmarks/bench_serving.py --num-steps 1 --flood 0,1,3,6 --requests 40

`--flood-kind reset` makes each attacker loop instead on: connect, upgrade, send a frame header that claims 8 MiB,
send 1 MiB of it, reset the connection (issue 63, round 5 item 2: a good client's median went from 7.7 to 496 ms
under three of them); `--attacker-address` sends them from another loopback address (127.0.0.2) than the good
client's.

    python benchmarks/bench_serving.py --model pi0_torch/demo_policy --flood 0,3 --flood-kind reset --requests 100

Only 127.0.0.1 is used; the number of requests is bounded by --clients x --requests (the flood by --requests and the
good client's time).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np


def _client_process(port: int, clients: int, requests: int, warmup: int, frame_shape: tuple[int, ...], results: Any) -> None:
    """Runs in a child process: `clients` threads, each its own connection; puts one summary dict on `results`."""
    import websockets.sync.client

    from pi0_torch.runtime.serving import pack_message, unpack_message

    barrier = threading.Barrier(clients + 1)
    latencies: list[float] = []
    batch_sizes: list[int] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(index: int) -> None:
        rng = np.random.default_rng(index)
        try:
            with websockets.sync.client.connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                meta = unpack_message(ws.recv())
                cameras = meta["camera_names"][:2]

                def request() -> tuple[float, int]:
                    observation = {
                        "images": {camera: rng.integers(0, 256, frame_shape, dtype=np.uint8) for camera in cameras},
                        "state": rng.standard_normal(meta["state_dim"]).astype(np.float32),
                        "prompt": "pick up the fork",
                    }
                    start = time.perf_counter()
                    ws.send(pack_message(observation))
                    reply = ws.recv()
                    if isinstance(reply, str):
                        raise RuntimeError(reply)
                    reply = unpack_message(reply)
                    elapsed = time.perf_counter() - start
                    if reply["actions"].shape != (meta["action_horizon"], meta["action_dim"]):
                        raise RuntimeError(f"actions of shape {reply['actions'].shape}")
                    return elapsed, reply["policy_timing"]["batch_size"]

                for _ in range(warmup):
                    request()
                barrier.wait()
                for _ in range(requests):
                    elapsed, batch = request()
                    with lock:
                        latencies.append(elapsed)
                        batch_sizes.append(batch)
        except Exception as error:
            with lock:
                errors.append(repr(error))
            barrier.abort()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for thread in threads:
        thread.start()
    try:
        barrier.wait()
    except threading.BrokenBarrierError:
        pass
    start = time.perf_counter()
    for thread in threads:
        thread.join()
    results.put({"latencies": latencies, "batch_sizes": batch_sizes, "errors": errors,
                 "wall": time.perf_counter() - start})


def refused_frame(max_objects: int = 100_000, items: int = 10_000) -> bytes:
    """A msgpack array of `max_objects // items` lists of `items` small ints: every list is within the item limit and
    the frame is 98 KiB, but it holds one object past `max_objects`, so the decoder refuses it at its last list."""
    inner = b"\xdc" + items.to_bytes(2, "big") + b"\x01" * items
    return b"\xdc" + (max_objects // items).to_bytes(2, "big") + inner * (max_objects // items)


def _reset_attack(port: int, address: str) -> bool:
    """One connect-upgrade-reset round: the websocket handshake, a masked binary frame header that claims 8 MiB, 1 MiB
    of its payload, then a TCP reset (SO_LINGER 0). True if the server accepted the handshake."""
    import base64
    import os
    import socket
    import struct

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as raw:
        raw.bind((address, 0))
        raw.connect(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        raw.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                     f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        response = b""
        while b"\r\n\r\n" not in response:
            chunk = raw.recv(4096)
            if not chunk:
                break
            response += chunk
        accepted = response.startswith(b"HTTP/1.1 101")
        if accepted:
            raw.sendall(b"\x82" + bytes([0x80 | 127]) + struct.pack(">Q", 8 * 2**20) + b"\0\0\0\0")
            raw.sendall(b"\0" * 2**20)
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    return accepted


def _attacker_process(port: int, attackers: int, started: Any, stop: Any, results: Any, kind: str = "refused",
                      address: str = "127.0.0.1") -> None:
    """Runs in a child process: `attackers` threads, each looping until `stop` is set on `refused_frame()` over its own
    connection (`kind` "refused"; counted: refusals) or on connect-upgrade-reset rounds from `address` ("reset";
    counted: rounds); puts the count and the seconds they took on `results`."""
    import websockets.sync.client

    frame = refused_frame()
    refusals = [0] * attackers
    errors: list[str] = []
    connected = threading.Barrier(attackers + 1)

    def reset(index: int) -> None:
        try:
            connected.wait()
            while not stop.is_set():
                try:
                    _reset_attack(port, address)
                except OSError:  # (a refused or reset handshake: the next round)
                    pass
                refusals[index] += 1
        except Exception as error:
            errors.append(repr(error))

    def attack(index: int) -> None:
        try:
            with websockets.sync.client.connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                ws.recv()  # the metadata
                connected.wait()
                while not stop.is_set():
                    ws.send(frame)
                    reply = ws.recv()
                    if not (isinstance(reply, str) and reply.startswith("invalid request: ")):
                        raise RuntimeError(f"not refused: {reply[:100]!r}")
                    refusals[index] += 1
        except Exception as error:
            errors.append(repr(error))
            connected.abort()

    threads = [threading.Thread(target=reset if kind == "reset" else attack, args=(i,)) for i in range(attackers)]
    for thread in threads:
        thread.start()
    try:
        connected.wait()
    except threading.BrokenBarrierError:
        pass
    start = time.perf_counter()
    started.set()
    for thread in threads:
        thread.join()
    results.put({"refusals": sum(refusals), "seconds": time.perf_counter() - start, "errors": errors})


def _flood(policy: Any, args: argparse.Namespace, frame_shape: tuple[int, ...]) -> None:
    """The good client's latency while 0, 1, 3, ... clients loop on a refused frame (one server each)."""
    from pi0_torch.runtime.serving import PolicyServer

    if args.flood_kind == "reset":
        print(f"connect-upgrade-reset rounds (8 MiB claimed, 1 MiB sent) from {args.attacker_address}")
    else:
        print(f"refused frame: {len(refused_frame()) / 1024:.0f} KiB, one object past --max-objects 100000")
    counted = "rounds" if args.flood_kind == "reset" else "refusals"
    print(f"| attackers | good requests | errors | p50 ms | p90 ms | max ms | {counted}/s |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    context = multiprocessing.get_context("spawn")
    for attackers in map(int, args.flood.split(",")):
        with PolicyServer(policy, host="127.0.0.1", port=0).serve_in_thread() as port:
            started, stop, results = context.Event(), context.Event(), context.Queue()
            flood = context.Process(target=_attacker_process, args=(port, attackers, started, stop, results,
                                                                    args.flood_kind, args.attacker_address))
            if attackers:
                flood.start()
                started.wait(timeout=600)
            good = context.Queue()
            client = context.Process(target=_client_process,
                                     args=(port, 1, args.requests, args.warmup, frame_shape, good))
            client.start()
            summary = good.get(timeout=3600)
            client.join()
            stop.set()
            attack = results.get(timeout=600) if attackers else {"refusals": 0, "seconds": 1.0, "errors": []}
            if attackers:
                flood.join()
        milliseconds = np.asarray(summary["latencies"]) * 1000
        p50, p90 = np.percentile(milliseconds, [50, 90]) if len(milliseconds) else (np.nan,) * 2
        print(f"| {attackers} | {len(milliseconds)} | {len(summary['errors']) + len(attack['errors'])} | {p50:.0f} | "
              f"{p90:.0f} | {milliseconds.max() if len(milliseconds) else np.nan:.0f} | "
              f"{attack['refusals'] / attack['seconds']:.0f} |", flush=True)
        for error in (summary["errors"] + attack["errors"])[:3]:
            print(f"  error: {error}")


def _random_model(preset: str, directory: Path, num_steps: int | None) -> Path:
    import torch

    from pi0_torch import PI0Config, PI0ForActionGeneration
    from pi0_torch.processing.normalization import NormStats
    from pi0_torch.processing.processing_pi0 import PI0Processor
    from pi0_torch.processing.tokenization import build_test_tokenizer

    torch.manual_seed(0)
    overrides = {"num_inference_steps": num_steps} if num_steps else {}
    config = PI0Config.from_preset(preset, **overrides)
    PI0ForActionGeneration(config).save_pretrained(directory)
    stats = {key: NormStats(mean=np.zeros(dim), std=np.ones(dim), q01=-np.ones(dim), q99=np.ones(dim))
             for key, dim in (("state", 8), ("actions", 7))}  # LIBERO's dims
    PI0Processor.from_config(config, tokenizer=build_test_tokenizer(), norm_stats=stats).save_pretrained(directory)
    return directory


def _direct_baseline(policy: Any, args: argparse.Namespace, frame_shape: tuple[int, ...]) -> tuple[Any, ...]:
    """The same requests straight into `policy.infer` (no network, no server): the floor the server adds to.

    Run on a worker thread, like the server's model thread (on a busy CPU, PyTorch's OpenMP threads behave
    differently on the main thread)."""
    rng = np.random.default_rng(0)
    cameras = policy.camera_names[:2]
    latencies = []
    start = 0.0
    for i in range(args.warmup + args.requests):
        if i == args.warmup:
            start = time.perf_counter()
        observation = {
            "images": {camera: rng.integers(0, 256, frame_shape, dtype=np.uint8) for camera in cameras},
            "state": rng.standard_normal(policy.processor.state_dim).astype(np.float32),
            "prompt": "pick up the fork",
        }
        begin = time.perf_counter()
        policy.infer(observation)
        if i >= args.warmup:
            latencies.append(time.perf_counter() - begin)
    return latencies, time.perf_counter() - start, [1] * len(latencies), []


def _print_row(label: str, clients: int, latencies: list[float], wall: float, batch_sizes: list[int],
               errors: list[str]) -> None:
    milliseconds = np.asarray(latencies) * 1000
    p50, p90, p99 = np.percentile(milliseconds, [50, 90, 99]) if len(milliseconds) else (np.nan,) * 3
    print(f"| {label} | {clients} | {len(milliseconds)} | {len(errors)} | {len(milliseconds) / wall:.2f} | "
          f"{p50:.0f} | {p90:.0f} | {p99:.0f} | {np.mean(batch_sizes) if batch_sizes else 0:.2f} |", flush=True)
    for error in errors[:3]:
        print(f"  error: {error}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="saved model folder (default: a random --preset model)")
    parser.add_argument("--preset", default="pi0_small", help="random model preset when --model is not given")
    parser.add_argument("--device", default=None)
    parser.add_argument("--dtype", default=None, choices=("float32", "bfloat16"))
    parser.add_argument("--num-steps", type=int, default=None)
    parser.add_argument("--clients", default="1,2,4", help="comma-separated client counts")
    parser.add_argument("--max-batch-size", default="1,4", help="comma-separated server settings")
    parser.add_argument("--requests", type=int, default=10, help="timed requests per client")
    parser.add_argument("--warmup", type=int, default=2, help="untimed requests per client first")
    parser.add_argument("--frame", default="224x224", help="client frame size HxW (2 cameras, uint8)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: as pi0-torch serve's "
                        "auto, 1 for a model under 10 M parameters)")
    parser.add_argument("--flood", default=None, metavar="N,N,...", help="instead of the load test: one good client's "
                        "latency while N other clients loop on a refused frame, for each N")
    parser.add_argument("--flood-kind", choices=("refused", "reset"), default="refused", help="what the --flood "
                        "attackers loop on: a refused frame, or connect-upgrade-reset rounds")
    parser.add_argument("--attacker-address", default="127.0.0.1", help="loopback address the reset attackers "
                        "connect from (the good client's is 127.0.0.1)")
    args = parser.parse_args()

    import torch

    from pi0_torch.runtime.policy import PI0Policy
    from pi0_torch.runtime.serving import PolicyServer
    from pi0_torch.utils.threads import set_threads

    frame_shape = (*map(int, args.frame.split("x")), 3)
    with tempfile.TemporaryDirectory() as scratch:
        model_dir = args.model or _random_model(args.preset, Path(scratch), args.num_steps)
        policy = PI0Policy.from_pretrained(model_dir, device=args.device, dtype=args.dtype, num_steps=args.num_steps)
        set_threads(args.threads, policy.model)  # as `pi0-torch serve` does
        name = args.model.name if args.model else f"random {args.preset}"
        print(f"model: {name}, {policy.metadata['model_type']}, {policy.num_steps} steps, device {policy.device}, "
              f"dtype {policy.metadata['dtype']}, torch threads {torch.get_num_threads()}, frames {args.frame} x2")
        if args.flood is not None:
            _flood(policy, args, frame_shape)
            return
        print("| server | clients | requests | errors | req/s | p50 ms | p90 ms | p99 ms | mean batch |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
        with concurrent.futures.ThreadPoolExecutor(max_workers=1) as model_thread:  # as the server runs the model
            baseline = model_thread.submit(_direct_baseline, policy, args, frame_shape).result()
        _print_row("none: policy.infer in process", 1, *baseline)
        context = multiprocessing.get_context("spawn")
        for max_batch in map(int, args.max_batch_size.split(",")):
            for clients in map(int, args.clients.split(",")):
                with PolicyServer(policy, host="127.0.0.1", port=0, max_batch_size=max_batch).serve_in_thread() as port:
                    results = context.Queue()
                    process = context.Process(target=_client_process,
                                              args=(port, clients, args.requests, args.warmup, frame_shape, results))
                    process.start()
                    summary = results.get(timeout=3600)
                    process.join()
                _print_row(f"max batch {max_batch}", clients, summary["latencies"], summary["wall"],
                           summary["batch_sizes"], summary["errors"])


if __name__ == "__main__":
    main()
