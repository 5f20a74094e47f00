"""Fully sharded fine-tuning (`pi0-torch train --fsdp`): PyTorch FSDP2 under the Hugging Face `Trainer`.

Under `torchrun` or `accelerate launch`, `--fsdp` shards the parameters, gradients and optimizer state of π0 / π0.5
over the processes with `torch.distributed.fsdp.fully_shard` (FSDP2: DTensor parameters sharded on dim 0) instead of
replicating them (DDP). Everything else is the plain run: the same data order, the same per-sample noise and times,
openpi's recipe, so the loss curve is the one of a single process with the same global batch.

- Wrap units ([`shard_model`]): each SigLIP encoder layer, each joint decoder layer, the text embedding, then the
  root (π0.5 also needs each layer's adaRMS modulations as units: see [`wrap_units`]).
- Mixed precision (`--bf16`): `MixedPrecisionPolicy(param_dtype=bfloat16, reduce_dtype=float32)`: float32 sharded
  master weights, bf16 gathered weights for forward and backward, gradients reduce-scattered and kept in float32.
  Inputs are not cast (RoPE, the flow-matching interpolation and the loss stay float32, as in bf16 inference); no
  autocast on top.
- Gradient clipping: `clip_grad_norm_` over the DTensor gradients takes the global norm across shards.
- Checkpoints ([`FSDPTrainer`]): `checkpoint-N/` holds the sharded model, optimizer state and EMA as
  `torch.distributed.checkpoint` (DCP) folders (`model_sharded/`, `optimizer_sharded/`, `ema_sharded/`), written by
  every process into the checkpoint's staging folder like the rest of it, plus `config.json`, the processor, the
  scheduler, RNG and trainer state. DCP reshards on load, so a run resumes on any number of processes.
  [`consolidate_checkpoint`] (`pi0-torch consolidate`) makes a model folder of one on a single process; the end of
  training writes the consolidated model into `--output-dir`, as a plain run does.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("accelerate",))  # transformers.trainer needs accelerate
import torch
import torch.distributed.checkpoint as dcp
from torch import nn
from torch.distributed.checkpoint.state_dict import (
    StateDictOptions,
    get_model_state_dict,
    get_optimizer_state_dict,
    set_model_state_dict,
    set_optimizer_state_dict,
)
from torch.distributed.device_mesh import DeviceMesh, init_device_mesh
from torch.distributed.fsdp import MixedPrecisionPolicy, fully_shard
from transformers import TrainerCallback, TrainerControl, TrainerState, TrainingArguments
from transformers.models.siglip.modeling_siglip import SiglipEncoderLayer
from transformers.trainer import SCHEDULER_NAME

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.layers import AdaRMSNorm, JointDecoderLayer
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.training.lora import merge_lora_state
from pi0_torch.training.pi0_trainer import CheckpointContents, EMACallback, PI0Trainer
from pi0_torch.utils import files

logger = logging.getLogger(__name__)

# The DCP folders of a sharded checkpoint (each complete once its `.metadata` is written, after every shard).
MODEL_FOLDER = "model_sharded"
OPTIMIZER_FOLDER = "optimizer_sharded"
EMA_FOLDER = "ema_sharded"


def wrap_units(model: nn.Module) -> list[nn.Module]:
    """The modules [`shard_model`] shards as units of their own, inner ones before the layers that hold them.

    Each SigLIP encoder layer and each joint decoder layer (the all-gather of one layer's weights, freed again after
    its forward and after its backward); the text embedding (π0's is 0.53 B of its 3.3 B parameters: gathered only
    while the prefix is embedded and while its gradient is reduced); and for π0.5 the adaRMS modulation of every
    expert norm inside a layer, because the model computes those modulations from the flow time before running the
    layers, outside the layer's own forward (a unit's weights are only gathered inside its forward).
    """
    inner = [m.modulation for layer in model.modules() if isinstance(layer, JointDecoderLayer)
             for m in layer.modules() if isinstance(m, AdaRMSNorm)]
    layers = [m for m in model.modules() if isinstance(m, (SiglipEncoderLayer, JointDecoderLayer))]
    embeddings = [m for name, m in model.named_modules() if name.endswith("embed_tokens") and isinstance(m, nn.Embedding)]
    return inner + layers + embeddings


def shard_model(model: nn.Module, *, bf16: bool, device_type: str = "cpu", mesh: DeviceMesh | None = None) -> nn.Module:
    """Shard `model` (a `PI0ForActionGeneration`, LoRA adapters or not) over all processes with FSDP2, in
    place: [`wrap_units`], then the root. Needs an initialised process group (the `Trainer`'s arguments set it up
    under `torchrun` / `accelerate launch`). Returns the same module, now an `FSDPModule`.

    The parameters become DTensors sharded on dim 0 (each process holds 1/N of every tensor, float32); frozen
    parameters (`--freeze`, LoRA's frozen Gemma) are sharded too and get no gradient. `bf16` gathers the weights in
    bfloat16 for compute and reduce-scatters gradients in float32. `mesh` defaults to all processes on `device_type`.
    """
    mesh = mesh or init_device_mesh(device_type, (torch.distributed.get_world_size(),))
    policy = MixedPrecisionPolicy(
        param_dtype=torch.bfloat16 if bf16 else None, reduce_dtype=torch.float32, cast_forward_inputs=False
    )
    for unit in wrap_units(model):
        fully_shard(unit, mesh=mesh, mp_policy=policy)
    fully_shard(model, mesh=mesh, mp_policy=policy)
    return model


class FSDPTrainer(PI0Trainer):
    """[`PI0Trainer`] for a model sharded by [`shard_model`]: no DDP wrapper, sharded (DCP) checkpoints.

    accelerate's own FSDP2 support is for GPUs only (on CPU it would wrap the sharded model in DDP), so the model is
    handed to it as already prepared, and the four checkpoint methods of the `Trainer` that assume one full copy of
    the weights per process are replaced: every process writes and reads its own shards of the model and the
    optimizer state through `torch.distributed.checkpoint`. Gradient clipping needs nothing: `clip_grad_norm_` over
    DTensor gradients computes the global norm across shards. Gradients are reduce-scattered after every micro-batch
    (no `no_sync`): accumulating unsharded gradients would cost a full gradient copy per process.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        model = kwargs["model"]
        model._is_accelerate_prepared = True  # accelerate's mark of a prepared model: keeps it from wrapping DDP
        super().__init__(*args, **kwargs)

    def _move_model_to_device(self, model: nn.Module, device: torch.device) -> None:
        pass  # `fully_shard` placed each process's shards on its device; `.to()` must not touch DTensor parameters

    def save_model(self, output_dir: str | None = None, _internal_call: bool = False) -> None:
        folder = Path(output_dir or self.args.output_dir)
        dcp.save({"model": get_model_state_dict(self.model)}, checkpoint_id=str(folder / MODEL_FOLDER))

    def _save_optimizer_and_scheduler(self, output_dir: str) -> None:
        optimizer = _torch_optimizer(self.optimizer)
        dcp.save({"optimizer": get_optimizer_state_dict(self.model, optimizer)}, checkpoint_id=str(Path(output_dir) / OPTIMIZER_FOLDER))
        if self.args.should_save:
            torch.save(self.lr_scheduler.state_dict(), Path(output_dir) / SCHEDULER_NAME)

    def _load_from_checkpoint(self, resume_from_checkpoint: str, model: nn.Module | None = None) -> None:
        state = get_model_state_dict(self.model)
        dcp.load({"model": state}, checkpoint_id=str(Path(resume_from_checkpoint) / MODEL_FOLDER))
        set_model_state_dict(self.model, state)

    def _load_optimizer_and_scheduler(self, checkpoint: str | None) -> None:
        if checkpoint is None:
            return
        optimizer = _torch_optimizer(self.optimizer)
        state = get_optimizer_state_dict(self.model, optimizer)
        dcp.load({"optimizer": state}, checkpoint_id=str(Path(checkpoint) / OPTIMIZER_FOLDER))
        set_optimizer_state_dict(self.model, optimizer, state)
        self.lr_scheduler.load_state_dict(torch.load(Path(checkpoint) / SCHEDULER_NAME, weights_only=True))


def _torch_optimizer(optimizer: torch.optim.Optimizer) -> torch.optim.Optimizer:
    """The torch optimizer inside accelerate's `AcceleratedOptimizer` wrapper."""
    return getattr(optimizer, "optimizer", optimizer)


def check_settings(fsdp: bool, model: str, resume_from_checkpoint: str | None) -> None:
    """Refuse what cannot work before anything is built: `--fsdp` outside a distributed launch, a resume across the
    sharded / plain boundary, and a sharded checkpoint given as `--model`."""
    if fsdp and "LOCAL_RANK" not in os.environ:
        raise ValueError(
            "--fsdp shards over the processes of a distributed launch: run it under `torchrun --nproc-per-node N -m "
            "pi0_torch.training ...` or `accelerate launch --config_file examples/accelerate/fsdp2.yaml -m "
            "pi0_torch.training ...` (one process works too: --nproc-per-node 1)"
        )
    if os.environ.get("ACCELERATE_USE_FSDP", "false").lower() == "true":
        raise ValueError(
            "launched with an accelerate FSDP config (distributed_type: FSDP): accelerate would shard with its own wrap "
            "policy. Launch with examples/accelerate/fsdp2.yaml (distributed_type: MULTI_GPU) and pass --fsdp: "
            "pi0-torch shards the model itself"
        )
    if is_sharded_checkpoint(model):
        raise ValueError(f"--model {model} is a sharded checkpoint: make a model folder of it with `pi0-torch "
                         f"consolidate {model} --output-dir DIR`, or continue its run with --resume-from-checkpoint")
    if resume_from_checkpoint is None:
        return
    sharded = is_sharded_checkpoint(resume_from_checkpoint)
    if fsdp and not sharded:
        raise ValueError(
            f"--resume-from-checkpoint {resume_from_checkpoint} was written without --fsdp: resume it without --fsdp, "
            f"or start an --fsdp run from its weights with --model {resume_from_checkpoint} (a fresh optimizer)"
        )
    if sharded and not fsdp:
        raise ValueError(
            f"--resume-from-checkpoint {resume_from_checkpoint} is a sharded (--fsdp) checkpoint: resume it with --fsdp "
            f"(on any number of processes), or make a model folder of it with `pi0-torch consolidate "
            f"{resume_from_checkpoint} --output-dir DIR`"
        )


def is_sharded_checkpoint(folder: str | Path) -> bool:
    """A `checkpoint-N` written by an `--fsdp` run (its model is a DCP folder, complete once DCP wrote `.metadata`)."""
    return (Path(folder) / MODEL_FOLDER / ".metadata").is_file()


# ----------------------------------------------------------------------------------------------------------------
# What a sharded checkpoint holds besides the Trainer's files.
# ----------------------------------------------------------------------------------------------------------------


class SaveModelConfigCallback(TrainerCallback, CheckpointContents):
    """Writes `config.json` into every checkpoint, so that [`consolidate_checkpoint`] can rebuild the model a sharded
    checkpoint belongs to (a LoRA run's adapters are in the sharded state itself)."""

    def __init__(self, model: nn.Module) -> None:
        self.config: PI0Config = model.config

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        self.config.save_pretrained(folder)


class ShardedEMACallback(EMACallback):
    """[`EMACallback`] for a sharded model: the averages are DTensors with the parameters' sharding (each process
    averages its own shards, no communication), saved into and restored from a DCP folder `ema_sharded/` by every
    process (so a resume on another number of processes reshards them), and copied into the model at the end, where
    the consolidated final model picks them up."""

    collective = True

    def on_train_begin(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, model: nn.Module | None = None, **kwargs: Any) -> None:
        self.shadow = {name: p.detach().float().clone() for name, p in self._trainable(model).items()}
        if self.resume_from is not None and (self.resume_from / EMA_FOLDER).is_dir():
            dcp.load({"ema": self.shadow}, checkpoint_id=str(self.resume_from / EMA_FOLDER))

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        dcp.save({"ema": self.shadow}, checkpoint_id=str(folder / EMA_FOLDER))


# ----------------------------------------------------------------------------------------------------------------
# Consolidation: sharded -> one model folder.
# ----------------------------------------------------------------------------------------------------------------


def _model_to_save(config: PI0Config | PI0FastConfig, state_dict: dict[str, torch.Tensor]) -> nn.Module:
    """A model holding the tensors of `state_dict` (names as the run's model had them; no copy but LoRA's merged
    weights), to write with `save_pretrained`. Its non-persistent buffers (SigLIP's position ids), which no checkpoint
    holds, stay on the meta device: load the written folder to run it."""
    with torch.device("meta"):
        model = (PI0FastForActionGeneration if isinstance(config, PI0FastConfig) else PI0ForActionGeneration)(config)
    model.load_state_dict(merge_lora_state(state_dict), strict=True, assign=True)
    return model


def gather_model(model: nn.Module) -> PI0ForActionGeneration | None:
    """The whole sharded `model`, LoRA merged, on the main process (None on the others) to write with
    `save_pretrained` ([`_model_to_save`]). Every process must call it: the tensors are gathered one at a time into
    the main process's CPU memory."""
    state = get_model_state_dict(model, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
    if torch.distributed.get_rank() != 0:
        return None
    return _model_to_save(model.config, state)


def consolidate_checkpoint(checkpoint: str | Path, output_dir: str | Path, *, ema: bool = False, overwrite: bool = False) -> Path:
    """A sharded `checkpoint-N` (of `pi0-torch train --fsdp`) or the checkpoint of a LoRA run (its adapters not
    merged) -> a model folder (safetensors + config + processor) that `from_pretrained` loads, LoRA merged; one process,
    no GPU. `ema=True` takes the EMA averages instead of the raw weights (as the final model of an EMA run does). The
    folder appears whole (written aside, then renamed)."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    checkpoint = Path(checkpoint)
    sharded = is_sharded_checkpoint(checkpoint)
    weights = [] if sharded else sorted(checkpoint.glob("model*.safetensors"))
    names = []
    for path in weights:  # (the headers only)
        with safe_open(str(path), "pt") as handle:
            names += handle.keys()
    if not sharded and not any(name.endswith(".lora_a") for name in names):
        raise ValueError(f"{checkpoint} is neither a sharded checkpoint (no {MODEL_FOLDER}/.metadata) nor a LoRA "
                         "checkpoint (no adapters in model*.safetensors): it is a model folder already")
    if not (checkpoint / "config.json").is_file():
        raise ValueError(f"{checkpoint} has no config.json (written by a version without it): cannot rebuild its model")
    if ema and not (checkpoint / EMA_FOLDER).is_dir():
        raise ValueError(f"--ema: {checkpoint} has no {EMA_FOLDER}/ (the run kept no EMA)")
    files.check_separate(checkpoint, output_dir)
    model_type = json.loads((checkpoint / "config.json").read_text()).get("model_type")
    config = (PI0FastConfig if model_type == PI0FastConfig.model_type else PI0Config).from_pretrained(checkpoint)
    if sharded:
        saved = dcp.FileSystemReader(str(checkpoint / MODEL_FOLDER)).read_metadata().state_dict_metadata
        state = {name.removeprefix("model."): torch.empty(tuple(meta.size), dtype=meta.properties.dtype)
                 for name, meta in saved.items()}  # (the run's model: a LoRA run's adapters and bfloat16 Gemma included)
        _load_sharded(checkpoint, state, ema)
    else:
        state = {name: tensor for path in weights for name, tensor in load_file(path).items()}
    model = _model_to_save(config, state)
    with files.atomic_output_dir(output_dir, overwrite=overwrite) as folder:
        model.save_pretrained(folder)
        if (checkpoint / "processor_config.json").is_file():
            processor = PI0FastProcessor if isinstance(config, PI0FastConfig) else PI0Processor
            processor.from_pretrained(checkpoint).save_pretrained(folder)
    return Path(output_dir)


def _load_sharded(checkpoint: Path, state: dict[str, torch.Tensor], ema: bool) -> None:
    """`state` (empty tensors named and shaped as the checkpoint's model) filled from its DCP folders."""
    with warnings.catch_warnings():  # DCP warns that it reads in one process, which is the point here
        warnings.filterwarnings("ignore", message="torch.distributed is disabled")
        dcp.load({"model": state}, checkpoint_id=str(checkpoint / MODEL_FOLDER), no_dist=True)
        if ema:  # the averages of the parameters the run trained, over their raw values
            saved = dcp.FileSystemReader(str(checkpoint / EMA_FOLDER)).read_metadata().state_dict_metadata
            averages = {name: state[name] for name in (key.removeprefix("ema.") for key in saved)}
            dcp.load({"ema": averages}, checkpoint_id=str(checkpoint / EMA_FOLDER), no_dist=True)


# ----------------------------------------------------------------------------------------------------------------
# `pi0-torch consolidate`.
# ----------------------------------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `pi0-torch consolidate`."""
    parser.add_argument("checkpoint", help="a checkpoint-N folder written by `pi0-torch train --fsdp` or `--lora`")
    parser.add_argument("--output-dir", required=True, help="the model folder to write (safetensors, config, processor)")
    parser.add_argument("--ema", action="store_true", help="take the EMA averages instead of the raw weights")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir")


def run(args: argparse.Namespace) -> int:
    output = consolidate_checkpoint(args.checkpoint, args.output_dir, ema=args.ema, overwrite=args.overwrite)
    print(f"wrote the consolidated model to {output}")
    return 0
