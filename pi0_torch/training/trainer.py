"""Fine-tune π0 / π0.5 / π0-FAST on LeRobot episode datasets with the Hugging Face `Trainer` (and `accelerate`):
[`train_policy`] and the `pi0-torch train` command.

A run checks its settings and output folder, picks the checkpoint it resumes from, builds the config, processor and
model, shards the model for `--fsdp`, trains it with openpi's recipe, and writes the final model, processor, the run's
settings and a loss plot into `--output-dir`, beside the `checkpoint-N/` folders. The pieces, usable on their own:

- `pi0_torch.training.settings`: [`TrainSettings`], their bounds, openpi's recipe as their defaults;
- `pi0_torch.training.model_setup`: the config, processor and model of a run;
- `pi0_torch.training.batches`: dataset samples -> model inputs ([`PI0DataCollator`]), per-sample flow draws;
- `pi0_torch.training.pi0_trainer`: [`PI0Trainer`] (openpi's schedule, seeded draws, checkpoints written aside) and
  its callbacks ([`EMACallback`], the processor in every checkpoint);
- `pi0_torch.training.trainable`: freezing and LoRA;
- `pi0_torch.training.checkpoints`: resuming, and the final model folder;
- `pi0_torch.training.evaluation`: a policy's predictions against a dataset's actions;
- `pi0_torch.training.fsdp`: fully sharded runs; `pi0_torch.training.fast`: π0-FAST's processor and FAST tokenizer.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

# all of it: the Trainer needs accelerate, the data datasets and av, the loss plot matplotlib, which a run would reach
# only later
require_extra("train", __name__)
import torch
from torch import nn
from transformers import TrainerCallback, TrainerControl, TrainerState, TrainingArguments, set_seed
from transformers.trainer import TRAINER_STATE_NAME

from pi0_torch.cli import bool_mask, json_object
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset, split_episodes
from pi0_torch.models.configuration_pi0 import preset_names
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
from pi0_torch.processing.robot_spaces import CONVERSIONS
from pi0_torch.runtime.policy_settings import PolicySettings
from pi0_torch.shipped_policy import policy_location
from pi0_torch.training import fsdp as sharding
from pi0_torch.training.batches import PI0DataCollator, default_camera_map
from pi0_torch.training.checkpoints import (
    check_resume_run,
    check_resume_settings,
    final_step,
    resolve_resume_checkpoint,
    run_record,
    save_final_model,
    trained_step,
)
from pi0_torch.training.model_setup import build_model, build_processor, check_memory, is_model_folder, load_config
from pi0_torch.training.pi0_trainer import EMACallback, PI0Trainer, SaveProcessorCallback, SaveRunSettingsCallback
from pi0_torch.training.settings import (
    LORA_RANK_EXPERT,
    LORA_RANK_VLM,
    OPENPI_BETAS,
    OPENPI_CLIP_NORM,
    OPENPI_EMA_DECAY,
    OPENPI_END_LR,
    OPENPI_EPS,
    OPENPI_PEAK_LR,
    OPENPI_TRAIN_STEPS,
    OPENPI_WARMUP_STEPS,
    OPENPI_WEIGHT_DECAY,
    TrainSettings,
    check_settings,
    flag_name,
)
from pi0_torch.training.lora import merge_lora
from pi0_torch.training.openpi_configs import OPENPI_CONFIGS, openpi_config
from pi0_torch.training.trainable import FREEZE_GROUPS, count_trainable
from pi0_torch.utils import files
from pi0_torch.utils.threads import add_threads_argument, set_threads
from pi0_torch.utils.validation import first_line

logger = logging.getLogger(__name__)

LOSS_PLOT_FILE = "loss.png"
_CHECKPOINTING_ARGUMENT = (
    "activation_checkpointing" if "activation_checkpointing" in TrainingArguments.__dataclass_fields__ else "gradient_checkpointing"
)


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


def _has_accelerator() -> bool:
    xpu = getattr(torch, "xpu", None)
    return torch.cuda.is_available() or torch.backends.mps.is_available() or bool(xpu and xpu.is_available())


def _episodes(root: str, split: str | None) -> list[int] | None:
    return split_episodes(root, split) if split else None


def train_policy(settings: TrainSettings) -> dict[str, Any]:
    """Fine-tune on a LeRobot dataset with `PI0Trainer`; writes `checkpoint-N/` folders (model + processor + the
    run's settings, + EMA) and the final model + processor into `settings.output_dir`. Returns `{"output_dir",
    "log_history", "trainable_parameters", "steps_trained"}`. Runs under `accelerate launch` unchanged (the global
    batch is split over processes). A resumed run is held against the settings its checkpoint recorded
    (`check_resume_run`: refused by name, or applied from the checkpoint's step on and logged); a save that fails
    (a full disk) raises `CheckpointSaveError`, an `OSError` saying how to resume.
    """
    check_settings(settings)
    if settings.lora and settings.ema_decay is not None:
        raise ValueError("--ema-decay with --lora: an average of the LoRA factors A and B is not the average of the "
                         "weight update B @ A, so openpi turns EMA off for LoRA fine-tuning; drop one of the two")
    if settings.warmup_steps >= settings.max_steps:
        warmup = scaled_warmup_steps(settings.max_steps)
        logger.info("warm-up of %d steps >= --max-steps %d: scaled to %d steps (openpi's %d of %d) so that the learning "
                    "rate reaches its peak", settings.warmup_steps, settings.max_steps, warmup, OPENPI_WARMUP_STEPS, OPENPI_TRAIN_STEPS)
        settings = replace(settings, warmup_steps=warmup)
    settings = replace(settings, resume_from_checkpoint=resolve_resume_checkpoint(settings.output_dir, settings.resume_from_checkpoint))
    check_run_folder(settings)
    # one run per output folder: a second one started into it is refused instead of mixing checkpoints (the main
    # process holds it for all)
    with files.output_lock(settings.output_dir) if _is_main_process() else contextlib.nullcontext():
        return _train_in_folder(settings)


def _is_main_process() -> bool:
    """Whether this is the run's first process (`accelerate launch` / torchrun set RANK; a plain run is)."""
    return os.environ.get("RANK", "0") == "0"


def _train_in_folder(settings: TrainSettings) -> dict[str, Any]:
    """`train_policy` once it holds the output folder."""
    check_run_folder(settings)  # (again: a run that held the folder until now may have filled it)
    sharding.check_settings(settings.fsdp, settings.model, settings.resume_from_checkpoint)
    set_seed(settings.seed)
    config = load_config(settings)
    if settings.config is not None:  # the model variant openpi's config fine-tunes
        recipe = openpi_config(settings.config)
        variant = "pi0_fast" if isinstance(config, PI0FastConfig) else "pi05" if config.pi05 else "pi0"
        if variant != recipe.variant:
            raise ValueError(f"--config {settings.config} fine-tunes a {recipe.variant} model (openpi starts from "
                             f"{recipe.base}); --model {settings.model} is a {variant} model")
    if not is_model_folder(settings.model):  # before the dataset loads and the model is built
        check_memory(config)
    record = run_record(settings)
    done = trained_step(settings.resume_from_checkpoint) if settings.resume_from_checkpoint else 0
    if settings.resume_from_checkpoint:
        check_resume_settings(config, settings.resume_from_checkpoint)  # the model's settings, by name
        check_resume_run(record, settings.resume_from_checkpoint)  # the run's: refused, or applied and logged
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
    if settings.batch_size > len(train_dataset):  # (the data loader gives what there is: a smaller batch, without a word)
        logger.warning("--batch-size %d is more than the %d frames of the training episodes: each step trains on a "
                       "batch of %d, every frame once (the schedule and learning rate were chosen for %d)",
                       settings.batch_size, len(train_dataset), len(train_dataset), settings.batch_size)
    processor = build_processor(settings, config, train_dataset)
    camera_map = default_camera_map(train_dataset.camera_keys, config.camera_names, settings.camera_map)
    model = build_model(settings, config)
    logger.info("torch uses %d CPU threads per process (--threads)", set_threads(settings.threads, model))

    trainer, divergence = build_trainer(settings, config, model, record, train_dataset, eval_dataset,
                                        PI0DataCollator(processor, camera_map), SaveProcessorCallback(processor))
    model = trainer.model
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
    broken = None if final is None else next((name for name, value in final.state_dict().items()  # (FSDP: the main
                                              if value.is_floating_point() and not bool(torch.isfinite(value).all())), None)
    if settings.fsdp:  # process holds the gathered model: every process learns its verdict, and stops alike
        flag = torch.tensor([float(broken is not None)], device=trainer.accelerator.device)
        if float(trainer.accelerator.reduce(flag, "sum")) > 0 and broken is None:
            broken = "named by the main process"
    if divergence.step is not None or broken is not None:
        last = [path.name for path in sorted(Path(settings.output_dir).glob("checkpoint-*"), key=_step_of)]
        raise TrainingDivergedError(
            f"training diverged{f' at step {divergence.step}' if divergence.step is not None else ''}: "
            f"{divergence.what or f'the weights hold NaN/inf (the first: {broken})'}; the final model was not saved "
            f"(last checkpoint: {last[-1] if last else 'none'}; lower --learning-rate, or check the data)")
    if trainer.is_world_process_zero():
        recommended = PolicySettings.load(settings.model) if is_model_folder(settings.model) else None  # (carried over)
        save_final_model(final, processor, settings.output_dir, vars(settings), trainer.state.global_step, recommended)
        plot_losses(trainer.state.log_history, Path(settings.output_dir) / LOSS_PLOT_FILE)
        files.record_written(Path(settings.output_dir), [Path(settings.output_dir) / LOSS_PLOT_FILE])
    trainer.accelerator.wait_for_everyone()
    return {"output_dir": settings.output_dir, "log_history": trainer.state.log_history, "trainable_parameters": trainable,
            "steps_trained": trainer.state.global_step - done}


def build_trainer(settings: TrainSettings, config: Any, model: nn.Module, record: dict[str, Any], train_dataset: Any,
                  eval_dataset: Any, collator: Any, *extra_callbacks: TrainerCallback) -> tuple[PI0Trainer, StopOnNonFiniteCallback]:
    """The trainer of a run, as `train_policy` runs it: openpi's recipe from `settings` (AdamW, clipping, the
    warm-up + cosine schedule, EMA, augmentation), the run's record in every checkpoint, and the callback that stops
    on a non-finite loss (returned too). Batches come from `collator` over `train_dataset`; a batch that holds `noise`
    and `time` trains with them instead of the trainer's own draws (the hook `tests/test_openpi_training.py` feeds
    openpi's recorded draws through)."""
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
        logging_nan_inf_filter=False,  # (a NaN loss is logged as NaN: `StopOnNonFiniteCallback` stops the run on it)
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

    divergence = StopOnNonFiniteCallback()
    callbacks: list[TrainerCallback] = [*extra_callbacks, SaveRunSettingsCallback(record), divergence]
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
        data_collator=collator,
        callbacks=callbacks,
        lr_schedule=dict(warmup_steps=settings.warmup_steps, decay_steps=settings.decay_steps, end_lr=settings.end_learning_rate),
        augment=settings.augment,
    )
    return trainer, divergence


class TrainingDivergedError(ValueError):
    """A run whose loss, gradient norm or weights went non-finite: nothing is saved as its final model."""


class StopOnNonFiniteCallback(TrainerCallback):
    """Stops a run at the first logged loss or gradient norm that is NaN or inf (the Trainer logs every
    `--logging-steps`; its NaN filter is off), and remembers the step and what diverged."""

    def __init__(self) -> None:
        self.step: int | None = None
        self.what: str | None = None

    def on_log(self, args: TrainingArguments, state: TrainerState, control: TrainerControl,
               logs: dict[str, Any] | None = None, **kwargs: Any) -> None:
        for key in ("loss", "grad_norm"):
            value = (logs or {}).get(key)
            if isinstance(value, (int, float)) and not math.isfinite(value) and self.step is None:
                self.step, self.what = state.global_step, f"the {key.replace('_', ' ')} is {value}"
                control.should_training_stop = True


def _step_of(path: Path) -> int:
    return int(path.name.rsplit("-", 1)[-1]) if path.name.rsplit("-", 1)[-1].isdigit() else -1


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
    model.add_argument("--model", required=True, help="checkpoint folder, demo (the policy shipped with the package), or "
                       f"a preset: {', '.join(preset_names() + fast_preset_names())}")
    model.add_argument("--config", metavar="NAME", help="openpi's training config of this name (its model variant and "
                       "sizes, data features, delta masks, norm stats, batch size, steps, schedule, EMA, LoRA; each "
                       f"overridden by its own flag): {', '.join(OPENPI_CONFIGS)}; --model is the converted base "
                       "checkpoint it names (pi0_base, pi05_base)")
    model.add_argument("--default-prompt", help="the prompt of episodes without a task (saved with the processor; "
                       "default: the model folder's)")
    model.add_argument("--state-in-prompt", action=argparse.BooleanOptionalAction, default=None, help="π0.5: the "
                       "discretized state in the prompt (openpi's discrete_state_input; default: the model folder's, "
                       "else on)")
    model.add_argument("--config-overrides", type=json_object, default={}, metavar="JSON",
                       help='preset overrides, e.g. \'{"image_size": 56, "action_horizon": 8}\'')
    model.add_argument("--tokenizer", help="PaliGemma SentencePiece model (file/folder); 'test' trains a tiny one (demos)")
    model.add_argument("--fast-tokenizer", help="π0-FAST: the FAST action tokenizer folder (physical-intelligence/fast layout), "
                       "or 'fit' to fit one to the training episodes (default: the model folder's)")
    model.add_argument("--norm-stats", default="auto",
                       help="'auto' (default: the model folder's statistics when they are of the dataset's robot space, "
                            "its state and action dims, as a trained policy continues; else the dataset's), 'dataset' "
                            "(computed from the training episodes), 'model' (the model folder's), or a norm_stats.json")

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
    recipe.add_argument("--no-augment", dest="augment", action="store_false", help="train on the images as they are "
                        "(default: openpi's augmentation of every sample: non-wrist cameras cropped to 95%%, resized "
                        "back and rotated up to 5 degrees; brightness, contrast and hue jittered)")
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
                           help="a checkpoint-N folder of an earlier run, or 'latest' (the newest readable one in "
                                "--output-dir; a fresh run when there is none). Another dataset, model, processor, "
                                "--lora / --freeze, batch size or seed is refused; changed schedule, optimizer and "
                                "interval settings apply from the checkpoint's step on, with a warning naming them")
    run_group.add_argument("--overwrite", action="store_true", help="replace an earlier run in --output-dir (only a "
                           "folder pi0-torch wrote; without it, a fresh run needs an absent or empty folder)")
    run_group.add_argument("--cpu", action="store_true", help="train on CPU even when a GPU is present")
    add_threads_argument(run_group)
    run_group.add_argument("--report-to", default="none", help="Trainer integrations (tensorboard, wandb, ...)")


def settings_from_args(args: argparse.Namespace) -> TrainSettings:
    """The run's settings from `pi0-torch train`'s options; with `--config NAME`, openpi's config of that name, each
    of its values replaced by the flag's where the flag was given (`args._argv`: the command line, where the CLI keeps
    it; else the options that differ from their defaults)."""
    names = {f for f in TrainSettings.__dataclass_fields__}
    values = {name: getattr(args, name) for name in names if hasattr(args, name)}
    values["camera_map"] = dict(args.camera)
    values["model"] = str(policy_location(args.model))  # `demo`: the shipped policy, as eval and serve take it
    values["progress"] = True  # long command-line work keeps its progress bar
    if args.config is None:
        return TrainSettings(**values)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = getattr(args, "_argv", None)
    if argv is not None:
        given = given_options(parser, argv)
    else:  # (an `argparse.Namespace` built by hand)
        defaults = {name: parser.get_default("camera" if name == "camera_map" else name) for name in values}
        defaults["camera_map"] = dict(defaults["camera_map"])
        given = {name for name, value in values.items() if value != defaults[name]}
    given |= {"dataset", "model", "output_dir"}
    recipe = openpi_config(args.config).settings
    kept = {name: value for name, value in values.items() if name in given or name not in recipe}
    overridden = sorted(flag_name(name) for name in given if name in recipe)
    logger.info("openpi's config %s%s", args.config, f", with {', '.join(overridden)} from the command line" if overridden else "")
    return TrainSettings.from_openpi_config(args.config, **kept)


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str]) -> set[str]:
    """The `TrainSettings` fields whose options (of `parser`, `add_arguments`') appear on the command line `argv`
    (`--batch-size 8`, `--batch-size=8`, `--no-augment`, `--camera ...`)."""
    given = set()
    for action in parser._actions:
        if any(token == flag or token.startswith(flag + "=") for token in argv for flag in action.option_strings):
            given.add("camera_map" if action.dest == "camera" else action.dest)
    return given


def error_line(error: BaseException) -> str:
    """The line `pi0-torch train` prints for a run that stopped on `error`: its first line; for an error raised in a
    DataLoader worker (`--num-workers`), which torch raises again as "Caught LeRobotDatasetError in DataLoader worker
    process 0." with the worker's traceback below, the worker's own error line.

    >>> error_line(ValueError("Caught ValueError in DataLoader worker process 0.\\nOriginal Traceback (most recent "
    ...                       "call last):\\n  File ...\\nValueError: episode 4 frame 6: the image cell is empty"))
    'episode 4 frame 6: the image cell is empty'
    """
    lines = str(error).strip().splitlines()
    if len(lines) > 2 and lines[0].startswith("Caught ") and lines[1].startswith("Original Traceback"):
        return lines[-1].split(": ", 1)[-1]
    return first_line(error)


def run(args: argparse.Namespace) -> int:
    # under torchrun / accelerate launch every process runs this: INFO lines from the first one only
    first_process = int(os.environ.get("RANK", "0")) == 0
    logging.basicConfig(level=logging.INFO if first_process else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        result = train_policy(settings_from_args(args))
    except (ValueError, OSError) as error:  # settings, config, dataset files: one line (the traceback at DEBUG)
        logger.debug("training failed", exc_info=True)
        print(f"error: {error_line(error)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # (as eval: one line; the checkpoints written so far stay)
        logger.debug("training interrupted", exc_info=True)
        print(f"stopped (Ctrl-C): the checkpoints saved in {args.output_dir} so far are kept; the same command with "
              "--resume-from-checkpoint latest continues", file=sys.stderr)
        return 130
    if result["trainable_parameters"] is None:
        print(f"nothing to train: {result['output_dir']} already holds this run's final model")
    else:
        print(f"saved the fine-tuned policy to {result['output_dir']}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m pi0_torch.training.trainer ...` (the same as `pi0-torch train ...`; handy after `accelerate launch -m`)."""
    parser = argparse.ArgumentParser(prog="pi0_torch.training", description="Fine-tune π0 / π0.5 on a LeRobot dataset.")
    add_arguments(parser)
    args = parser.parse_args(argv)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    return run(args)
