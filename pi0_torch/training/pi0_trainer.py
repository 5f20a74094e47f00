"""[`PI0Trainer`]: the Hugging Face `Trainer` of every fine-tuning run (one process or many through `accelerate`), and
the callbacks a run adds to it.

- [`PI0Trainer`]: a `Trainer` whose flow-matching noise and time are drawn per sample from a generator keyed by
  (seed, optimizer step, position of the sample in the global batch) (`pi0_torch.training.batches.flow_draws`), so a
  run gives the same losses on one process or several with the same global batch, and after a resume; whose
  training images get openpi's augmentation, drawn the same way (`pi0_torch.training.augmentation`); whose
  learning-rate schedule is openpi's ([`openpi_learning_rate`]); whose checkpoints appear whole: each is written
  aside and renamed into place once complete ([`PI0Trainer._save_checkpoint`]); and which, resuming, trains with its
  own schedule, optimizer settings and intervals rather than the checkpoint's ([`PI0Trainer._prepare_for_training`]).
- [`EMACallback`]: exponential moving average of the weights (openpi's `ema_decay` 0.99); the final model is the
  average, as openpi saves its EMA parameters for inference.
- [`SaveProcessorCallback`]: writes the processor (tokenizer, norm stats, settings) into every checkpoint folder,
  so `checkpoint-N/` loads with `from_pretrained` like the final folder.
- [`SaveRunSettingsCallback`]: records the run's settings in every checkpoint folder, which a resumed run is
  checked against (`pi0_torch.training.checkpoints.check_resume_run`).
- log lines that print numbers as numbers ([`numeric_logs`]).

`pi0_torch.training.fsdp` builds the sharded trainer and callbacks of `--fsdp` on these.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("accelerate",))  # the Trainer needs accelerate
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn
from transformers import Trainer, TrainerCallback, TrainerControl, TrainerState, TrainingArguments
from transformers.trainer_callback import PrinterCallback, ProgressCallback
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR, rotate_checkpoints

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.training.augmentation import augment_images, check_augmentable, draw_augmentation
from pi0_torch.training.batches import flow_draws
from pi0_torch.training.checkpoints import TRAIN_SETTINGS_FILE, save_failed
from pi0_torch.training.settings import OPENPI_EMA_DECAY
from pi0_torch.utils import files

EMA_FILE = "ema_weights.safetensors"


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

    def __init__(self, *args: Any, lr_schedule: dict[str, float] | None = None, augment: bool = False,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.augment = augment  # openpi's image augmentation of training batches (`pi0_torch.training.augmentation`)
        self._augmented_once = False
        for plain, numeric in ((ProgressCallback, NumericProgressCallback), (PrinterCallback, NumericPrinterCallback)):
            if self.pop_callback(plain) is not None:
                self.add_callback(numeric)
        self.lr_schedule = lr_schedule
        self._run_hyperparameters: list[dict[str, Any]] = []  # the optimizer's param groups as this run made them
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

    def train(self, *args: Any, **kwargs: Any) -> Any:
        """The Trainer's `train`; a run that stops on an error closes its progress bar first, so that the error
        printed next starts a line of its own."""
        try:
            return super().train(*args, **kwargs)
        except BaseException:
            for callback in self.callback_handler.callbacks:
                if isinstance(callback, ProgressCallback) and callback.training_bar is not None:
                    callback.training_bar.close()
                    callback.training_bar = None
            raise

    def get_decay_parameter_names(self, model: nn.Module) -> list[str]:
        """Every parameter, as openpi decays them (its AdamW has no mask): biases, norm scales and embeddings too (the
        Trainer's default leaves biases and norms out)."""
        return [name for name, _ in model.named_parameters()]

    def _clip_grad_norm(self, model: nn.Module) -> torch.Tensor:
        """openpi's clipping (`optax.clip_by_global_norm`): the gradients' global norm, returned, and above
        `max_grad_norm` every gradient times `max_grad_norm / norm`, with no epsilon (torch's `clip_grad_norm_` divides
        by `norm + 1e-6`). Gradients that are shards (FSDP2's DTensors) keep the Trainer's own clipping."""
        gradients = [parameter.grad for parameter in model.parameters() if parameter.grad is not None]
        if not gradients or any(type(gradient) is not torch.Tensor for gradient in gradients):
            return super()._clip_grad_norm(model)
        norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(gradients)).float())
        scale = torch.clamp(self.args.max_grad_norm / norm, max=1.0)  # (1 below the bound: the gradients unchanged)
        torch._foreach_mul_(gradients, scale.to(gradients[0].dtype))
        return norm

    def create_optimizer(self, model: nn.Module | None = None) -> torch.optim.Optimizer:
        optimizer = super().create_optimizer(model)
        groups = getattr(optimizer, "optimizer", optimizer).param_groups  # (inside accelerate's wrapper, if any)
        self._run_hyperparameters = [{k: v for k, v in group.items() if k != "params"} for group in groups]
        return optimizer

    def _prepare_for_training(self, max_steps: int, train_dataloader: Any, resume_from_checkpoint: str | None) -> Any:
        """The Trainer's preparation (which loads a checkpoint's trainer, optimizer and scheduler states when
        resuming); then, when resuming, this run's settings where those states would keep the checkpoint's: the
        logging / evaluation / saving intervals (the trainer state), the weight decay and other hyperparameters of
        each parameter group (the optimizer state), and the peak learning rate, from which the schedule continues at
        the checkpoint's step (the scheduler state). `check_resume_run` has logged which of them changed."""
        prepared = super()._prepare_for_training(max_steps, train_dataloader, resume_from_checkpoint)
        if resume_from_checkpoint is not None:
            self.state.compute_steps(self.args, max_steps)
            optimizer = getattr(self.optimizer, "optimizer", self.optimizer)
            for group, chosen in zip(optimizer.param_groups, self._run_hyperparameters, strict=True):
                group.update({name: value for name, value in chosen.items() if name != "lr"})  # (lr: the schedule's)
            scheduler = getattr(self.lr_scheduler, "scheduler", self.lr_scheduler)
            if isinstance(scheduler, torch.optim.lr_scheduler.LambdaLR):  # openpi's, and the Trainer's own schedules
                scheduler.base_lrs = [chosen["lr"] for chosen in self._run_hyperparameters]
                rates = [base * rate(scheduler.last_epoch) for base, rate in zip(scheduler.base_lrs, scheduler.lr_lambdas)]
                for group, base, rate in zip(optimizer.param_groups, scheduler.base_lrs, rates):
                    group["initial_lr"], group["lr"] = base, rate
                scheduler._last_lr = rates
        return prepared

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
        killed save leaves only the hidden folder, which the next run removes. A save whose writes fail (a full
        disk: torch reports it as an `inline_container` error) removes the hidden folder and stops the run with a
        `CheckpointSaveError` that says so and that resuming continues from the last complete checkpoint.
        """
        run_dir = Path(super()._get_output_dir(trial))
        final = run_dir / f"{PREFIX_CHECKPOINT_DIR}-{self.state.global_step}"
        staging = run_dir / files.partial_name(final.name, "save")
        try:
            self._save_checkpoint_aside(model, trial, staging, final)
        except (OSError, RuntimeError, SafetensorError) as error:
            failure = save_failed(final.name, run_dir, error)
            if self.args.should_save:
                shutil.rmtree(staging, ignore_errors=True)
            raise failure from error
        if self.args.should_save:
            files.record_written(run_dir, [final])
            rotate_checkpoints(
                str(run_dir), save_total_limit=self.args.save_total_limit,
                best_model_checkpoint=self.state.best_model_checkpoint, use_mtime=True,
            )
        self.accelerator.wait_for_everyone()

    def _save_checkpoint_aside(self, model: nn.Module, trial: Any, staging: Path, final: Path) -> None:
        """Write the checkpoint `final` into the hidden folder `staging` (every process) and rename it into place."""
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

    def compute_loss(self, model: nn.Module, inputs: dict[str, Any], return_outputs: bool = False, num_items_in_batch: Any = None) -> Any:
        inputs = dict(inputs)
        sample_index = inputs.pop("sample_index", None)
        config = self.accelerator.unwrap_model(model).config
        draws = "noise" not in inputs and sample_index is not None and isinstance(config, PI0Config)  # (π0-FAST: none)
        augment = self.augment and model.training and sample_index is not None
        keys = self._flow_keys({**inputs, "sample_index": sample_index}, model.training) if draws or augment else []
        device = inputs["input_ids"].device
        if draws:
            noise, time, delay = flow_draws(config, keys)
            inputs["noise"], inputs["time"] = noise.to(device), time.to(device)
            if delay is not None:
                inputs["inference_delay"] = delay.to(device)
        if augment:  # (keyed apart from the flow draws: (seed, 2, step, position))
            pixel_values = inputs["pixel_values"]
            if not self._augmented_once:  # (one host read, on the first batch: what the processor gives, or refused)
                check_augmentable(pixel_values)
                self._augmented_once = True
            draws_of_images = draw_augmentation([(key[0], 2, *key[2:]) for key in keys], *pixel_values.shape[-2:])
            inputs["pixel_values"] = augment_images(pixel_values, config.camera_names, draws_of_images)
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


class SaveRunSettingsCallback(TrainerCallback, CheckpointContents):
    """Writes the run's settings (`pi0_torch.training.checkpoints.run_record`) into every `checkpoint-N` folder: what
    a run resumed from it is held against (`check_resume_run`)."""

    def __init__(self, record: Mapping[str, Any]) -> None:
        self.record = dict(record)

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        (folder / TRAIN_SETTINGS_FILE).write_text(json.dumps(self.record, indent=2) + "\n")


class SaveProcessorCallback(TrainerCallback, CheckpointContents):
    """Saves the processor into every `checkpoint-N` folder, next to the weights."""

    def __init__(self, processor: PI0Processor) -> None:
        self.processor = processor

    def write_checkpoint(self, folder: Path, state: TrainerState) -> None:
        self.processor.save_pretrained(folder)
