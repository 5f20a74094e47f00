"""CPU threads for torch: the `--threads` option of `pi0-torch eval`, `serve` and `train`.

torch runs a matmul on one thread per core by default. The matmuls of a small model are too short to be worth
splitting, and extra threads only wait on each other and on whatever else runs on the machine: on a 2-core machine
the 0.36 M-parameter `pi0_small` samples a chunk in 38 ms on one thread and in 100 ms (up to 1.4 s while another
process was busy) on two. So `--threads auto`, the default, runs a model under `SMALL_MODEL_PARAMETERS` on one
thread and leaves a larger one at torch's default; `--threads N` sets N.

>>> threads_option("auto") is None, threads_option("3")
(True, 3)
"""

from __future__ import annotations

import argparse
from typing import Any

SMALL_MODEL_PARAMETERS = 10_000_000  # below: one thread (the demo policy, the small presets); medium is 48.7 M
MAX_THREADS = 1024  # more is no machine's core count (`--threads 1000000` crashed torch's thread pool)


def threads_option(text: str) -> int | None:
    """argparse type of `--threads`: a positive count, or `auto` (None)."""
    if text == "auto":
        return None
    try:
        threads = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of threads in [1, {MAX_THREADS}] or auto, got {text!r}") from None
    if not 1 <= threads <= MAX_THREADS:
        raise argparse.ArgumentTypeError(f"expected a number of threads in [1, {MAX_THREADS}] or auto, got {threads}")
    return threads


def add_threads_argument(parser: argparse.ArgumentParser | Any) -> None:
    """Add `--threads N|auto` to a command's parser (or argument group)."""
    parser.add_argument("--threads", type=threads_option, default=None, metavar="N|auto",
                        help="CPU threads torch uses (default auto: 1 for a model under "
                             f"{SMALL_MODEL_PARAMETERS // 1_000_000} M parameters such as the demo policy, "
                             "else one per core)")


def set_threads(threads: int | None, model: Any) -> int:
    """Set torch's CPU threads for running `model` (a `torch.nn.Module`): `threads`, or for None (auto) one thread
    for a model under `SMALL_MODEL_PARAMETERS` and torch's default for a larger one. Returns the count in use."""
    import torch

    if threads is None:
        if sum(parameter.numel() for parameter in model.parameters()) >= SMALL_MODEL_PARAMETERS:
            return torch.get_num_threads()
        threads = 1
    torch.set_num_threads(threads)
    return threads
