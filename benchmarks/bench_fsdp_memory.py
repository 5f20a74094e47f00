"""Per-process memory of FSDP2 fine-tuning (`pi0-torch train --fsdp`): measured on CPU, estimated for GPUs.

    # measured: real tensors, CPU, gloo; one line of JSON per process
    torchrun --standalone --nproc-per-node 2 benchmarks/bench_fsdp_memory.py measure --preset pi0_medium --batch 1 \\
        [--no-tracker]
    # estimated: fake tensors (no memory, no compute) and a fake process group of N ranks, in one process
    python benchmarks/bench_fsdp_memory.py estimate --preset pi0 --world 1 8 --batch 4 --bf16 [--checkpointing] [--lora]

Both run the same training step as `pi0-torch train --fsdp` (`shard_model`'s wrap units and mixed-precision policy,
AdamW, global-norm clipping) on a synthetic batch of the preset's full input (3 cameras, `max_token_len` text
tokens), two optimizer steps, under PyTorch's `FSDPMemTracker` (`torch.distributed._tools`), which follows every
tensor storage and sorts it into sharded / unsharded parameters, gradients, optimizer state, activations, temporary
tensors and the all-gather / reduce-scatter buffers. Printed: the breakdown at the peak (GiB), the exact bytes of
this process's local shards of the parameters, gradients and AdamW state after the last step, and the closed-form
terms: sharded parameters 4 P / N, gradients 4 T / N, AdamW state 8 T / N bytes (P parameters, T trainable, N
processes). `measure` adds the process's peak resident memory (`ru_maxrss`) and its resident memory before the model
was built; `--no-tracker` leaves the tracker out (its per-operation bookkeeping is slow on CPU: over 15 minutes for
one medium process on a shared 2-core machine, against 3 without).

Under fake tensors the model's input checks and the skipping of absent cameras (both read tensor values) are
bypassed; every camera is present, so the computation is the same. With `--checkpointing` the tracker's activation
figure is not trustworthy (see docs/training.md, "Memory per process").
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
from collections.abc import Iterable
from contextlib import nullcontext
from pathlib import Path
from typing import Any
from unittest import mock

import torch
import torch.distributed as dist
from torch.distributed.device_mesh import init_device_mesh
from torch.distributed.tensor import DTensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.training.fsdp import shard_model
from pi0_torch.training.settings import OPENPI_BETAS, OPENPI_EPS
from pi0_torch.training.lora import apply_lora
from pi0_torch.training.trainable import count_trainable, freeze

GIB = 1024**3


def synthetic_batch(config: PI0Config, batch: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    shape = (batch, config.action_horizon, config.action_dim)
    size = config.image_size
    return {
        "pixel_values": torch.rand(batch, config.num_cameras, 3, size, size, generator=generator) * 2 - 1,
        "image_masks": torch.ones(batch, config.num_cameras, dtype=torch.bool),
        "input_ids": torch.randint(3, config.vocab_size, (batch, config.max_token_len), generator=generator),
        "attention_mask": torch.ones(batch, config.max_token_len, dtype=torch.bool),
        "state": torch.randn(batch, config.action_dim, generator=generator),
        "actions": torch.randn(shape, generator=generator),
        "noise": torch.randn(shape, generator=generator),
        "time": torch.rand(batch, generator=generator) * 0.9 + 0.05,
    }


def build(preset: str, lora: bool, checkpointing: bool, fake: bool = False) -> torch.nn.Module:
    """The model as `pi0-torch train` builds it from a preset (fake: without transformers' weight initialisation,
    which reads tensor values)."""
    from transformers.initialization import no_init_weights

    torch.manual_seed(0)
    with no_init_weights() if fake else nullcontext():
        model = PI0ForActionGeneration(PI0Config.from_preset(preset))
    freeze(model)
    if checkpointing:
        model.gradient_checkpointing_enable()
    return apply_lora(model) if lora else model


def tracked_steps(
    model: torch.nn.Module, batch: dict[str, torch.Tensor], steps: int, track: bool = True
) -> tuple[dict[str, Any], dict[str, int]]:
    """`steps` optimizer steps under `FSDPMemTracker` (`track`; its per-op bookkeeping is slow on CPU): the breakdown
    at the peak (empty without `track`), and [`shard_bytes`] after the last step (bytes)."""
    from torch.distributed._tools.fsdp2_mem_tracker import FSDPMemTracker

    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=1e-5, betas=OPENPI_BETAS, eps=OPENPI_EPS, weight_decay=1e-10)
    model.train()
    tracker = FSDPMemTracker(model, optimizer)
    tracker.track_inputs(tuple(batch.values()))
    with tracker if track else nullcontext():
        for _ in range(steps):
            loss = model(**batch).loss
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            optimizer.step()
            held = shard_bytes(model, optimizer)  # (after the step: the gradients are still there)
            optimizer.zero_grad()
            tracker.reset_mod_stats()  # (module-wise stats are per step; the peak is kept)
            gc.collect()  # the tracker's hooks leave reference cycles holding tensors (training alone leaves none)
    if not track:
        return {}, held
    peak = tracker.get_tracker_snapshot("peak")
    (device, breakdown), = peak.items()
    return {"device": str(device), **{key: int(value) for key, value in breakdown.items()}}, held


def local_bytes(tensors: Iterable[torch.Tensor]) -> int:
    """Bytes of this process's part of `tensors` (the local shard of a DTensor, all of a plain tensor)."""
    return sum((t.to_local() if isinstance(t, DTensor) else t).nbytes for t in tensors)


def shard_bytes(model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> dict[str, int]:
    """Exact accounting: the bytes this process holds of the parameters, gradients and AdamW state."""
    params = list(model.parameters())
    return {
        "params": local_bytes(params),
        "grads": local_bytes(p.grad for p in params if p.grad is not None),
        "optimizer": local_bytes(v for state in optimizer.state.values() for v in state.values() if torch.is_tensor(v)),
    }


def closed_form(model: torch.nn.Module, world: int) -> dict[str, float]:
    total = sum(p.numel() for p in model.parameters())
    trainable = count_trainable(model)
    stored = sum(p.numel() * p.element_size() for p in model.parameters())  # (LoRA: the frozen projections in bf16)
    return {
        "parameters": total, "trainable": trainable,
        "sharded_params_GiB": stored / world / GIB, "grads_GiB": 4 * trainable / world / GIB,
        "adamw_GiB": 8 * trainable / world / GIB,
    }


def rss_gib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / GIB


def measure(args: argparse.Namespace) -> None:
    dist.init_process_group("gloo")
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // dist.get_world_size()))
    before = rss_gib()
    model = shard_model(build(args.preset, args.lora, args.checkpointing), bf16=args.bf16)
    batch = synthetic_batch(model.config, args.batch)
    breakdown, held = tracked_steps(model, batch, args.steps, track=not args.no_tracker)
    result = {
        "rank": dist.get_rank(), "world": dist.get_world_size(), "preset": args.preset, "batch": args.batch,
        "bf16": args.bf16, "checkpointing": args.checkpointing, "lora": args.lora,
        "tracked_GiB": {key: value / GIB for key, value in breakdown.items() if key != "device"},
        "local_shards_GiB": {key: value / GIB for key, value in held.items()},
        "closed_form": closed_form(model, dist.get_world_size()),
        "rss_before_model_GiB": before, "peak_rss_GiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB,
    }
    print(json.dumps(result), flush=True)
    dist.destroy_process_group()


def estimate(args: argparse.Namespace) -> None:
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.testing._internal.distributed.fake_pg import FakeStore

    from pi0_torch.inference.layout import InputFacts

    def every_token_valid(self: Any, pixel_values: torch.Tensor, image_masks: torch.Tensor, input_ids: torch.Tensor,
                          *rest: Any, **floats: Any) -> InputFacts:  # (the checks read values: fake tensors hold none)
        batch, cameras, length = pixel_values.shape[0], pixel_values.shape[1], input_ids.shape[1]
        return InputFacts(((True,) * cameras,) * batch, (length,) * batch, length)

    for world in args.world:
        dist.init_process_group("fake", rank=0, world_size=world, store=FakeStore())
        mesh = init_device_mesh("cpu", (world,))
        with mock.patch.object(PI0ForActionGeneration, "_check_inputs", every_token_valid), FakeTensorMode():
            model = shard_model(build(args.preset, args.lora, args.checkpointing, fake=True), bf16=args.bf16, mesh=mesh)
            breakdown, held = tracked_steps(model, synthetic_batch(model.config, args.batch), args.steps)
            result = {
                "world": world, "preset": args.preset, "batch": args.batch, "bf16": args.bf16,
                "checkpointing": args.checkpointing, "lora": args.lora,
                "tracked_GiB": {key: value / GIB for key, value in breakdown.items() if key != "device"},
                "local_shards_GiB": {key: value / GIB for key, value in held.items()},
                "closed_form": closed_form(model, world),
            }
        print(json.dumps(result), flush=True)
        dist.destroy_process_group()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("measure", "estimate"))
    parser.add_argument("--preset", default="pi0_medium")
    parser.add_argument("--batch", type=int, default=2, help="samples per process")
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--world", type=int, nargs="+", default=[1, 2, 4, 8], help="estimate: process counts")
    parser.add_argument("--bf16", action="store_true")
    parser.add_argument("--checkpointing", action="store_true", help="activation checkpointing")
    parser.add_argument("--lora", action="store_true")
    parser.add_argument("--no-tracker", action="store_true", help="measure: exact shard bytes and peak RSS only")
    args = parser.parse_args()
    (measure if args.mode == "measure" else estimate)(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
