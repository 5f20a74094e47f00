"""Fine-tune π0 / π0.5 (and π0-FAST, see `pi0_torch.training.fast`) on LeRobot episode datasets with the Hugging Face
`Trainer` (and `accelerate`).

Pieces, usable on their own or through [`train_policy`] / `pi0-torch train`:

- [`PI0DataCollator`]: dataset samples -> `PI0ForActionGeneration.forward` inputs through `PI0Processor`.
- [`PI0Trainer`]: a `Trainer` whose flow-matching noise and time are drawn per sample from a generator keyed by
  (seed, optimizer step, position of the sample in the global batch), so a run gives the same losses on one process
  or several with the same global batch, and after a resume; and whose learning-rate schedule is openpi's.
- openpi's optimizer recipe (`src/openpi/training/optimizer.py`): AdamW b1 0.9, b2 0.95, eps 1e-8, weight decay
  1e-10 (the Trainer leaves biases and norms undecayed, openpi decays all: immaterial at 1e-10), global-norm
  clipping 1.0, and `optax.warmup_cosine_decay_schedule` from peak/(warmup+1) up to the peak
  2.5e-5 over 1,000 steps, cosine down to 2.5e-6 at `decay_steps` (openpi: 30,000 = its run length; here the run
  length by default) ([`openpi_learning_rate`]).
- [`EMACallback`]: exponential moving average of the weights (openpi's `ema_decay` 0.99); the final model is the
  average, as openpi saves its EMA parameters for inference.
- [`SaveProcessorCallback`]: writes the processor (tokenizer, norm stats, settings) into every checkpoint folder,
  so `checkpoint-N/` loads with `from_pretrained` like the final folder.
- Checkpoints appear whole: each is written aside and renamed into place once complete
  ([`PI0Trainer._save_checkpoint`]); resuming skips incomplete ones ([`resolve_resume_checkpoint`]).
- [`freeze`] (`vision`: SigLIP + its projection; `vlm`: the whole PaliGemma side) and [`apply_lora`] (openpi's
  LoRA fine-tune: rank 16 on the VLM Gemma, 32 on the action expert, the rest of the Gemma frozen; the vision
  tower and the action/state/time heads keep training).

Parameters that can never influence the loss (the VLM's final norm and the last layer's VLM o-projection and MLP:
the prefix output of the last layer is never read, only its keys/values) are frozen in every run
([`loss_free_parameter_names`]); they would get no gradient anyway, and freezing them keeps DDP's set of
gradient-carrying parameters static.
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import math
import os
import re
import shutil
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

# all of it: the Trainer needs accelerate, LoRA peft, the loss plot matplotlib, which a run would reach only later
require_extra("train", __name__)
import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn
from transformers import Trainer, TrainerCallback, TrainerControl, TrainerState, TrainingArguments
from transformers.trainer_callback import PrinterCallback, ProgressCallback
from transformers.trainer import TRAINER_STATE_NAME
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR, rotate_checkpoints

from pi0_torch.cli import bool_mask, json_object
from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset, split_episodes
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.normalization import compute_norm_stats, load_openpi_norm_stats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.processing.robot_spaces import CONVERSIONS, get_conversion
from pi0_torch.processing.tokenization import TEST_TOKENIZER, TEST_TOKENIZER_VOCAB, build_test_tokenizer
from pi0_torch.training.fast import build_fast_processor
from pi0_torch.utils import files
from pi0_torch.utils.threads import add_threads_argument, set_threads
from pi0_torch.utils.validation import MAX_SEED, check_float, check_int, first_line

logger = logging.getLogger(__name__)

# openpi defaults (src/openpi/training/optimizer.py: AdamW, CosineDecaySchedule; config.py: TrainConfig.ema_decay)
OPENPI_PEAK_LR = 2.5e-5
OPENPI_END_LR = 2.5e-6
OPENPI_WARMUP_STEPS = 1_000
OPENPI_TRAIN_STEPS = 30_000  # the recipe's run length: its warm-up is 1/30 of it
OPENPI_BETAS = (0.9, 0.95)
OPENPI_EPS = 1e-8
OPENPI_WEIGHT_DECAY = 1e-10
OPENPI_CLIP_NORM = 1.0
OPENPI_EMA_DECAY = 0.99
# openpi's LoRA variants (src/openpi/models/gemma.py): gemma_2b_lora rank 16 / alpha 16, gemma_300m_lora 32 / 32
LORA_RANK_VLM = 16
LORA_RANK_EXPERT = 32
LORA_TARGETS = ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")
EMA_FILE = "ema_weights.safetensors"
TRAIN_SETTINGS_FILE = "pi0_train_settings.json"
FINAL_STEP_KEY = "final_step"  # in TRAIN_SETTINGS_FILE: the step of the final model beside it
LOSS_PLOT_FILE = "loss.png"
_CHECKPOINTING_ARGUMENT = (
    "activation_checkpointing" if "activation_checkpointing" in TrainingArguments.__dataclass_fields__ else "gradient_checkpointing"
)


# ----------------------------------------------------------------------------------------------------------------
# Batches.
# ----------------------------------------------------------------------------------------------------------------


def default_camera_map(dataset_cameras: Sequence[str], model_cameras: Sequence[str], overrides: Mapping[str, str] | None = None) -> dict[str, str]:
    """dataset camera key -> model camera name. Default: the dataset's cameras in order onto the model's.

    `overrides` maps model camera name -> dataset key (the CLI's `--camera base_0_rgb=observation.images.top`);
    when given it is the whole map. Model cameras left without a dataset camera are fed as absent (mask False).
    """
    if overrides:
        unknown_model = sorted(set(overrides) - set(model_cameras))
        unknown_data = sorted(set(overrides.values()) - set(dataset_cameras))
        if unknown_model or unknown_data:
            raise ValueError(
                f"camera map: model cameras {unknown_model} not in {list(model_cameras)}; dataset cameras "
                f"{unknown_data} not in {list(dataset_cameras)}"
            )
        return {data_key: model_name for model_name, data_key in overrides.items()}
    if len(dataset_cameras) > len(model_cameras):
        raise ValueError(
            f"the dataset has {len(dataset_cameras)} cameras {list(dataset_cameras)} but the model only "
            f"{len(model_cameras)} {list(model_cameras)}; choose them with a camera map (--camera MODEL=DATASET)"
        )
    return dict(zip(dataset_cameras, model_cameras))


@dataclass
class PI0DataCollator:
    """`LeRobotEpisodeDataset` samples -> a batch of `PI0ForActionGeneration.forward` inputs (torch tensors).

    Cameras are renamed with `camera_map` (dataset key -> model camera name; unmapped dataset cameras are dropped).
    The batch also holds `sample_index` (the samples' dataset indices, used by [`PI0Trainer`] for evaluation draws).
    """

    processor: PI0Processor
    camera_map: dict[str, str]

    def __call__(self, samples: Sequence[Mapping[str, Any]]) -> dict[str, torch.Tensor]:
        observations = [
            {
                "images": {self.camera_map[key]: frame for key, frame in sample["images"].items() if key in self.camera_map},
                "prompt": sample["prompt"],
                "state": sample["state"],
                "actions": sample["actions"],
            }
            for sample in samples
        ]
        batch = dict(self.processor(observations, return_tensors="pt"))
        batch["sample_index"] = torch.tensor([int(sample["index"]) for sample in samples], dtype=torch.long)
        return batch


def flow_draws(config: PI0Config, keys: Sequence[Sequence[int]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Flow-matching noise `[B, horizon, action_dim]` and times `[B]` (Beta(a, b) * scale + offset, as the model's own
    sampler), one independent numpy generator per sample seeded with that sample's key (a tuple of ints); with
    `config.rtc_max_delay > 0` (training-time real-time chunking) also an inference delay per sample, uniform in
    `[0, rtc_max_delay]` (long `[B]`; None otherwise), drawn after the noise and time so those stay the same."""
    noise, time, delay = [], [], []
    for key in keys:
        rng = np.random.default_rng([int(k) for k in key])
        noise.append(rng.standard_normal((config.action_horizon, config.action_dim)))
        time.append(rng.beta(config.time_beta_alpha, config.time_beta_beta) * config.time_scale + config.time_offset)
        delay.append(rng.integers(0, config.rtc_max_delay + 1))
    delays = torch.tensor(delay, dtype=torch.long) if config.rtc_max_delay > 0 else None
    return torch.tensor(np.stack(noise), dtype=torch.float32), torch.tensor(time, dtype=torch.float32), delays


# ----------------------------------------------------------------------------------------------------------------
# Optimizer schedule and the Trainer.
# ----------------------------------------------------------------------------------------------------------------


def openpi_learning_rate(step: int, peak_lr: float, warmup_steps: int, decay_steps: int, end_lr: float) -> float:
    """openpi's `CosineDecaySchedule` (`optax.warmup_cosine_decay_schedule`) at optimizer step `step` (0-based).

    Linear from `peak_lr / (warmup_steps + 1)` to `peak_lr` over `warmup_steps`, then cosine from `peak_lr` to
    `end_lr` until `decay_steps` (counted from step 0, warmup included), then constant `end_lr`.

    >>> [round(openpi_learning_rate(s, 1.0, 4, 8, 0.1), 4) for s in (0, 2, 4, 6, 8, 20)]
    [0.2, 0.6, 1.0, 0.55, 0.1, 0.1]
    """
    if step < warmup_steps:
        start = peak_lr / (warmup_steps + 1)
        return start + (peak_lr - start) * step / warmup_steps
    span = max(decay_steps - warmup_steps, 1)
    progress = min(step - warmup_steps, span) / span
    return end_lr + (peak_lr - end_lr) * 0.5 * (1 + math.cos(math.pi * progress))


class PI0Trainer(Trainer):
    """`Trainer` with per-sample seeded flow-matching draws and openpi's learning-rate schedule.

    Training draws are keyed by `(seed, optimizer step, position in the global batch)`, where a process's micro
    batch m of an optimizer step covers positions `(m * world_size + process_index) * per_device_batch + j`, which
    is exactly the order `accelerate` shards a global batch in. Evaluation draws are keyed by the sample's dataset
    index, so every evaluation of a checkpoint sees the same noise.
    """

    def __init__(self, *args: Any, lr_schedule: dict[str, float] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for plain, numeric in ((ProgressCallback, NumericProgressCallback), (PrinterCallback, NumericPrinterCallback)):
            if self.pop_callback(plain) is not None:
                self.add_callback(numeric)
        self.lr_schedule = lr_schedule
        self._draw_step = -1
        self._micro_batch = 0
        self._staging_run_dir: Path | None = None  # set while `_save_checkpoint` writes aside

    def create_scheduler(self, num_training_steps: int, optimizer: torch.optim.Optimizer | None = None) -> Any:
        if self.lr_schedule is None:
            return super().create_scheduler(num_training_steps, optimizer)
        if self.lr_scheduler is None:
            settings = dict(self.lr_schedule)
            peak = self.args.learning_rate
            settings["decay_steps"] = settings.get("decay_steps") or num_training_steps
            self.lr_scheduler = torch.optim.lr_scheduler.LambdaLR(
                optimizer or self.optimizer,
                lambda step: openpi_learning_rate(step, peak, **settings) / peak,
            )
            self._created_lr_scheduler = True
        return self.lr_scheduler

    def _flow_keys(self, inputs: Mapping[str, torch.Tensor], training: bool) -> list[tuple[int, ...]]:
        size = inputs["input_ids"].shape[0]
        if not training:
            return [(self.args.seed, 1, int(i)) for i in inputs["sample_index"]]
        step = self.state.global_step
        if step != self._draw_step:
            self._draw_step, self._micro_batch = step, 0
        first = (self._micro_batch * self.args.world_size + self.args.process_index) * self.args.per_device_train_batch_size
        self._micro_batch += 1
        return [(self.args.seed, 0, step, first + j) for j in range(size)]

    def _get_output_dir(self, trial: Any) -> str:
        return str(self._staging_run_dir) if self._staging_run_dir is not None else super()._get_output_dir(trial)

    def _save_checkpoint(self, model: nn.Module, trial: Any) -> None:
        """Write `checkpoint-N` aside and rename it into place once complete (weights, optimizer, scheduler, RNG
        states of every process, trainer state, and what callbacks add through `write_checkpoint(folder)`).

        The Trainer writes a checkpoint in place, so a process killed while saving left a `checkpoint-N` without
        `trainer_state.json` that resuming then failed on. Here every process writes into the hidden folder
        `.checkpoint-N.partial-save/checkpoint-N` (the Trainer's own saving code, pointed there), and the main
        process renames the finished folder to `checkpoint-N` (atomic) before the old ones are rotated out. A
        killed save leaves only the hidden folder, which the next run removes.
        """
        run_dir = Path(super()._get_output_dir(trial))
        final = run_dir / f"{PREFIX_CHECKPOINT_DIR}-{self.state.global_step}"
        staging = run_dir / files.partial_name(final.name, "save")
        if self.args.should_save:
            shutil.rmtree(staging, ignore_errors=True)  # an earlier attempt at this very step
            staging.mkdir(parents=True)
            files.claim(staging)
        self.accelerator.wait_for_everyone()
        self._staging_run_dir = staging
        try:
            super()._save_checkpoint(model, trial)  # into staging / checkpoint-N; rotates nothing there
        finally:
            self._staging_run_dir = None
        for callback in self.callback_handler.callbacks:
            if isinstance(callback, CheckpointContents) and (self.args.should_save or callback.collective):
                callback.write_checkpoint(staging / final.name, self.state)
        self.accelerator.wait_for_everyone()  # every process's files are in
        if self.args.should_save:
            files.publish(staging / final.name, final)
            shutil.rmtree(staging, ignore_errors=True)
            files.record_written(run_dir, [final])
            rotate_checkpoints(
                str(run_dir), save_total_limit=self.args.save_total_limit,
                best_model_checkpoint=self.state.best_model_checkpoint, use_mtime=True,
            )
        self.accelerator.wait_for_everyone()

    def compute_loss(self, model: nn.Module, inputs: dict[str, Any], return_outputs: bool = False, num_items_in_batch: Any = None) -> Any:
        inputs = dict(inputs)
        sample_index = inputs.pop("sample_index", None)
        config = self.accelerator.unwrap_model(model).config
        if "noise" not in inputs and sample_index is not None and isinstance(config, PI0Config):  # π0-FAST draws nothing
            noise, time, delay = flow_draws(config, self._flow_keys({**inputs, "sample_index": sample_index}, model.training))
            device = inputs["input_ids"].device
            inputs["noise"], inputs["time"] = noise.to(device), time.to(device)
            if delay is not None:
                inputs["inference_delay"] = delay.to(device)
        outputs = model(**inputs)
        return (outputs.loss, outputs) if return_outputs else outputs.loss


# ----------------------------------------------------------------------------------------------------------------
# Callbacks.
# ----------------------------------------------------------------------------------------------------------------


def numeric_logs(logs: Mapping[str, Any]) -> dict[str, Any]:
    """A Trainer log entry for printing: floats rounded to 4 significant digits but kept numbers (transformers'
    progress callbacks print them as strings), `total_flos` dropped.

    >>> numeric_logs({"loss": 0.123456, "grad_norm": 12.3456, "learning_rate": 2.5e-05, "epoch": 1, "total_flos": 3.0})
    {'loss': 0.1235, 'grad_norm': 12.35, 'learning_rate': 2.5e-05, 'epoch': 1}
    """
    return {k: float(f"{v:.4g}") if isinstance(v, float) else v for k, v in logs.items() if k != "total_flos"}


class NumericProgressCallback(ProgressCallback):
    """transformers' progress bar, whose log lines print numbers as numbers."""

    def on_log(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, logs: dict | None = None, **kwargs: Any) -> None:
        if state.is_world_process_zero and self.training_bar is not None:
            self.training_bar.write(str(numeric_logs(logs or {})))


class NumericPrinterCallback(PrinterCallback):
    """transformers' log printer (used without a progress bar), printing numbers as numbers."""

    def on_log(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, logs: dict | None = None, **kwargs: Any) -> None:
        if state.is_local_process_zero:
            print(numeric_logs(logs or {}))


class CheckpointContents:
    """A callback that adds files to every checkpoint: [`PI0Trainer`] calls `write_checkpoint` on the main process
    (on every process when `collective`, e.g. for a sharded save) while the checkpoint is still being written aside,
    so the files appear together with the rest of it."""

    collective = False

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        raise NotImplementedError


class EMACallback(TrainerCallback, CheckpointContents):
    """Exponential moving average of the trainable weights: `ema = decay * ema + (1 - decay) * weights` after every
    optimizer step (openpi's `ema_decay`, default 0.99).

    Each checkpoint folder gets `ema_weights.safetensors` (the averages, restored on resume); at the end of training
    the averages are copied into the model, so the final `save_model` writes them (openpi also saves its EMA
    parameters for inference).
    """

    def __init__(self, decay: float = OPENPI_EMA_DECAY, resume_from: str | Path | None = None) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.resume_from = Path(resume_from) if resume_from else None
        self.shadow: dict[str, torch.Tensor] = {}

    @staticmethod
    def _trainable(model: nn.Module) -> dict[str, nn.Parameter]:
        return {name: p for name, p in model.named_parameters() if p.requires_grad}

    def on_train_begin(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, model: nn.Module | None = None, **kwargs: Any) -> None:
        params = self._trainable(model)
        self.shadow = {name: p.detach().float().clone() for name, p in params.items()}
        if self.resume_from is not None and (self.resume_from / EMA_FILE).is_file():
            saved = load_file(str(self.resume_from / EMA_FILE))
            if set(saved) != set(self.shadow):
                raise ValueError(f"{self.resume_from / EMA_FILE} does not match the trainable parameters of this run")
            self.shadow = {name: tensor.float() for name, tensor in saved.items()}

    @torch.no_grad()
    def on_step_end(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, model: nn.Module | None = None, **kwargs: Any) -> None:
        for name, param in self._trainable(model).items():
            self.shadow[name].lerp_(param.detach().float(), 1.0 - self.decay)

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        save_file({name: t.contiguous() for name, t in self.shadow.items()}, str(folder / EMA_FILE))
        files.give_default_mode(folder / EMA_FILE)

    @torch.no_grad()
    def on_train_end(self, args: TrainingArguments, state: TrainerState, control: TrainerControl, model: nn.Module | None = None, **kwargs: Any) -> None:
        for name, param in self._trainable(model).items():
            param.copy_(self.shadow[name].to(param.dtype))


class SaveProcessorCallback(TrainerCallback, CheckpointContents):
    """Saves the processor into every `checkpoint-N` folder, next to the weights."""

    def __init__(self, processor: PI0Processor) -> None:
        self.processor = processor

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        self.processor.save_pretrained(folder)


# ----------------------------------------------------------------------------------------------------------------
# What trains: freezing and LoRA.
# ----------------------------------------------------------------------------------------------------------------

FREEZE_GROUPS = ("vision", "vlm")


def _group_prefixes(model: PI0ForActionGeneration, group: str) -> tuple[str, ...]:
    vision = ("vision_tower.", "image_projection.")
    if group == "vision":
        return vision
    if group == "vlm":
        layers = tuple(f"layers.{i}.{kind}." for i in range(len(model.layers)) for kind in ("vlm", "block"))  # block: π0-FAST
        return vision + ("embed_tokens.", "vlm_final_norm.", "final_norm.") + layers
    raise ValueError(f"unknown freeze group {group!r}; expected one of {FREEZE_GROUPS}")


def loss_free_parameter_names(model: PI0ForActionGeneration) -> list[str]:
    """Parameters that cannot influence the flow-matching loss: the VLM's final norm, and in the last layer the VLM
    o-projection, MLP norm and MLP (the last layer's prefix output is never read; its keys/values are)."""
    if isinstance(model.config, PI0FastConfig):
        return []  # every π0-FAST parameter feeds the next-token loss
    last = f"layers.{len(model.layers) - 1}.vlm."
    unused = ("vlm_final_norm.", last + "o_proj.", last + "mlp_norm.", last + "gate_up_proj.", last + "down_proj.")
    return [name for name, _ in model.named_parameters() if name.startswith(unused)]


def freeze(model: PI0ForActionGeneration, groups: Sequence[str] = ()) -> int:
    """Set `requires_grad=False` on the parameters of `groups` ("vision", "vlm") and on the loss-free parameters.

    Returns the number of trainable parameters left.
    """
    prefixes = tuple(prefix for group in groups for prefix in _group_prefixes(model, group))
    unused = set(loss_free_parameter_names(model))
    for name, param in model.named_parameters():
        if name in unused or (prefixes and name.startswith(prefixes)):
            param.requires_grad_(False)
    return count_trainable(model)


def count_trainable(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def apply_lora(
    model: PI0ForActionGeneration,
    rank_vlm: int = LORA_RANK_VLM,
    rank_expert: int = LORA_RANK_EXPERT,
    freeze_groups: Sequence[str] = (),
) -> nn.Module:
    """openpi-style LoRA through `peft`: adapters of rank `rank_vlm` (alpha = rank) on every VLM Gemma projection and
    of rank `rank_expert` on every action-expert projection; the Gemma base weights, norms and text embedding are
    frozen; the vision tower, its projection and the action/state/time heads keep training in full (peft
    `modules_to_save`), unless `freeze_groups` freezes them too.

    Returns the `peft.PeftModel`; `merge_lora` turns it back into a plain `PI0ForActionGeneration`.
    """
    from peft import LoraConfig, get_peft_model

    frozen_prefixes = tuple(prefix for group in freeze_groups for prefix in _group_prefixes(model, group))
    unused = set(loss_free_parameter_names(model))
    full_modules = [
        name for name, module in model.named_children()
        if name not in ("layers", "embed_tokens", "vlm_final_norm", "expert_final_norm", "final_norm")
        and not f"{name}.".startswith(frozen_prefixes)
        and any(True for _ in module.parameters())
    ]
    targets = "|".join(LORA_TARGETS)
    layer_kinds = "expert" if "vlm" in freeze_groups else "vlm|expert|block"  # a frozen VLM gets no adapters either
    expert_rank = {r"layers\.\d+\.expert\..*": rank_expert} if isinstance(model.config, PI0Config) else {}  # π0-FAST: no expert
    config = LoraConfig(
        r=rank_vlm,
        lora_alpha=rank_vlm,
        target_modules=rf"layers\.\d+\.({layer_kinds})\.({targets})",
        rank_pattern=expert_rank,
        alpha_pattern=expert_rank,
        modules_to_save=full_modules,
        exclude_modules=[name.rsplit(".", 1)[0] for name in unused],
    )
    return get_peft_model(model, config)


def merge_lora(model: nn.Module) -> PI0ForActionGeneration:
    """A `peft` LoRA model -> the plain model with the adapters merged into the weights (others returned as is)."""
    from peft import PeftModel

    return model.merge_and_unload() if isinstance(model, PeftModel) else model  # type: ignore[return-value]


# ----------------------------------------------------------------------------------------------------------------
# Evaluation against ground truth.
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class PolicyEvaluation:
    """Predicted vs true action chunks of every frame of a dataset, in robot units, and the mean-action baseline."""

    predictions: np.ndarray  # [N, horizon, A]
    targets: np.ndarray  # [N, horizon, A]
    baseline: np.ndarray  # [N, horizon, A]: the training data's mean action at every step
    prompts: list[str]
    episode_index: np.ndarray  # [N]

    @property
    def mse(self) -> float:
        return float(np.mean((self.predictions - self.targets) ** 2))

    @property
    def baseline_mse(self) -> float:
        return float(np.mean((self.baseline - self.targets) ** 2))

    @property
    def error_ratio(self) -> float:
        """Policy MSE / baseline MSE (0 = perfect, 1 = no better than always predicting the mean action)."""
        return self.mse / self.baseline_mse

    def summary(self) -> str:
        return (
            f"{len(self.targets)} frames: policy MSE {self.mse:.3g}, mean-action baseline MSE {self.baseline_mse:.3g}, "
            f"ratio {self.error_ratio:.3f}"
        )


@torch.no_grad()
def evaluate_policy(
    model: PI0ForActionGeneration,
    processor: PI0Processor,
    dataset: LeRobotEpisodeDataset,
    camera_map: Mapping[str, str] | None = None,
    *,
    batch_size: int = 64,
    seed: int = 0,
    num_steps: int | None = None,
    progress: bool = False,
) -> PolicyEvaluation:
    """Run `generate_actions` through the processor on every frame of `dataset` and compare with its action chunks.

    The noise of batch k comes from `torch.Generator().manual_seed(seed + k)`, so the result is reproducible. The
    baseline predicts the mean action of the processor's statistics (the training data) at every step.
    """
    from tqdm.auto import tqdm

    model.eval()
    camera_map = dict(camera_map) if camera_map is not None else default_camera_map(dataset.camera_keys, model.config.camera_names)
    collator = PI0DataCollator(processor, camera_map)
    action_stats = processor.norm_stats["actions"] if processor.norm_stats else None
    mean = np.zeros(processor.action_dim_robot) if action_stats is None else action_stats.mean[: processor.action_dim_robot]
    if processor.value_conversion is not None:  # the statistics describe converted actions
        mean = get_conversion(processor.value_conversion).actions_to_robot(mean)
    predictions, targets, baselines, prompts, episodes = [], [], [], [], []
    starts = range(0, len(dataset), batch_size)
    for number, start in enumerate(tqdm(starts, desc="evaluating", disable=not progress)):
        samples = [dataset[i] for i in range(start, min(start + batch_size, len(dataset)))]
        batch = collator(samples)
        generator = torch.Generator().manual_seed(seed + number)
        inputs = {k: batch[k].to(model.device) for k in ("pixel_values", "image_masks", "input_ids", "attention_mask", "state")}
        actions = model.generate_actions(**inputs, num_steps=num_steps, generator=generator).cpu()
        raw_state = np.stack([s["state"] for s in samples])
        predictions.append(processor.postprocess_actions(actions.numpy(), state=raw_state if processor.delta_action_mask else None))
        targets.append(np.stack([s["actions"] for s in samples]))
        baselines.append(np.broadcast_to(mean, targets[-1].shape).astype(np.float32))
        prompts += [s["prompt"] for s in samples]
        episodes += [s["episode_index"] for s in samples]
    return PolicyEvaluation(
        np.concatenate(predictions), np.concatenate(targets), np.concatenate(baselines), prompts, np.asarray(episodes)
    )


# ----------------------------------------------------------------------------------------------------------------
# A whole run.
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class TrainSettings:
    """Everything a fine-tuning run needs; the fields mirror `pi0-torch train`'s options (see `add_arguments`)."""

    dataset: str
    model: str
    output_dir: str
    config_overrides: dict[str, Any] = field(default_factory=dict)
    tokenizer: str | None = None
    norm_stats: str = "dataset"
    camera_map: dict[str, str] = field(default_factory=dict)
    state_key: str = "observation.state"
    action_key: str = "action"
    train_split: str | None = None
    eval_split: str | None = None
    short_episodes: str = "pad"
    delta_action_mask: list[bool] | None = None
    value_conversion: str | None = None
    max_steps: int = 30_000
    batch_size: int = 32
    gradient_accumulation_steps: int = 1
    learning_rate: float = OPENPI_PEAK_LR
    end_learning_rate: float = OPENPI_END_LR
    warmup_steps: int = OPENPI_WARMUP_STEPS
    decay_steps: int | None = None
    weight_decay: float = OPENPI_WEIGHT_DECAY
    max_grad_norm: float = OPENPI_CLIP_NORM
    ema_decay: float | None = None
    rtc_max_delay: int | None = None
    fast_tokenizer: str | None = None
    lora: bool = False
    lora_rank_vlm: int = LORA_RANK_VLM
    lora_rank_expert: int = LORA_RANK_EXPERT
    freeze: list[str] = field(default_factory=list)
    bf16: bool = False
    gradient_checkpointing: bool = False
    fsdp: bool = False
    seed: int = 42
    logging_steps: int = 10
    save_steps: int = 1_000
    save_total_limit: int | None = None
    eval_steps: int | None = None
    num_workers: int = 0
    threads: int | None = None  # CPU threads of torch per process; None: auto (pi0_torch.utils.threads)
    resume_from_checkpoint: str | None = None
    overwrite: bool = False  # replace an earlier run in output_dir (only a folder pi0-torch wrote)
    cpu: bool = False
    report_to: str = "none"
    progress: bool = False  # progress bars (the command line turns them on)


# The largest value of each count of a run (a batch of 1e9 would fail on its first allocation, not by name).
RUN_LIMITS: dict[str, int] = {
    "batch_size": 65_536, "gradient_accumulation_steps": 65_536, "lora_rank_vlm": 4_096, "lora_rank_expert": 4_096,
    "num_workers": 1_024, "max_steps": 1_000_000_000, "decay_steps": 1_000_000_000, "warmup_steps": 1_000_000_000,
    "seed": MAX_SEED,
}


def check_settings(settings: TrainSettings) -> None:
    """Refuse settings no run can use (`ValueError` naming the `pi0-torch train` flag): `--max-steps 0` would
    otherwise train one step, a zero batch or save interval would fail deep inside the Trainer."""
    def flag(name: str) -> str:
        return "--" + name.replace("_", "-")

    for name in ("max_steps", "batch_size", "gradient_accumulation_steps", "logging_steps", "save_steps",
                 "lora_rank_vlm", "lora_rank_expert"):
        check_int(flag(name), getattr(settings, name), minimum=1, maximum=RUN_LIMITS.get(name))
    for name in ("decay_steps", "save_total_limit", "eval_steps"):
        if getattr(settings, name) is not None:
            check_int(flag(name), getattr(settings, name), minimum=1, maximum=RUN_LIMITS.get(name))
    for name in ("warmup_steps", "num_workers", "seed"):
        check_int(flag(name), getattr(settings, name), minimum=0, maximum=RUN_LIMITS.get(name))
    check_float("--learning-rate", settings.learning_rate, minimum=0.0, exclusive_minimum=True)
    for name in ("end_learning_rate", "weight_decay", "max_grad_norm"):
        check_float(flag(name), getattr(settings, name), minimum=0.0)
    if not isinstance(settings.config_overrides, Mapping):
        raise ValueError(f"--config-overrides must be a JSON object, got {type(settings.config_overrides).__name__}")


def _is_model_folder(model: str) -> bool:
    return (Path(model) / "config.json").is_file()


def load_config(settings: TrainSettings) -> PI0Config | PI0FastConfig:
    """The model config: a checkpoint folder's `config.json`, or a preset with `config_overrides`."""
    if _is_model_folder(settings.model):
        if settings.config_overrides:
            raise ValueError("config_overrides apply to presets only; a checkpoint folder keeps its own config")
        model_type = json.loads((Path(settings.model) / "config.json").read_text()).get("model_type")
        config = (PI0FastConfig if model_type == PI0FastConfig.model_type else PI0Config).from_pretrained(settings.model)
    elif settings.model in fast_preset_names():
        config = PI0FastConfig.from_preset(settings.model, **settings.config_overrides)
    elif settings.model not in preset_names():
        raise ValueError(f"--model {settings.model!r} is neither a checkpoint folder (with config.json) nor a preset "
                         f"{preset_names() + fast_preset_names()}")
    else:
        config = PI0Config.from_preset(settings.model, **settings.config_overrides)
    if settings.rtc_max_delay is not None:  # a training choice the saved config records
        if not isinstance(config, PI0Config):
            raise ValueError("--rtc-max-delay applies to π0 / π0.5 (flow matching); π0-FAST decodes tokens")
        config = PI0Config.from_dict({**config.to_dict(), "rtc_max_delay": settings.rtc_max_delay})
    return config


def _processor_class(config: PI0Config | PI0FastConfig) -> type[PI0Processor]:
    return PI0FastProcessor if isinstance(config, PI0FastConfig) else PI0Processor


# Processor settings a fine-tuning run takes over from the model folder's processor (unless a flag overrides them):
# what the model was trained to read and to predict. Sizes come from the config, robot dims from the dataset.
INHERITED_PROCESSOR_SETTINGS = (
    "norm_mode", "delta_action_mask", "value_conversion", "min_norm_scale", "float_image_range", "required_cameras",
    "default_prompt", "truncation",
)


def run_processor_settings(settings: TrainSettings, model_processor: PI0Processor | None) -> dict[str, Any]:
    """The processor settings of a run: the model folder's (`INHERITED_PROCESSOR_SETTINGS`), with
    `--delta-action-mask` / `--value-conversion` on top when given (`"none"` turns a value conversion off). A flag
    that changes an inherited setting logs a warning naming both values."""
    saved = model_processor.to_dict() if model_processor is not None else {}
    chosen = {name: saved[name] for name in INHERITED_PROCESSOR_SETTINGS if name in saved}
    flags = {"delta_action_mask": settings.delta_action_mask, "value_conversion": settings.value_conversion}
    for name, value in flags.items():
        if value is None:
            continue
        value = None if value == "none" else value
        if name in chosen and chosen[name] != value:
            logger.warning("--%s %s replaces the %s %s that %s was trained with", name.replace("_", "-"),
                           "none" if value is None else value, name, chosen[name], settings.model)
        chosen[name] = value
    kept = [f"{name}={value}" for name, value in chosen.items() if name in saved and flags.get(name) is None]
    if kept:
        logger.info("processor settings of %s kept: %s (--delta-action-mask / --value-conversion override those two)",
                    settings.model, ", ".join(kept))
    return chosen


def build_processor(settings: TrainSettings, config: PI0Config | PI0FastConfig, dataset: LeRobotEpisodeDataset) -> PI0Processor:
    """The processor of a run: tokenizer from `--tokenizer` (or the model folder), norm stats from the dataset (or
    the model folder's processor, or an openpi `norm_stats.json`), robot dims from the dataset, and every other
    setting from the model folder's processor unless a flag overrides it ([`run_processor_settings`]); for π0-FAST
    the FAST tokenizer from `--fast-tokenizer` (a folder, or `fit`), else the model folder's. A resumed run takes
    the checkpoint's processor, which must fit the dataset."""
    processor_class = _processor_class(config)
    if settings.resume_from_checkpoint and (Path(settings.resume_from_checkpoint) / "processor_config.json").is_file():
        processor = processor_class.from_pretrained(settings.resume_from_checkpoint)
        for name, ours, theirs in (("state_dim", processor.state_dim, dataset.state_dim),
                                   ("action_dim_robot", processor.action_dim_robot, dataset.action_dim)):
            if ours != theirs:
                raise ValueError(f"--resume-from-checkpoint {settings.resume_from_checkpoint}: its processor has "
                                 f"{name} {ours}, the dataset {theirs}; resume with the run's dataset")
        return processor
    model_processor = None
    if _is_model_folder(settings.model) and (Path(settings.model) / "processor_config.json").is_file():
        model_processor = processor_class.from_pretrained(settings.model)
    if settings.tokenizer == TEST_TOKENIZER:
        prompts = sorted(set(dataset.tasks.values()))
        tokenizer: Any = build_test_tokenizer(vocab_size=min(TEST_TOKENIZER_VOCAB, config.vocab_size), extra_sentences=prompts)
    elif settings.tokenizer:
        tokenizer = settings.tokenizer
    elif model_processor is not None:
        tokenizer = model_processor.tokenizer
    else:
        raise ValueError("no tokenizer: pass --tokenizer PATH (PaliGemma's SentencePiece model), or --tokenizer test for a tiny demo model")

    chosen = run_processor_settings(settings, model_processor)
    if settings.norm_stats == "dataset":
        dataset.check_value_spread()  # one corrupt value would make every other one normalize to about 0
        chunks: Iterable[dict[str, np.ndarray]] = dataset.iter_state_action_chunks()
        if chosen.get("value_conversion") is not None:  # the statistics of what the model sees
            conversion = get_conversion(chosen["value_conversion"])
            chunks = ({"state": conversion.state_to_model(c["state"]), "actions": conversion.actions_to_model(c["actions"])}
                      for c in chunks)
        norm_stats = compute_norm_stats(
            chunks, delta_action_mask=chosen.get("delta_action_mask"), total=len(dataset.episodes), progress=settings.progress,
        )
    elif settings.norm_stats == "model":
        if model_processor is None:
            raise ValueError(f"--norm-stats model: {settings.model} has no processor with norm stats")
        norm_stats = model_processor.norm_stats
    else:
        norm_stats = load_openpi_norm_stats(settings.norm_stats)
    robot = dict(state_dim=dataset.state_dim, action_dim_robot=dataset.action_dim, **chosen)
    if isinstance(config, PI0FastConfig):
        action_tokenizer: Any = settings.fast_tokenizer
        if action_tokenizer is None and model_processor is not None:
            action_tokenizer = model_processor.action_tokenizer
        return build_fast_processor(config, tokenizer, norm_stats, dataset, action_tokenizer, **robot)
    return PI0Processor.from_config(config, tokenizer, norm_stats, **robot)


def build_model(settings: TrainSettings, config: PI0Config | PI0FastConfig) -> nn.Module:
    """The model with its frozen parts set, wrapped in LoRA when asked."""
    model_class = PI0FastForActionGeneration if isinstance(config, PI0FastConfig) else PI0ForActionGeneration
    if _is_model_folder(settings.model):  # with the run's config: it may add training choices (rtc_max_delay)
        model = model_class.from_pretrained(settings.model, config=config, dtype=torch.float32)
    else:
        torch.manual_seed(settings.seed)
        model = model_class(config)
    for group in settings.freeze:
        if group not in FREEZE_GROUPS:
            raise ValueError(f"--freeze {group!r}: expected one of {FREEZE_GROUPS}")
    if "vlm" in settings.freeze and isinstance(config, PI0FastConfig):
        raise ValueError("--freeze vlm: π0-FAST is all VLM, nothing would train; freeze 'vision' or use --lora")
    freeze(model, settings.freeze)
    if settings.lora:
        return apply_lora(model, settings.lora_rank_vlm, settings.lora_rank_expert, settings.freeze)
    return model


# (the last: the sharded model of an --fsdp run, a DCP folder complete once its .metadata is written)
WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "adapter_model.safetensors", "model_sharded/.metadata")
TORCH_STATE_SUFFIXES = (".pt", ".pth")  # optimizer, scheduler, RNG and scaler states, loaded when resuming


def checkpoint_problem(folder: Path) -> str | None:
    """Why resuming from the checkpoint `folder` would fail (None when it would not): a missing or unreadable
    trainer state, no weights, or a weights / optimizer / scheduler / RNG file that is truncated or not what its name
    says. The files are opened the way resuming opens them (safetensors headers; `torch.load` with `weights_only` and
    memory mapping, so nothing large is read and nothing is unpickled), and the reason never suggests unpickling."""
    state_path = folder / TRAINER_STATE_NAME
    if not state_path.is_file():
        return f"no {TRAINER_STATE_NAME}"
    try:
        state = json.loads(state_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return f"{TRAINER_STATE_NAME} is not valid JSON"
    if not isinstance(state, dict) or not isinstance(state.get("global_step"), int) or state["global_step"] < 0:
        return f"{TRAINER_STATE_NAME} holds no step count (global_step)"
    if not any((folder / name).is_file() for name in WEIGHT_FILES):
        return "no weights"
    for path in sorted(folder.iterdir()):
        problem = None
        if path.suffix == ".safetensors":
            problem = _safetensors_problem(path)
        elif path.suffix in TORCH_STATE_SUFFIXES:
            problem = _torch_state_problem(path)
        if problem:
            return f"{path.name} {problem}"
    return None


def _safetensors_problem(path: Path) -> str | None:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), "pt"):
            return None
    except (SafetensorError, OSError) as error:
        return f"is not a readable safetensors file ({first_line(error)})"


def _torch_state_problem(path: Path) -> str | None:
    import pickle

    from transformers.trainer_pt_utils import safe_globals

    try:
        with safe_globals():
            torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        return None
    except (RuntimeError, OSError, ValueError, EOFError, pickle.UnpicklingError):
        return "is not a readable torch state file (truncated, empty or corrupt)"


def _checkpoint_step(folder: Path) -> int | None:
    match = re.fullmatch(rf"{PREFIX_CHECKPOINT_DIR}-(\d+)", folder.name)
    return int(match[1]) if match and folder.is_dir() else None


def resolve_resume_checkpoint(output_dir: str | Path, requested: str | None) -> str | None:
    """The checkpoint a run resumes from: `requested` is None (a fresh run), `"latest"` (the newest readable
    `checkpoint-N` in `output_dir`, or a fresh run when there is none) or a `checkpoint-N` folder.

    A checkpoint that cannot be resumed from ([`checkpoint_problem`]: incomplete, truncated, garbage) is skipped
    with a warning naming it and why, falling back to the newest readable one before it in the same folder.
    """
    if requested is None:
        return None
    if requested == "latest":
        folder, before = Path(output_dir), None
    else:
        given = Path(requested)
        if not given.is_dir():
            raise ValueError(f"--resume-from-checkpoint {requested}: no such folder")
        problem = checkpoint_problem(given)
        if problem is None:
            return str(given)
        folder, before = given.parent, _checkpoint_step(given)
        logger.warning("%s cannot be resumed from (%s): looking for an earlier readable checkpoint", given, problem)
    candidates = sorted(
        ((step, path) for path in (folder.iterdir() if folder.is_dir() else ()) if (step := _checkpoint_step(path)) is not None),
        reverse=True,
    )
    for step, path in candidates:
        if before is not None and step >= before:
            continue
        problem = checkpoint_problem(path)
        if problem is None:
            logger.info("resuming from %s", path)
            return str(path)
        logger.warning("skipping %s: it cannot be resumed from (%s)", path, problem)
    if requested == "latest":
        if candidates:
            raise ValueError(f"--resume-from-checkpoint latest: none of the {len(candidates)} checkpoints in {folder} "
                             "can be resumed from (see the warnings); move them aside to start afresh")
        logger.info("no checkpoint in %s: starting a fresh run", folder)
        return None
    raise ValueError(f"--resume-from-checkpoint {requested} cannot be resumed from and {folder} holds no readable "
                     "checkpoint before it")


def check_run_folder(settings: TrainSettings) -> None:
    """Refuse an `--output-dir` this run may not write (a `ValueError` naming why), before anything is loaded.

    A run that continues a checkpoint of `--output-dir` writes there (without `--overwrite`: the two contradict).
    Any other run needs the folder absent or empty, or `--overwrite` and a folder pi0-torch wrote
    ([`pi0_torch.utils.files.check_output_dir`]): another run's checkpoints and final model are never mixed with
    this one's. The folder never overlaps the model folder or the dataset."""
    output = Path(settings.output_dir)
    for source in (settings.model, settings.dataset):
        if Path(source).is_dir():
            files.check_separate(source, output)
    if _continues_in_place(settings):
        if settings.overwrite:
            raise ValueError(f"--overwrite starts {output} over, --resume-from-checkpoint "
                             f"{settings.resume_from_checkpoint} continues its run: pass one of them")
        return
    files.check_output_dir(output, settings.overwrite)


def _continues_in_place(settings: TrainSettings) -> bool:
    resume = settings.resume_from_checkpoint
    return resume is not None and Path(resume).resolve().parent == Path(settings.output_dir).resolve()


def clear_run_folder(folder: Path) -> None:
    """Empty an output folder that [`check_run_folder`] let `--overwrite` replace (everything in it is pi0-torch's)."""
    for entry in folder.iterdir() if folder.is_dir() else ():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
    logger.info("--overwrite: removed the earlier run in %s", folder)


def trained_step(checkpoint: str | Path) -> int:
    """The optimizer steps a checkpoint holds (its trainer state's `global_step`; checked by [`checkpoint_problem`])."""
    return int(json.loads((Path(checkpoint) / TRAINER_STATE_NAME).read_text())["global_step"])


def final_step(output_dir: str | Path) -> int | None:
    """The step of the final model in `output_dir`, from its run settings file (written last); None without one."""
    try:
        step = json.loads((Path(output_dir) / TRAIN_SETTINGS_FILE).read_text()).get(FINAL_STEP_KEY)
    except (OSError, ValueError, AttributeError):
        return None
    return step if isinstance(step, int) else None


# settings a checkpoint's processor_config.json records of the model config (LoRA checkpoints hold no config.json)
PROCESSOR_CONFIG_SETTINGS = {"camera_names": "camera_names", "image_size": "image_size", "max_token_len": "max_token_len",
                             "model_action_dim": "action_dim", "action_horizon": "action_horizon"}


def check_resume_settings(config: PI0Config | PI0FastConfig, checkpoint: str | Path) -> None:
    """Refuse resuming a checkpoint trained with other model settings, naming each (`action_horizon 4 there, 8
    now`), instead of failing later on a tensor shape: every config setting when the checkpoint has its
    `config.json`, else those its processor records."""
    checkpoint = Path(checkpoint)
    if (checkpoint / "config.json").is_file():
        saved_config = type(config).from_pretrained(checkpoint)
        names = [name for name, parameter in inspect.signature(type(config).__init__).parameters.items()
                 if name != "self" and parameter.kind is not inspect.Parameter.VAR_KEYWORD]
        saved = {name: getattr(saved_config, name) for name in names}
    else:
        recorded = json.loads((checkpoint / "processor_config.json").read_text())
        saved = {name: recorded[key] for key, name in PROCESSOR_CONFIG_SETTINGS.items() if key in recorded}
    differing = [f"{name} {value!r} there, {getattr(config, name)!r} now" for name, value in saved.items()
                 if value != getattr(config, name)]
    if differing:
        raise ValueError(f"--resume-from-checkpoint {checkpoint} was trained with other model settings: "
                         f"{'; '.join(differing)} (--model / --config-overrides / --rtc-max-delay); resume with the "
                         "run's settings, or start a new --output-dir")


def check_memory(config: PI0Config | PI0FastConfig) -> None:
    """Before a model is built from a config: refuse one whose float32 weights alone exceed this machine's memory,
    and warn when weights, gradients and AdamW's two moments (16 bytes a parameter) would."""
    import psutil

    parameters = config.estimated_parameters()
    available = psutil.virtual_memory().total
    if 4 * parameters > available:
        raise ValueError(f"this config has about {parameters / 1e9:.1f} B parameters, {4 * parameters / 2**30:.1f} GiB "
                         f"of float32 weights alone; this machine has {available / 2**30:.1f} GiB of memory "
                         "(--config-overrides)")
    if 16 * parameters > available:
        logger.warning("this config has about %.2f B parameters: training needs about %.1f GiB for weights, gradients "
                       "and AdamW state, more than this machine's %.1f GiB", parameters / 1e9,
                       16 * parameters / 2**30, available / 2**30)


def _has_accelerator() -> bool:
    xpu = getattr(torch, "xpu", None)
    return torch.cuda.is_available() or torch.backends.mps.is_available() or bool(xpu and xpu.is_available())


def _episodes(root: str, split: str | None) -> list[int] | None:
    return split_episodes(root, split) if split else None


def train_policy(settings: TrainSettings) -> dict[str, Any]:
    """Fine-tune on a LeRobot dataset with `PI0Trainer`; writes `checkpoint-N/` folders (model + processor, + EMA)
    and the final model + processor into `settings.output_dir`. Returns `{"output_dir", "log_history",
    "trainable_parameters"}`. Runs under `accelerate launch` unchanged (the global batch is split over processes).
    """
    from transformers import set_seed

    from pi0_torch.training import fsdp as sharding

    check_settings(settings)
    if settings.lora and settings.ema_decay is not None:
        raise ValueError("--ema-decay with --lora: an average of the LoRA factors A and B is not the average of the "
                         "weight update B @ A, so openpi turns EMA off for LoRA fine-tuning; drop one of the two")
    settings = replace(settings, resume_from_checkpoint=resolve_resume_checkpoint(settings.output_dir, settings.resume_from_checkpoint))
    check_run_folder(settings)
    sharding.check_settings(settings.fsdp, settings.model, settings.resume_from_checkpoint)
    set_seed(settings.seed)
    config = load_config(settings)
    if not _is_model_folder(settings.model):  # before the dataset loads and the model is built
        check_memory(config)
    done = trained_step(settings.resume_from_checkpoint) if settings.resume_from_checkpoint else 0
    if settings.resume_from_checkpoint:
        check_resume_settings(config, settings.resume_from_checkpoint)
        finished = final_step(settings.output_dir)
        if done >= settings.max_steps and _continues_in_place(settings) and finished is not None and finished >= done:
            logger.info("%s holds the final model of step %d (--max-steps %d): nothing to train", settings.output_dir,
                        finished, settings.max_steps)
            state = TrainerState.load_from_json(str(Path(settings.resume_from_checkpoint) / TRAINER_STATE_NAME))
            return {"output_dir": settings.output_dir, "log_history": state.log_history, "trainable_parameters": None,
                    "steps_trained": 0}
    dataset_options = dict(
        state_key=settings.state_key, action_key=settings.action_key, short_episodes=settings.short_episodes,
        progress=settings.progress,
    )
    train_dataset = LeRobotEpisodeDataset(
        settings.dataset, config.action_horizon, episodes=_episodes(settings.dataset, settings.train_split), **dataset_options
    )
    eval_dataset = (
        LeRobotEpisodeDataset(settings.dataset, config.action_horizon, episodes=_episodes(settings.dataset, settings.eval_split), **dataset_options)
        if settings.eval_split
        else None
    )
    processor = build_processor(settings, config, train_dataset)
    camera_map = default_camera_map(train_dataset.camera_keys, config.camera_names, settings.camera_map)
    model = build_model(settings, config)
    logger.info("torch uses %d CPU threads per process (--threads)", set_threads(settings.threads, model))

    args = TrainingArguments(
        output_dir=settings.output_dir,
        max_steps=settings.max_steps,
        per_device_train_batch_size=1,  # set below from the global batch once the world size is known
        per_device_eval_batch_size=1,
        gradient_accumulation_steps=settings.gradient_accumulation_steps,
        learning_rate=settings.learning_rate,
        adam_beta1=OPENPI_BETAS[0],
        adam_beta2=OPENPI_BETAS[1],
        adam_epsilon=OPENPI_EPS,
        weight_decay=settings.weight_decay,
        max_grad_norm=settings.max_grad_norm,
        logging_steps=settings.logging_steps,
        save_steps=settings.save_steps,
        save_total_limit=settings.save_total_limit,
        eval_strategy="steps" if eval_dataset is not None else "no",
        eval_steps=settings.eval_steps or settings.save_steps,
        seed=settings.seed,
        data_seed=settings.seed,
        bf16=settings.bf16 and not settings.fsdp,  # with --fsdp: FSDP's mixed-precision policy instead of autocast
        dataloader_num_workers=settings.num_workers,
        dataloader_persistent_workers=settings.num_workers > 0,  # workers keep their decoded-frame caches
        dataloader_pin_memory=_has_accelerator() and not settings.cpu,
        remove_unused_columns=False,
        label_names=["token_loss_mask" if isinstance(config, PI0FastConfig) else "actions"],
        use_cpu=settings.cpu or not _has_accelerator(),  # (bf16 autocast on CPU needs it said explicitly)
        report_to=settings.report_to,
        disable_tqdm=not settings.progress,
        # transformers >= 5.x renamed gradient_checkpointing to activation_checkpointing (the old name warns)
        **{_CHECKPOINTING_ARGUMENT: settings.gradient_checkpointing},
    )
    per_step = args.world_size * settings.gradient_accumulation_steps
    if settings.batch_size % per_step:
        raise ValueError(
            f"--batch-size {settings.batch_size} (global) must be divisible by processes x accumulation steps = {per_step}"
        )
    args.per_device_train_batch_size = args.per_device_eval_batch_size = settings.batch_size // per_step
    if settings.fsdp:
        model = sharding.shard_model(model, bf16=settings.bf16, device_type=args.device.type)
    if settings.warmup_steps >= settings.max_steps:
        warmup = scaled_warmup_steps(settings.max_steps)
        logger.info("warm-up of %d steps >= --max-steps %d: scaled to %d steps (openpi's %d of %d) so that the learning "
                    "rate reaches its peak", settings.warmup_steps, settings.max_steps, warmup, OPENPI_WARMUP_STEPS, OPENPI_TRAIN_STEPS)
        settings = replace(settings, warmup_steps=warmup)

    callbacks: list[TrainerCallback] = [SaveProcessorCallback(processor)]
    if settings.ema_decay is not None:
        ema_type = sharding.ShardedEMACallback if settings.fsdp else EMACallback
        callbacks.append(ema_type(settings.ema_decay, resume_from=settings.resume_from_checkpoint))
    if settings.fsdp:
        callbacks.append(sharding.SaveModelConfigCallback(model))
    trainer = (sharding.FSDPTrainer if settings.fsdp else PI0Trainer)(
        model=model,
        args=args,
        train_dataset=train_dataset,
        eval_dataset=eval_dataset,
        data_collator=PI0DataCollator(processor, camera_map),
        callbacks=callbacks,
        lr_schedule=dict(warmup_steps=settings.warmup_steps, decay_steps=settings.decay_steps, end_lr=settings.end_learning_rate),
    )
    if trainer.args.should_save:
        if settings.overwrite and not _continues_in_place(settings):
            clear_run_folder(Path(settings.output_dir))  # (check_run_folder found only pi0-torch's files there)
        files.remove_stale_partials(settings.output_dir)  # checkpoints of a killed run that never finished
    trainer.accelerator.wait_for_everyone()
    trainable = count_trainable(model)
    logger.info("trainable parameters: %d of %d", trainable, sum(p.numel() for p in model.parameters()))
    if done >= settings.max_steps:  # the Trainer would train one more step: write the checkpoint's final model
        logger.info("%s already holds step %d (--max-steps %d): writing its final model without training",
                    settings.resume_from_checkpoint, done, settings.max_steps)
        _load_checkpoint_for_final(trainer, settings.resume_from_checkpoint)
    else:
        trainer.train(resume_from_checkpoint=settings.resume_from_checkpoint)

    final = sharding.gather_model(trainer.model) if settings.fsdp else merge_lora(trainer.model)  # (all processes)
    if trainer.is_world_process_zero():
        _save_final(final, processor, settings, trainer.state.global_step)
        plot_losses(trainer.state.log_history, Path(settings.output_dir) / LOSS_PLOT_FILE)
        files.record_written(Path(settings.output_dir), [Path(settings.output_dir) / LOSS_PLOT_FILE])
    trainer.accelerator.wait_for_everyone()
    return {"output_dir": settings.output_dir, "log_history": trainer.state.log_history, "trainable_parameters": trainable,
            "steps_trained": trainer.state.global_step - done}


def _load_checkpoint_for_final(trainer: PI0Trainer, checkpoint: str) -> None:
    """Put a finished checkpoint's weights (and, with EMA, its averages) into the trainer's model and its trainer
    state into the trainer, as training to its step would have left them."""
    trainer.state = TrainerState.load_from_json(str(Path(checkpoint) / TRAINER_STATE_NAME))
    trainer._load_from_checkpoint(checkpoint)
    for callback in trainer.callback_handler.callbacks:
        if isinstance(callback, EMACallback):
            callback.on_train_begin(trainer.args, trainer.state, trainer.control, model=trainer.model)
            callback.on_train_end(trainer.args, trainer.state, trainer.control, model=trainer.model)


def scaled_warmup_steps(max_steps: int) -> int:
    """The warm-up for a run shorter than openpi's: the recipe's proportion (1,000 of 30,000 steps), at least 1.

    >>> scaled_warmup_steps(100), scaled_warmup_steps(3_000), scaled_warmup_steps(10)
    (3, 100, 1)
    """
    return max(1, max_steps * OPENPI_WARMUP_STEPS // OPENPI_TRAIN_STEPS)


def plot_losses(log_history: Sequence[Mapping[str, Any]], path: Path) -> None:
    """Write the training loss (and the eval loss, when evaluated) against the step as a PNG (matplotlib, Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6, 4), dpi=100)
    axes = figure.add_subplot()
    for key, label in (("loss", "training loss"), ("eval_loss", "eval loss")):
        points = [(entry["step"], entry[key]) for entry in log_history if key in entry]
        if points:
            axes.plot(*zip(*points), marker="o" if len(points) < 30 else None, markersize=3, label=label)
    axes.set_xlabel("step")
    axes.set_ylabel("flow-matching loss")
    axes.grid(alpha=0.3)
    if axes.lines:
        axes.set_yscale("log")
        axes.legend()
    figure.tight_layout()
    FigureCanvasAgg(figure).print_png(str(path))


def _save_final(model: PI0ForActionGeneration, processor: PI0Processor, settings: TrainSettings, step: int) -> None:
    """Model + processor + the run's settings (with the final `step`) into `output_dir`, next to the checkpoint
    folders: written into a hidden folder, flushed to disk, and moved into place with the settings file last, so a
    run killed while saving never leaves a half-written final model that looks finished ([`final_step`])."""
    output = Path(settings.output_dir)
    staging = output / files.partial_name("final", "save")
    shutil.rmtree(staging, ignore_errors=True)  # an earlier attempt
    staging.mkdir(parents=True)
    files.claim(staging)
    model.save_pretrained(staging)
    processor.save_pretrained(staging)
    record = {**vars(settings), FINAL_STEP_KEY: step}
    (staging / TRAIN_SETTINGS_FILE).write_text(json.dumps(record, indent=2, default=str) + "\n")
    files.sync_tree(staging)
    (output / TRAIN_SETTINGS_FILE).unlink(missing_ok=True)  # the earlier final model is no longer the finished one
    entries = sorted((e for e in staging.iterdir() if e.name != files.OWNER_FILE), key=lambda e: e.name == TRAIN_SETTINGS_FILE)
    for entry in entries:
        if entry.is_dir():
            files.publish(entry, output / entry.name)
        else:
            os.replace(entry, output / entry.name)
    files.sync_folder(output)
    shutil.rmtree(staging)
    files.record_written(output, [output / entry.name for entry in entries])


# ----------------------------------------------------------------------------------------------------------------
# `pi0-torch train`.
# ----------------------------------------------------------------------------------------------------------------


def _key_value(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise argparse.ArgumentTypeError(f"expected MODEL_CAMERA=DATASET_KEY, got {text!r}")
    return name, value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `pi0-torch train` (openpi's recipe by default)."""
    data = parser.add_argument_group("data")
    data.add_argument("--dataset", required=True, help="LeRobot dataset folder (v3.0 or v2.x, holding meta/info.json)")
    data.add_argument("--train-split", help="split of meta/info.json 'splits' to train on (default: every episode)")
    data.add_argument("--eval-split", help="split to evaluate the loss on every --eval-steps")
    data.add_argument("--camera", action="append", type=_key_value, default=[], metavar="MODEL_CAMERA=DATASET_KEY",
                      help="feed dataset camera DATASET_KEY as MODEL_CAMERA (repeatable; default: dataset cameras in order)")
    data.add_argument("--state-key", default="observation.state")
    data.add_argument("--action-key", default="action")
    data.add_argument("--short-episodes", choices=("pad", "skip", "error"), default="pad",
                      help="episodes shorter than the action horizon: pad with the last action (default), skip, or fail")
    data.add_argument("--delta-action-mask", type=bool_mask, metavar="1,1,...,0",
                      help="action dims predicted relative to the state (openpi DeltaActions; default: the model "
                      "folder's)")
    data.add_argument("--value-conversion", choices=[*sorted(CONVERSIONS), "none"], help="convert the robot's state and "
                      "actions into the base model's space, as openpi does for ALOHA data (adapt_to_pi); saved with the "
                      "processor (default: the model folder's; 'none' turns it off)")
    data.add_argument("--num-workers", type=int, default=0, help="DataLoader workers per process")

    model = parser.add_argument_group("model")
    model.add_argument("--model", required=True, help=f"checkpoint folder, or a preset: {', '.join(preset_names() + fast_preset_names())}")
    model.add_argument("--config-overrides", type=json_object, default={}, metavar="JSON",
                       help='preset overrides, e.g. \'{"image_size": 56, "action_horizon": 8}\'')
    model.add_argument("--tokenizer", help="PaliGemma SentencePiece model (file/folder); 'test' trains a tiny one (demos)")
    model.add_argument("--fast-tokenizer", help="π0-FAST: the FAST action tokenizer folder (physical-intelligence/fast layout), "
                       "or 'fit' to fit one to the training episodes (default: the model folder's)")
    model.add_argument("--norm-stats", default="dataset",
                       help="'dataset' (compute from the training episodes), 'model' (the model folder's), or a norm_stats.json")

    recipe = parser.add_argument_group("optimization (openpi defaults)")
    recipe.add_argument("--output-dir", required=True)
    recipe.add_argument("--max-steps", type=int, default=30_000)
    recipe.add_argument("--batch-size", type=int, default=32, help="global batch, split over processes and accumulation")
    recipe.add_argument("--gradient-accumulation-steps", type=int, default=1)
    recipe.add_argument("--learning-rate", type=float, default=OPENPI_PEAK_LR, help="peak learning rate")
    recipe.add_argument("--end-learning-rate", type=float, default=OPENPI_END_LR)
    recipe.add_argument("--warmup-steps", type=int, default=OPENPI_WARMUP_STEPS)
    recipe.add_argument("--decay-steps", type=int, help="end of the cosine decay (default: --max-steps)")
    recipe.add_argument("--weight-decay", type=float, default=OPENPI_WEIGHT_DECAY)
    recipe.add_argument("--max-grad-norm", type=float, default=OPENPI_CLIP_NORM)
    recipe.add_argument("--ema-decay", type=float, nargs="?", const=OPENPI_EMA_DECAY,
                        help=f"keep an EMA of the weights (bare flag: openpi's {OPENPI_EMA_DECAY}); the final model is the EMA")
    recipe.add_argument("--rtc-max-delay", type=int, metavar="D",
                        help="training-time real-time chunking: each sample takes its first d ~ U{0..D} actions as "
                             "given, so that the policy continues the executing chunk from its committed actions "
                             "(eval --execution rtc-trained; PI0Policy then uses rtc_method='conditioning' by default; "
                             "0 turns it off)")
    recipe.add_argument("--lora", action="store_true", help="LoRA on the Gemma experts (openpi's low-memory fine-tune)")
    recipe.add_argument("--lora-rank-vlm", type=int, default=LORA_RANK_VLM)
    recipe.add_argument("--lora-rank-expert", type=int, default=LORA_RANK_EXPERT)
    recipe.add_argument("--freeze", action="append", choices=FREEZE_GROUPS, default=[],
                        help="freeze the vision tower, or the whole VLM side (vision + Gemma 2B); repeatable")
    recipe.add_argument("--bf16", action="store_true", help="bf16 mixed precision (autocast)")
    recipe.add_argument("--gradient-checkpointing", action="store_true")
    recipe.add_argument("--fsdp", action="store_true", help="shard parameters, gradients and optimizer state over the "
                        "processes (PyTorch FSDP2; under torchrun / accelerate launch); checkpoints are sharded")
    recipe.add_argument("--seed", type=int, default=42)

    run_group = parser.add_argument_group("run")
    run_group.add_argument("--logging-steps", type=int, default=10)
    run_group.add_argument("--save-steps", type=int, default=1_000)
    run_group.add_argument("--save-total-limit", type=int)
    run_group.add_argument("--eval-steps", type=int)
    run_group.add_argument("--resume-from-checkpoint", metavar="DIR|latest",
                           help="a checkpoint-N folder of an earlier run with the same settings, or 'latest' (the newest "
                                "readable one in --output-dir; a fresh run when there is none)")
    run_group.add_argument("--overwrite", action="store_true", help="replace an earlier run in --output-dir (only a "
                           "folder pi0-torch wrote; without it, a fresh run needs an absent or empty folder)")
    run_group.add_argument("--cpu", action="store_true", help="train on CPU even when a GPU is present")
    add_threads_argument(run_group)
    run_group.add_argument("--report-to", default="none", help="Trainer integrations (tensorboard, wandb, ...)")


def settings_from_args(args: argparse.Namespace) -> TrainSettings:
    names = {f for f in TrainSettings.__dataclass_fields__}
    values = {name: getattr(args, name) for name in names if hasattr(args, name)}
    values["camera_map"] = dict(args.camera)
    values["progress"] = True  # long command-line work keeps its progress bar
    return TrainSettings(**values)


def run(args: argparse.Namespace) -> int:
    # under torchrun / accelerate launch every process runs this: INFO lines from the first one only
    first_process = int(os.environ.get("RANK", "0")) == 0
    logging.basicConfig(level=logging.INFO if first_process else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        result = train_policy(settings_from_args(args))
    except (ValueError, OSError) as error:  # settings, config, dataset files: one line (the traceback at DEBUG)
        logger.debug("training failed", exc_info=True)
        print(f"error: {first_line(error)}", file=sys.stderr)
        return 1
    if result["trainable_parameters"] is None:
        print(f"nothing to train: {result['output_dir']} already holds this run's final model")
    else:
        print(f"saved the fine-tuned policy to {result['output_dir']}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m pi0_torch.training.trainer ...` (the same as `pi0-torch train ...`; handy after `accelerate launch -m`)."""
    parser = argparse.ArgumentParser(prog="pi0_torch.training", description="Fine-tune π0 / π0.5 on a LeRobot dataset.")
    add_arguments(parser)
    return run(parser.parse_args(argv))

