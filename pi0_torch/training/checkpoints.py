"""The folders a fine-tuning run leaves, apart from how the `Trainer` writes its checkpoints
(`pi0_torch.training.pi0_trainer`; sharded: `pi0_torch.training.fsdp`): which `checkpoint-N` a run resumes from
([`resolve_resume_checkpoint`]: the newest readable one; [`checkpoint_problem`] says why another cannot be resumed
from), whether it was trained with the run's model settings ([`check_resume_settings`]) and what a resumed run may
change of the settings the checkpoint recorded ([`run_record`], [`check_resume_run`]), the final model beside the
checkpoints ([`save_final_model`]: written aside and moved into place with the settings file last, so that a killed
save never looks finished, [`final_step`]), and the error of a save that failed ([`save_failed`]: a full disk is
named as such).
"""

from __future__ import annotations

import errno
import hashlib
import inspect
import json
import logging
import os
import re
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("accelerate",))  # transformers.trainer needs accelerate
import torch
from safetensors import SafetensorError
from transformers.trainer import TRAINER_STATE_NAME
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.runtime.policy_settings import PolicySettings
from pi0_torch.training.settings import RESUME_APPLIED, RESUME_REFUSED, SOURCE_SETTINGS, TrainSettings, flag_name
from pi0_torch.utils import files
from pi0_torch.utils.validation import first_line

logger = logging.getLogger(__name__)

TRAIN_SETTINGS_FILE = "pi0_train_settings.json"  # the run's settings: beside the final model, and in every checkpoint
FINAL_STEP_KEY = "final_step"  # in TRAIN_SETTINGS_FILE: the step of the final model beside it
SOURCES_KEY = "source_fingerprints"  # in a checkpoint's TRAIN_SETTINGS_FILE: what its path settings named
FINGERPRINT_BYTES = 1 << 20  # a file's fingerprint: its size, and its first and last MiB
FULL_DISK_BYTES = 64 << 20  # a save that failed with less free space than this failed on a full disk
# (the last: the sharded model of an --fsdp run, a DCP folder complete once its .metadata is written)
WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "model_sharded/.metadata")
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


def check_resume_settings(config: PI0Config | PI0FastConfig, checkpoint: str | Path) -> None:
    """Refuse resuming a checkpoint trained with other model settings, naming each (`action_horizon 4 there, 8
    now`), instead of failing later on a tensor shape: every setting of the checkpoint's `config.json`."""
    checkpoint = Path(checkpoint)
    if not (checkpoint / "config.json").is_file():
        raise ValueError(f"--resume-from-checkpoint {checkpoint} has no config.json: not a checkpoint of pi0-torch "
                         "train (LoRA checkpoints of versions that trained LoRA through peft cannot be resumed)")
    saved_config = type(config).from_pretrained(checkpoint)
    names = [name for name, parameter in inspect.signature(type(config).__init__).parameters.items()
             if name != "self" and parameter.kind is not inspect.Parameter.VAR_KEYWORD]
    saved = {name: getattr(saved_config, name) for name in names}
    differing = [f"{name} {value!r} there, {getattr(config, name)!r} now" for name, value in saved.items()
                 if value != getattr(config, name)]
    if differing:
        raise ValueError(f"--resume-from-checkpoint {checkpoint} was trained with other model settings: "
                         f"{'; '.join(differing)} (--model / --config-overrides / --rtc-max-delay); resume with the "
                         "run's settings, or start a new --output-dir")


def source_fingerprint(value: Any) -> str | None:
    """A digest of the files a path-valued setting names ([`SOURCE_SETTINGS`]), so that a copy elsewhere counts as
    the same and other files at the same path do not: a LeRobot dataset by its `meta/` folder (info, tasks,
    episodes, statistics), another folder by the files directly in it, a file by itself; of each file its name, its
    size and its first and last `FINGERPRINT_BYTES`. None when `value` names nothing on disk (a preset, `test`,
    `dataset`)."""
    if not isinstance(value, str) or not value:
        return None
    path = Path(value).expanduser()
    if (path / "meta" / "info.json").is_file():
        base = path / "meta"
        names = sorted(p for p in base.rglob("*") if p.is_file())
    elif path.is_dir():
        base, names = path, sorted(p for p in path.iterdir() if p.is_file())
    elif path.is_file():
        base, names = path.parent, [path]
    else:
        return None
    digest = hashlib.sha256()
    for name in names:
        size = name.stat().st_size
        digest.update(f"{name.relative_to(base)}\0{size}\0".encode())
        with name.open("rb") as handle:
            digest.update(handle.read(FINGERPRINT_BYTES))
            if size > FINGERPRINT_BYTES:
                handle.seek(max(FINGERPRINT_BYTES, size - FINGERPRINT_BYTES))
                digest.update(handle.read())
    return digest.hexdigest()


def run_record(settings: TrainSettings) -> dict[str, Any]:
    """What every checkpoint of a run records of it (in its `TRAIN_SETTINGS_FILE`), for [`check_resume_run`]: the
    settings as JSON values, and the fingerprints of the files its path settings name ([`source_fingerprint`])."""
    record = json.loads(json.dumps(vars(settings), default=str))
    record[SOURCES_KEY] = {name: source_fingerprint(getattr(settings, name)) for name in SOURCE_SETTINGS}
    return record


def check_resume_run(record: Mapping[str, Any], checkpoint: str | Path) -> None:
    """Hold a resumed run's settings ([`run_record`]) against those its checkpoint recorded, so that it never
    records one thing and does another: a change of a setting in `RESUME_REFUSED` (the data, the model and its
    processor, what trains, the batches) is refused (`ValueError` naming each flag, its value there and now); a
    change of any other (`RESUME_APPLIED`: the schedule, the optimizer, the intervals) is applied from the
    checkpoint's step on, and a warning names each. A path setting names the same thing when its files are the same:
    a dataset copied elsewhere resumes (named in the warning), other files at the same path are refused. A
    checkpoint written before runs recorded their settings is resumed with a warning that nothing was checked."""
    checkpoint = Path(checkpoint)
    try:
        saved = json.loads((checkpoint / TRAIN_SETTINGS_FILE).read_text())
    except FileNotFoundError:
        logger.warning("%s records no run settings (written by an earlier pi0-torch): this run's settings are not "
                       "checked against the run it continues", checkpoint)
        return
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"--resume-from-checkpoint {checkpoint}: its {TRAIN_SETTINGS_FILE} is unreadable "
                         f"({first_line(error)})") from None
    if not isinstance(saved, dict):
        raise ValueError(f"--resume-from-checkpoint {checkpoint}: its {TRAIN_SETTINGS_FILE} is not a JSON object")
    fingerprints = (saved.get(SOURCES_KEY) or {}, record[SOURCES_KEY])
    refused, applied = [], []
    for name in RESUME_REFUSED + RESUME_APPLIED:
        if name not in saved:  # a setting newer than the checkpoint
            continue
        there, now = _comparable(name, saved[name]), _comparable(name, record[name])
        before, after = (prints.get(name) for prints in fingerprints)
        files_known = before is not None and after is not None
        if files_known and before != after:
            refused.append(f"{flag_name(name)} {_shown(now)} holds other files than when the checkpoint was written"
                           if there == now else _difference(name, there, now))
        elif there == now:
            continue
        elif files_known:
            applied.append(f"{flag_name(name)} {_shown(there)} -> {_shown(now)} (the same files)")
        elif name in RESUME_REFUSED:
            refused.append(_difference(name, there, now))
        else:
            applied.append(f"{flag_name(name)} {_shown(there)} -> {_shown(now)}")
    if refused:
        raise ValueError(f"--resume-from-checkpoint {checkpoint} continues a run with other settings: "
                         f"{'; '.join(refused)}. They make the checkpoint's weights, optimizer state and processor what "
                         "they are: resume with the run's settings, or start a new --output-dir")
    if applied:
        logger.warning("resuming %s with changed settings, applied from its step on: %s", checkpoint, "; ".join(applied))


def _comparable(name: str, value: Any) -> Any:
    return sorted(value) if name == "freeze" and isinstance(value, list) else value


def _difference(name: str, there: Any, now: Any) -> str:
    """`--flag A there, B now`; of two mappings only the keys that differ (`--config-overrides action_horizon 4
    there, 8 now`)."""
    if isinstance(there, dict) and isinstance(now, dict):
        keys = [key for key in {**there, **now} if there.get(key, ()) != now.get(key, ())]
        return "; ".join(f"{flag_name(name)} {key} {_shown(there.get(key, '(unset)'))} there, "
                         f"{_shown(now.get(key, '(unset)'))} now" for key in keys)
    return f"{flag_name(name)} {_shown(there)} there, {_shown(now)} now"


def _shown(value: Any) -> str:
    return value if isinstance(value, str) else repr(value)


class CheckpointSaveError(OSError):
    """Writing a checkpoint or the final model failed ([`save_failed`] says why and how to go on)."""


def save_failed(what: str, run_dir: str | Path, error: BaseException) -> CheckpointSaveError:
    """The error to raise after writing `what` (`checkpoint-6`, `the final model`) into `run_dir` failed with
    `error` and its partial files were left aside: it says that the disk is full when it is (an ENOSPC / EDQUOT
    error, or less than `FULL_DISK_BYTES` free: torch's writer reports a full disk only as an `inline_container`
    error such as "unexpected pos 576 vs 534") and that resuming continues from the last complete checkpoint."""
    run_dir = Path(run_dir)
    full = any(getattr(cause, "errno", None) in (errno.ENOSPC, errno.EDQUOT)
               or "No space left on device" in str(cause) or "Disk quota exceeded" in str(cause)
               for cause in _causes(error))
    try:
        full = full or shutil.disk_usage(run_dir).free < FULL_DISK_BYTES
    except OSError:
        pass
    steps = sorted(step for path in (run_dir.iterdir() if run_dir.is_dir() else ()) if (step := _checkpoint_step(path)) is not None)
    last = f"{PREFIX_CHECKPOINT_DIR}-{steps[-1]}" if steps else "none yet: the run starts over"
    return CheckpointSaveError(
        f"saving {what} into {run_dir} failed: {'the disk is full' if full else 'a write failed'} ({first_line(error)}); "
        "nothing half-written was left in its place. Free some space and run the same command with "
        f"--resume-from-checkpoint latest: it continues from the last complete checkpoint ({last})"
    )


def _causes(error: BaseException) -> Iterator[BaseException]:
    """`error` and the errors it was raised from."""
    while error is not None:
        yield error
        error = error.__cause__ or error.__context__


def final_step(output_dir: str | Path) -> int | None:
    """The step of the final model in `output_dir`, from its run settings file (written last); None without one."""
    try:
        step = json.loads((Path(output_dir) / TRAIN_SETTINGS_FILE).read_text()).get(FINAL_STEP_KEY)
    except (OSError, ValueError, AttributeError):
        return None
    return step if isinstance(step, int) else None


def save_final_model(model: PI0ForActionGeneration, processor: PI0Processor, output_dir: str | Path,
                     settings: Mapping[str, Any], step: int, policy_settings: PolicySettings | None = None) -> None:
    """Model + processor + the run's `settings` (with the final `step`) into `output_dir`, next to the checkpoint
    folders, and `policy_settings` (the base model's recommended inference settings, `policy_settings.json`) when
    given: written into a hidden folder, flushed to disk, and moved into place with the settings file last, so a
    run killed while saving never leaves a half-written final model that looks finished ([`final_step`]). A write
    that fails (a full disk) removes the hidden folder and raises [`CheckpointSaveError`] ([`save_failed`])."""
    output = Path(output_dir)
    staging = output / files.partial_name("final", "save")
    shutil.rmtree(staging, ignore_errors=True)  # an earlier attempt
    try:
        staging.mkdir(parents=True)
        files.claim(staging)
        model.save_pretrained(staging)
        processor.save_pretrained(staging)
        if policy_settings is not None and policy_settings != PolicySettings():
            policy_settings.save(staging)
        record = {**settings, FINAL_STEP_KEY: step}
        (staging / TRAIN_SETTINGS_FILE).write_text(json.dumps(record, indent=2, default=str) + "\n")
        files.sync_tree(staging)
    except (OSError, RuntimeError, SafetensorError) as error:  # a full disk, most often
        failure = save_failed("the final model", output, error)
        shutil.rmtree(staging, ignore_errors=True)
        raise failure from error
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
