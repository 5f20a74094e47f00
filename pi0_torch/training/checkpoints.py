"""The folders a fine-tuning run leaves, apart from how the `Trainer` writes its checkpoints
(`pi0_torch.training.pi0_trainer`; sharded: `pi0_torch.training.fsdp`): which `checkpoint-N` a run resumes from
([`resolve_resume_checkpoint`]: the newest readable one; [`checkpoint_problem`] says why another cannot be resumed
from), whether it was trained with the run's model settings ([`check_resume_settings`]), and the final model beside
the checkpoints ([`save_final_model`]: written aside and moved into place with the settings file last, so that a
killed save never looks finished, [`final_step`]).
"""

from __future__ import annotations

import inspect
import json
import logging
import os
import re
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("accelerate",))  # transformers.trainer needs accelerate
import torch
from transformers.trainer import TRAINER_STATE_NAME
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.utils import files
from pi0_torch.utils.validation import first_line

logger = logging.getLogger(__name__)

TRAIN_SETTINGS_FILE = "pi0_train_settings.json"
FINAL_STEP_KEY = "final_step"  # in TRAIN_SETTINGS_FILE: the step of the final model beside it
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


def trained_step(checkpoint: str | Path) -> int:
    """The optimizer steps a checkpoint holds (its trainer state's `global_step`; checked by [`checkpoint_problem`])."""
    return int(json.loads((Path(checkpoint) / TRAINER_STATE_NAME).read_text())["global_step"])


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


def final_step(output_dir: str | Path) -> int | None:
    """The step of the final model in `output_dir`, from its run settings file (written last); None without one."""
    try:
        step = json.loads((Path(output_dir) / TRAIN_SETTINGS_FILE).read_text()).get(FINAL_STEP_KEY)
    except (OSError, ValueError, AttributeError):
        return None
    return step if isinstance(step, int) else None


def save_final_model(model: PI0ForActionGeneration, processor: PI0Processor, output_dir: str | Path,
                     settings: Mapping[str, Any], step: int) -> None:
    """Model + processor + the run's `settings` (with the final `step`) into `output_dir`, next to the checkpoint
    folders: written into a hidden folder, flushed to disk, and moved into place with the settings file last, so a
    run killed while saving never leaves a half-written final model that looks finished ([`final_step`])."""
    output = Path(output_dir)
    staging = output / files.partial_name("final", "save")
    shutil.rmtree(staging, ignore_errors=True)  # an earlier attempt
    staging.mkdir(parents=True)
    files.claim(staging)
    model.save_pretrained(staging)
    processor.save_pretrained(staging)
    record = {**settings, FINAL_STEP_KEY: step}
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
