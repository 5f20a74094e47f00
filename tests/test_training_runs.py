"""Issue 28, classes 2, 5, 6 and 9, and issue 38, classes 10, 11 and 15: what `pi0-torch train` does with its
output folder, its checkpoints and the model folder it fine-tunes.

- a fresh run never writes into another run's folder (unless `--overwrite`, which removes that run first);
- re-running a finished run with `latest` trains nothing and rewrites nothing;
- `latest` skips any checkpoint that cannot be resumed from, naming it, and never suggests unpickling;
- resuming with other model settings names them; with other run settings it refuses them by name or applies them
  and says so;
- a save that fails on a full disk says so, leaves nothing half-written, and resuming continues the run;
- fine-tuning from a model folder keeps every processor setting unless a flag overrides it (with a warning);
- one corrupt value in a dataset is refused, naming its episode and frame; so are video timestamps that would
  select other frames (in one line from the command).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file
from test_training import TINY, losses, settings

from pi0_torch.data.lerobot_dataset import LeRobotDatasetError, LeRobotEpisodeDataset
from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.data.synthetic_data import CAMERA_KEY, write_synthetic_dataset
from pi0_torch.envs.demos import record_demos
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.training import checkpoints
from pi0_torch.training.checkpoints import TRAIN_SETTINGS_FILE, CheckpointSaveError, resolve_resume_checkpoint
from pi0_torch.training.model_setup import run_processor_settings
from pi0_torch.training.pi0_trainer import EMA_FILE, openpi_learning_rate
from pi0_torch.training.settings import RESUME_APPLIED, RESUME_REFUSED, RESUME_UNCHECKED, TrainSettings
from pi0_torch.training.trainer import main, train_policy
from pi0_torch.utils import files
from pi0_torch.utils.files import OutputPathError
from pi0_torch.utils.files import OutputPathError

DEMO_POLICY = Path(__file__).resolve().parents[1] / "pi0_torch" / "demo_policy"


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("data") / "reach", num_episodes=8, num_heldout=2,
                                   episode_length=8, image_size=32, storage="image", seed=1)


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def finished_run(dataset_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of 4 steps with checkpoints at 2 and 4 and EMA (never modified by the tests: copy it)."""
    output = tmp_path_factory.mktemp("finished") / "run"
    train_policy(settings(dataset_root, output, max_steps=4, save_steps=2, ema_decay=0.9))
    return output


def copy_run(finished_run: Path, tmp_path: Path) -> Path:
    output = tmp_path / "run"
    shutil.copytree(finished_run, output)
    return output


# ---------------------------------------------------------------------------------------------------- the run folder


def test_a_fresh_run_never_writes_into_another_runs_folder(dataset_root: Path, finished_run: Path, tmp_path: Path) -> None:
    """Issue 28.2: a fresh `--max-steps 3` run into a finished run's folder overwrote its checkpoint-2 and final
    model, and `latest` then mixed the two runs."""
    output = copy_run(finished_run, tmp_path)
    before = tree(output)
    with pytest.raises(OutputPathError, match=r"exists and is not empty \(pass --overwrite"):
        train_policy(settings(dataset_root, output, max_steps=3, save_steps=2))
    (output / "notes.md").write_text("mine")
    with pytest.raises(OutputPathError, match=r"did not write \(notes.md\)"):
        train_policy(settings(dataset_root, output, max_steps=3, save_steps=2, overwrite=True))
    (output / "notes.md").unlink()
    assert tree(output) == before
    with pytest.raises(ValueError, match="--overwrite starts .* over, --resume-from-checkpoint .* continues"):
        train_policy(settings(dataset_root, output, max_steps=3, overwrite=True, resume_from_checkpoint="latest"))
    with pytest.raises(OutputPathError, match="lies inside the input"):
        train_policy(settings(dataset_root, dataset_root / "run", max_steps=3))
    result = train_policy(settings(dataset_root, output, max_steps=3, save_steps=2, overwrite=True))
    assert result["steps_trained"] == 3
    assert sorted(p.name for p in output.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-3"]  # none of the old
    assert json.loads((output / TRAIN_SETTINGS_FILE).read_text())["final_step"] == 3


def test_two_runs_into_one_folder_the_second_is_refused(dataset_root: Path, tmp_path: Path) -> None:
    """Round 5, item 4: two runs started at once into one folder left a checkpoint with the first one's weights and
    the second one's settings. The folder is held by its run (a lock beside it that the kernel drops when the holder
    dies, however it dies); a second run is refused in one line, naming the holder."""
    output = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from pi0_torch.utils.files import output_lock
with output_lock({str(output)!r}):
    print("held", flush=True)
    time.sleep(600)
"""], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputPathError, match=rf"{re.escape(str(output))} is being written by another run \(pid "
                                                  rf"{holder.pid} on .*\); wait for it to finish or choose another"):
            train_policy(settings(dataset_root, output, max_steps=1))
    finally:
        holder.kill()  # SIGKILL: no cleanup runs in the holder
        holder.wait()
    assert train_policy(settings(dataset_root, output, max_steps=1))["steps_trained"] == 1
    assert not any(path.name.endswith(files.LOCK_SUFFIX) for path in tmp_path.iterdir())  # released and removed


def test_rerunning_a_finished_run_with_latest_trains_nothing(dataset_root: Path, finished_run: Path, tmp_path: Path,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    """Issue 28.2: re-running a finished run with `latest` trained steps 5, 6, 7 (the Trainer always takes one
    more step after a resume) and rewrote the final model."""
    output = copy_run(finished_run, tmp_path)
    before = tree(output)
    rerun = settings(dataset_root, output, max_steps=4, save_steps=2, ema_decay=0.9, resume_from_checkpoint="latest")
    with caplog.at_level(logging.INFO):
        result = train_policy(rerun)
    assert result["steps_trained"] == 0 and "nothing to train" in caplog.text
    assert tree(output) == before
    # killed between its last checkpoint and the final save: the final model is written from checkpoint-4, untrained
    (output / TRAIN_SETTINGS_FILE).unlink()
    final_before = load_file(str(output / "model.safetensors"))
    result = train_policy(rerun)
    assert result["steps_trained"] == 0 and sorted(p.name for p in output.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-4"]
    final = load_file(str(output / "model.safetensors"))
    ema = load_file(str(output / "checkpoint-4" / EMA_FILE))
    for name, average in ema.items():
        torch.testing.assert_close(final[name], average)  # the EMA weights of step 4, as the first run saved them
        torch.testing.assert_close(final[name], final_before[name])
    # a longer --max-steps continues the run
    assert train_policy(replace(rerun, max_steps=6))["steps_trained"] == 2


# ---------------------------------------------------------------------------------------------------- checkpoints


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


CORRUPTIONS = {
    "model.safetensors truncated": ("model.safetensors", _truncate),
    "model.safetensors garbage": ("model.safetensors", lambda p: p.write_bytes(b"\x00garbage" * 100)),
    "model.safetensors empty": ("model.safetensors", lambda p: p.write_bytes(b"")),
    "optimizer.pt garbage": ("optimizer.pt", lambda p: p.write_bytes(b"garbage" * 100)),
    "optimizer.pt empty": ("optimizer.pt", lambda p: p.write_bytes(b"")),
    "optimizer.pt truncated": ("optimizer.pt", _truncate),
    "scheduler.pt garbage": ("scheduler.pt", lambda p: p.write_bytes(b"garbage")),
    "rng_state.pth truncated": ("rng_state.pth", _truncate),
    "ema truncated": (EMA_FILE, _truncate),
    "trainer_state.json a list": ("trainer_state.json", lambda p: p.write_text("[1, 2]")),
    "trainer_state.json not JSON": ("trainer_state.json", lambda p: p.write_text("{")),
    "trainer_state.json without a step": ("trainer_state.json", lambda p: p.write_text("{}")),
}


@pytest.mark.parametrize("corruption", sorted(CORRUPTIONS))
def test_latest_skips_an_unreadable_newest_checkpoint(corruption: str, finished_run: Path, tmp_path: Path,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    """Issue 28.5: 6 of 11 corruptions of the newest checkpoint crashed resume with a traceback, one advising
    `weights_only=False`. Each is now skipped with a warning naming the checkpoint and the file."""
    output = copy_run(finished_run, tmp_path)
    name, corrupt = CORRUPTIONS[corruption]
    corrupt(output / "checkpoint-4" / name)
    with caplog.at_level(logging.INFO):
        assert resolve_resume_checkpoint(output, "latest") == str(output / "checkpoint-2")
    warning = next(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert f"skipping {output / 'checkpoint-4'}: it cannot be resumed from" in warning and name in warning, warning
    assert "weights_only" not in caplog.text and "unpickl" not in caplog.text.lower()


def test_resume_from_a_fallback_checkpoint_continues_the_run(dataset_root: Path, finished_run: Path, tmp_path: Path) -> None:
    output = copy_run(finished_run, tmp_path)
    (output / "checkpoint-4" / "optimizer.pt").write_bytes(b"garbage")
    resumed = train_policy(settings(dataset_root, output, max_steps=4, save_steps=2, ema_decay=0.9,
                                    resume_from_checkpoint="latest"))
    assert resumed["steps_trained"] == 2  # steps 3 and 4 again, from checkpoint-2
    assert resolve_resume_checkpoint(output, "latest") == str(output / "checkpoint-4")  # written anew, whole
    (output / "checkpoint-2" / "model.safetensors").unlink()
    (output / "checkpoint-4" / "model.safetensors").write_bytes(b"")
    with pytest.raises(ValueError, match="none of the 2 checkpoints .* can be resumed from"):
        resolve_resume_checkpoint(output, "latest")  # not a fresh run over two broken ones


def test_resuming_with_other_model_settings_names_them(dataset_root: Path, finished_run: Path, tmp_path: Path) -> None:
    """Issue 28.9: another action_horizon failed on a tensor shape ('observations[0].actions: expected shape [4, 3]')."""
    output = copy_run(finished_run, tmp_path)
    overrides = {**TINY, "action_horizon": 8}
    with pytest.raises(ValueError, match=r"trained with other model settings: action_horizon 4 there, 8 now"):
        train_policy(settings(dataset_root, output, max_steps=6, save_steps=2, ema_decay=0.9, config_overrides=overrides,
                              resume_from_checkpoint="latest"))


# ---------------------------------------------------------------------------------------------------- resuming with other settings


def test_every_setting_has_a_resume_rule() -> None:
    """Issue 38.11: each setting a resumed run may change is either refused or applied (and logged); a new setting
    must be put in one of the three groups."""
    groups = (RESUME_REFUSED, RESUME_APPLIED, RESUME_UNCHECKED)
    names = [name for group in groups for name in group]
    assert sorted(names) == sorted(f.name for f in dataclasses.fields(TrainSettings))  # each once


@pytest.fixture(scope="module")
def other_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("other") / "reach", num_episodes=8, num_heldout=2,
                                   episode_length=8, image_size=32, storage="image", seed=2)


REFUSED_CHANGES = {  # a change of what the run is -> how the refusal names it
    "another dataset": (lambda data: dict(dataset=str(data)), r"--dataset \S+/data\d*/reach there, \S+/other\d*/reach now"),
    "lora": (lambda data: dict(lora=True, ema_decay=None), r"--lora False there, True now"),
    "freeze vision": (lambda data: dict(freeze=["vision"]), r"--freeze \[\] there, \['vision'\] now"),
    "norm stats of the model": (lambda data: dict(norm_stats="model"), r"--norm-stats auto there, model now"),
    "delta actions": (lambda data: dict(delta_action_mask=[True, False]), r"--delta-action-mask None there, \[True, False\] now"),
    "camera": (lambda data: dict(camera_map={"base_0_rgb": CAMERA_KEY}), rf"--camera base_0_rgb \(unset\) there, {CAMERA_KEY} now"),
    "batch size": (lambda data: dict(batch_size=8), r"--batch-size 4 there, 8 now"),
    "seed": (lambda data: dict(seed=1), r"--seed 0 there, 1 now"),
    "two at once": (lambda data: dict(seed=1, train_split="heldout"), r"--train-split train there, heldout now; --seed 0 there"),
}


@pytest.mark.parametrize("change", sorted(REFUSED_CHANGES))
def test_resuming_refuses_a_change_of_what_the_run_is_by_name(change: str, dataset_root: Path, other_dataset: Path,
                                                              finished_run: Path, tmp_path: Path) -> None:
    """Issue 38.11: another --dataset was accepted without a word, `--norm-stats model` was recorded while the
    checkpoint's statistics were used, `--lora` / `--freeze vision` failed on an optimizer size. A change of the
    data, the model and its processor, what trains, or the batches is refused, naming each flag, before anything
    is loaded or written."""
    output = copy_run(finished_run, tmp_path)
    before = tree(output)
    changes, expected = REFUSED_CHANGES[change]
    resumed = settings(dataset_root, output, max_steps=6, save_steps=2, ema_decay=0.9, resume_from_checkpoint="latest")
    with pytest.raises(ValueError, match=rf"--resume-from-checkpoint \S+/checkpoint-4 continues a run with other settings: "
                                         rf"{expected}.*: resume with the run's settings, or start a new --output-dir"):
        train_policy(replace(resumed, **changes(other_dataset)))
    assert tree(output) == before


def test_resuming_applies_a_changed_schedule_and_intervals_and_says_so(dataset_root: Path, finished_run: Path,
                                                                       tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 38.11: `--learning-rate 1.0 --warmup-steps 1` on resume kept the checkpoint's peak learning rate (in
    the scheduler state), weight decay (in the optimizer state) and save interval (in the trainer state), without a
    word. They now apply from the checkpoint's step on, a warning names each, and the checkpoints and the final
    settings file record what was done."""
    changed = settings(dataset_root, tmp_path / "resumed", max_steps=4, save_steps=1, ema_decay=0.5, learning_rate=1e-2,
                       end_learning_rate=5e-3, warmup_steps=1, weight_decay=0.1,
                       resume_from_checkpoint=str(finished_run / "checkpoint-2"))
    with caplog.at_level(logging.WARNING):
        result = train_policy(changed)
    warning = next(r.getMessage() for r in caplog.records if "with changed settings" in r.getMessage())
    for part in ("--learning-rate 0.001 -> 0.01", "--end-learning-rate 0.0001 -> 0.005", "--warmup-steps 2 -> 1",
                 "--weight-decay 1e-10 -> 0.1", "--ema-decay 0.9 -> 0.5", "--save-steps 2 -> 1"):
        assert part in warning, warning
    rates = {entry["step"]: entry["learning_rate"] for entry in result["log_history"] if "learning_rate" in entry}
    for step in (3, 4):  # the logged rate of step k is the schedule at optimizer step k - 1
        assert rates[step] == pytest.approx(openpi_learning_rate(step - 1, 1e-2, 1, 4, 5e-3), rel=1e-6)
    output = Path(result["output_dir"])
    assert sorted(p.name for p in output.glob("checkpoint-*")) == ["checkpoint-3", "checkpoint-4"]  # every step now
    groups = torch.load(output / "checkpoint-4" / "optimizer.pt", weights_only=True)["param_groups"]
    assert [g["weight_decay"] for g in groups] == [0.1, 0.0] and {g["initial_lr"] for g in groups} == {1e-2}
    for record in (output / "checkpoint-4" / TRAIN_SETTINGS_FILE, output / TRAIN_SETTINGS_FILE):
        saved = json.loads(record.read_text())
        assert (saved["learning_rate"], saved["warmup_steps"], saved["weight_decay"], saved["save_steps"]) == (1e-2, 1, 0.1, 1)
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # the same settings again: nothing changed, nothing said
        assert train_policy(replace(changed, resume_from_checkpoint="latest"))["steps_trained"] == 0
    assert "changed settings" not in caplog.text


def test_a_copy_of_the_dataset_resumes_and_other_files_at_its_path_do_not(dataset_root: Path, finished_run: Path,
                                                                          tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The dataset is known by its files (meta/: info, tasks, episodes, statistics), not its path: a copy staged
    elsewhere (a cluster job's local disk) resumes, saying so; other episodes recorded at the same path do not."""
    output = copy_run(finished_run, tmp_path)
    copy = Path(shutil.copytree(dataset_root, tmp_path / "staged" / "reach"))
    with caplog.at_level(logging.WARNING):
        resumed = train_policy(settings(copy, output, max_steps=4, save_steps=2, ema_decay=0.9, resume_from_checkpoint="latest"))
    assert resumed["steps_trained"] == 0  # (finished: the settings are checked first)
    assert f"--dataset {dataset_root} -> {copy} (the same files)" in caplog.text
    run = settings(copy, tmp_path / "on-copy", max_steps=2, save_steps=1)
    train_policy(run)
    shutil.rmtree(copy)
    write_synthetic_dataset(copy, num_episodes=8, num_heldout=2, episode_length=8, image_size=32, storage="image", seed=5)
    with pytest.raises(ValueError, match=rf"--dataset {copy} holds other files than when the checkpoint was written"):
        train_policy(replace(run, max_steps=3, resume_from_checkpoint="latest"))


# ---------------------------------------------------------------------------------------------------- a full disk


def _fail_on_final_model(original):
    def save_pretrained(self, folder, *args, **kwargs):
        if ".final" in str(folder):
            raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")
        return original(self, folder, *args, **kwargs)

    return save_pretrained


def _fail_on_checkpoint_4(original):
    def save(obj, path, *args, **kwargs):
        if "checkpoint-4" in str(path):
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534")
        return original(obj, path, *args, **kwargs)

    return save


@pytest.mark.parametrize("what", ["checkpoint-4", "the final model"])
def test_a_save_on_a_full_disk_says_so_and_resuming_continues_the_run(what: str, dataset_root: Path, finished_run: Path,
                                                                      tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 38.15: a full disk while saving a checkpoint ended in torch's `inline_container` error (resume then
    worked). The error now says that the disk is full, that nothing half-written was left, and that resuming
    continues from the last complete checkpoint; and it does. torch's writer reports a full disk only as that
    error, so the free space decides (here made to look full); safetensors and OSError name ENOSPC themselves."""
    output = tmp_path / "run"
    run = settings(dataset_root, output, max_steps=4, save_steps=2, ema_decay=0.9)
    if what == "checkpoint-4":
        monkeypatch.setattr(checkpoints, "FULL_DISK_BYTES", 1 << 62)
        monkeypatch.setattr(torch, "save", _fail_on_checkpoint_4(torch.save))
        cause = r"\[enforce fail at inline_container.cc:672\] . unexpected pos 576 vs 534"
    else:
        monkeypatch.setattr(PI0ForActionGeneration, "save_pretrained", _fail_on_final_model(PI0ForActionGeneration.save_pretrained))
        cause = r"Error while serializing: I/O error: No space left on device \(os error 28\)"
    last = "checkpoint-2" if what == "checkpoint-4" else "checkpoint-4"
    with pytest.raises(CheckpointSaveError, match=rf"^saving {what} into {output} failed: the disk is full \({cause}\); "
                                                  r"nothing half-written was left in its place\. Free some space and run the "
                                                  rf"same command with --resume-from-checkpoint latest: it continues from "
                                                  rf"the last complete checkpoint \({last}\)$"):
        train_policy(run)
    assert not [p.name for p in output.iterdir() if ".partial" in p.name]  # removed: the space is free again
    assert not (output / TRAIN_SETTINGS_FILE).exists()  # no final model that looks finished
    assert (output / "checkpoint-4").is_dir() == (what == "the final model")
    monkeypatch.undo()
    resumed = train_policy(replace(run, resume_from_checkpoint="latest"))
    assert resumed["steps_trained"] == (2 if what == "checkpoint-4" else 0)
    expected = json.loads((finished_run / "checkpoint-4" / "trainer_state.json").read_text())["log_history"]
    assert losses(resumed["log_history"]) == pytest.approx(losses(expected), rel=1e-6)
    assert json.loads((output / TRAIN_SETTINGS_FILE).read_text())["final_step"] == 4


# ---------------------------------------------------------------------------------------------------- processor settings


def test_fine_tuning_the_demo_policy_keeps_its_processor_settings(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 28.6: `--model pi0_torch/demo_policy` wrote `"delta_action_mask": null` (the policy has [true, true,
    false]): the loss at step 1 was 1.50 against 0.17 and PickPlace went from 80% to 0%."""
    data = tmp_path / "demos"
    record_demos("pi0_torch/PickPlace-v0", 4, data, image_size=48, storage="image")
    base = dict(dataset=str(data), model=str(DEMO_POLICY), max_steps=1, batch_size=8, warmup_steps=1,
                logging_steps=1, save_steps=1000, seed=0, progress=False)
    kept = train_policy(settings_from(base, output_dir=str(tmp_path / "kept")))
    saved = json.loads((Path(kept["output_dir"]) / "processor_config.json").read_text())
    reference = json.loads((DEMO_POLICY / "processor_config.json").read_text())
    for name in ("delta_action_mask", "value_conversion", "norm_mode", "min_norm_scale", "float_image_range"):
        assert saved[name] == reference[name], name
    # the inference settings it was validated with come along (issue 38.3)
    assert (Path(kept["output_dir"]) / "policy_settings.json").read_text() == (DEMO_POLICY / "policy_settings.json").read_text()
    assert kept["log_history"][0]["loss"] < 0.5  # in the policy's own action space (measured 0.24)
    with caplog.at_level(logging.WARNING):
        absolute = train_policy(settings_from(base, output_dir=str(tmp_path / "absolute"), delta_action_mask=[False] * 3))
    assert absolute["log_history"][0]["loss"] > 1.0  # another action space: what dropping the mask did (measured 2.3)
    assert "--delta-action-mask [False, False, False] replaces the delta_action_mask [True, True, False]" in caplog.text
    saved = json.loads((tmp_path / "absolute" / "processor_config.json").read_text())
    assert saved["delta_action_mask"] == [False, False, False]


def settings_from(base: dict, **changes: object) -> TrainSettings:
    return TrainSettings(**{**base, **changes})


def test_a_value_conversion_is_inherited_and_none_turns_it_off(caplog: pytest.LogCaptureFixture) -> None:
    stats = {key: NormStats(mean=np.zeros(14), std=np.ones(14)) for key in ("state", "actions")}
    aloha = PI0Processor(build_test_tokenizer(), norm_stats=stats, value_conversion="aloha",
                         delta_action_mask=[True] * 6 + [False] * 8)
    base = settings_from(dict(dataset="d", model="m", output_dir="o"))
    assert run_processor_settings(base, aloha)["value_conversion"] == "aloha"
    assert run_processor_settings(base, aloha)["delta_action_mask"] == [True] * 6 + [False] * 8
    with caplog.at_level(logging.WARNING):
        chosen = run_processor_settings(replace(base, value_conversion="none"), aloha)
    assert chosen["value_conversion"] is None and "--value-conversion none replaces the value_conversion aloha" in caplog.text
    assert run_processor_settings(base, None) == {}  # a preset: the processor's defaults


# ---------------------------------------------------------------------------------------------------- data


def test_one_corrupt_value_in_a_dataset_is_refused_naming_episode_and_frame(tmp_path: Path) -> None:
    """Issue 28.9: one action of 3e38 gave norm stats with std 3.9e37, and training went on."""
    rng = np.random.default_rng(0)
    episodes = []
    for number in range(4):
        actions = rng.uniform(-1, 1, (10, 2)).astype(np.float32)
        if number == 2:
            actions[5, 1] = 3e38
        episodes.append(EpisodeRecord("go", {"observation.images.top": np.zeros((10, 8, 8, 3), np.uint8)},
                                      {"observation.state": rng.uniform(-1, 1, (10, 2)), "action": actions}))
    root = write_lerobot_dataset(tmp_path / "data", episodes, fps=10, storage="image",
                                 vector_names={"observation.state": ["x", "y"], "action": ["x", "y"]})
    with pytest.raises(LeRobotDatasetError, match=r"'action' dim 1 is 3e\+38 at episode 2 frame 5"):
        LeRobotEpisodeDataset(root, 4, progress=False).check_value_spread()
    with pytest.raises(LeRobotDatasetError, match="episode 2 frame 5"):
        train_policy(settings(root, tmp_path / "run", max_steps=1, train_split=None))
    assert not (tmp_path / "run").exists()


def _zero_timestamps(table: pa.Table) -> pa.Table:
    zeros = pa.array(np.zeros(len(table)), table.schema.field("timestamp").type)
    return table.set_column(table.schema.get_field_index("timestamp"), "timestamp", zeros)


def _null_images(table: pa.Table) -> pa.Table:
    index = table.schema.get_field_index(CAMERA_KEY)
    return table.set_column(index, CAMERA_KEY, pa.nulls(len(table), table.schema.field(index).type))


BROKEN_DATA = {  # storage, how the first data file is broken, --num-workers, what the one line says after the file
    "video timestamps at 0": ("video", _zero_timestamps, 0,
                              "episode 0 frame 1 has timestamp 0 s, but its video frame is at 0.1 s"),
    "null image cells, read by a DataLoader worker": ("image", _null_images, 1,
                                                      rf"episode [01] frame \d+, camera '{CAMERA_KEY}': the image cell is empty"),
}


@pytest.mark.parametrize("broken", sorted(BROKEN_DATA))
def test_broken_data_stops_the_command_in_one_line(broken: str, tmp_path: Path, capsys) -> None:
    """Issue 38.10 / 38.15: with every parquet timestamp at 0, episode 0 trained on 1 distinct frame of 18 and
    `train` exited 0; a null image cell gave a traceback (read by a DataLoader worker: "Caught LeRobotDatasetError in
    DataLoader worker process 0."). The command now exits 1 with one line naming the data file, episode and frame."""
    storage, corrupt, workers, expected = BROKEN_DATA[broken]
    root = write_synthetic_dataset(tmp_path / "reach", num_episodes=2, episode_length=18, image_size=32, seed=1, storage=storage)
    path = root / "data" / "chunk-000" / "file-000.parquet"
    pq.write_table(corrupt(pq.read_table(path)), path)
    code = main(["--dataset", str(root), "--model", "pi0_small", "--config-overrides", json.dumps(TINY), "--tokenizer",
                 "test", "--output-dir", str(tmp_path / "run"), "--max-steps", "1", "--batch-size", "2",
                 "--num-workers", str(workers)])
    error = capsys.readouterr().err.strip().splitlines()[-1]  # a line of its own, after the progress bar
    assert code == 1 and re.match(rf"error: {re.escape(str(path))}: {expected}", error), error


def test_a_diverged_run_is_not_saved_as_a_finished_policy(dataset_root: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A learning rate of 1e6: the loss or the weights go non-finite; the run stops naming the step and exits 1, and
    no final model (config.json, weights, the settings' final step) is written."""
    output = tmp_path / "diverged"
    code = main(["--dataset", str(dataset_root), "--model", "pi0_small", "--output-dir", str(output), "--tokenizer",
                 "test", "--config-overrides", json.dumps(TINY), "--max-steps", "6", "--batch-size", "2",
                 "--learning-rate", "1e6", "--logging-steps", "1", "--save-steps", "100", "--no-augment"])
    assert code == 1
    assert re.search(r"error: training diverged( at step \d+)?: .*the final model was not saved", capsys.readouterr().err)
    assert not (output / "config.json").exists() and not (output / TRAIN_SETTINGS_FILE).exists()


def test_norm_stats_of_another_robot_space_are_refused(dataset_root: Path, tmp_path: Path) -> None:
    """Issue 63, round 5 item 10: `--norm-stats` with 3-dim statistics for a 2-dim dataset was cut to 2 dims without a
    word, trained and saved. Refused before anything is written, naming the file and both dims."""
    from pi0_torch.processing.normalization import save_openpi_norm_stats

    state_dim = LeRobotEpisodeDataset(dataset_root, 4, progress=False).state_dim
    stats = {key: NormStats(mean=np.zeros(state_dim + 1), std=np.ones(state_dim + 1)) for key in ("state", "actions")}
    path = save_openpi_norm_stats(tmp_path / "stats", stats)
    with pytest.raises(ValueError, match=rf"--norm-stats {re.escape(str(path))}: .* have {state_dim + 1} state dims, "
                                         rf"the dataset {state_dim}: they describe another robot"):
        train_policy(settings(dataset_root, tmp_path / "run", max_steps=1, norm_stats=str(path)))
    assert not (tmp_path / "run").exists()


def test_a_batch_larger_than_the_dataset_is_named(dataset_root: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 63, round 5 item 10: `--batch-size 1000` on 48 frames trained at 48 without a word."""
    frames = len(LeRobotEpisodeDataset(dataset_root, 4, episodes=None, progress=False))
    with caplog.at_level(logging.WARNING, logger="pi0_torch.training.trainer"):
        train_policy(settings(dataset_root, tmp_path / "run", max_steps=1, batch_size=1000, train_split=None))
    assert f"--batch-size 1000 is more than the {frames} frames of the training episodes" in caplog.text


def test_the_action_key_equal_to_the_state_key_is_refused(dataset_root: Path) -> None:
    """Issue 63, round 5 item 9: `--action-key` equal to the state key gave a pyarrow `KeyError` traceback."""
    with pytest.raises(LeRobotDatasetError, match=r"the action key and the state key are both 'observation.state'"):
        LeRobotEpisodeDataset(dataset_root, 4, state_key="observation.state", action_key="observation.state", progress=False)


def test_ctrl_c_in_train_is_one_line_and_keeps_the_checkpoints(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 63, round 5 item 9: Ctrl-C in `train` printed a traceback (eval says it in one line)."""
    from pi0_torch.training import trainer

    def interrupted(settings: TrainSettings) -> dict:
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "train_policy", interrupted)
    assert main(["--dataset", str(tmp_path / "data"), "--model", "demo", "--output-dir", str(tmp_path / "run")]) == 130
    err = capsys.readouterr().err.strip()
    assert err == (f"stopped (Ctrl-C): the checkpoints saved in {tmp_path / 'run'} so far are kept; the same command "
                   "with --resume-from-checkpoint latest continues"), err


def _libero_like_dataset(root: Path) -> Path:
    """A small LeRobot dataset laid out as openpi's LIBERO conversion writes it: `image`, `wrist_image`, `state` (8)
    and `actions` (7)."""
    rng = np.random.default_rng(0)
    episodes = [EpisodeRecord("put the bowl on the plate",
                              {"image": rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8),
                               "wrist_image": rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)},
                              {"state": rng.uniform(-1, 1, (12, 8)), "actions": rng.uniform(-1, 1, (12, 7))})
                for _ in range(4)]
    return write_lerobot_dataset(root, episodes, fps=10, storage="image",
                                 vector_names={"state": [f"s{i}" for i in range(8)], "actions": [f"a{i}" for i in range(7)]})


def test_openpi_configs_by_name(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 60, item 4: `train --config pi0_libero` takes openpi's TrainConfig values (LIBERO's features and cameras,
    its delta mask, the dataset's norm stats, EMA 0.99, the schedule), each flag given overriding one; the model variant
    is checked against --model; unknown and unfollowable names are one line."""
    from pi0_torch.training.openpi_configs import OPENPI_CONFIGS

    data = _libero_like_dataset(tmp_path / "libero")
    argv = ["--dataset", str(data), "--model", "pi0_small", "--output-dir", str(tmp_path / "run"), "--config",
            "pi0_libero", "--config-overrides", json.dumps({**TINY, "action_dim": 8}), "--tokenizer", "test",
            "--max-steps", "2", "--batch-size", "4", "--logging-steps", "1", "--threads", "1"]
    with caplog.at_level(logging.INFO, logger="pi0_torch.training.trainer"):
        assert main(argv) == 0
    assert "openpi's config pi0_libero, with --batch-size, --max-steps from the command line" in caplog.text
    record = json.loads((tmp_path / "run" / TRAIN_SETTINGS_FILE).read_text())
    settings = record.get("settings", record)
    assert settings["config"] == "pi0_libero" and settings["ema_decay"] == 0.99 and settings["batch_size"] == 4
    assert settings["camera_map"] == {"base_0_rgb": "image", "left_wrist_0_rgb": "wrist_image"}
    processor = PI0Processor.from_pretrained(tmp_path / "run")
    assert processor.delta_action_mask == [True] * 6 + [False] and processor.norm_mode == "zscore"

    mismatched = TrainSettings.from_openpi_config("pi05_libero", dataset=str(data), model="pi0_small", tokenizer="test",
                                                  output_dir=str(tmp_path / "pi05"), config_overrides=dict(TINY))
    with pytest.raises(ValueError, match=r"--config pi05_libero fine-tunes a pi05 model \(openpi starts from "
                                         r"pi05_base\); --model pi0_small is a pi0 model"):
        train_policy(mismatched)
    with pytest.raises(SystemExit):
        main(["--dataset", str(data), "--model", "pi0_small", "--output-dir", str(tmp_path / "x"), "--config"])
    for name, message in (("pi0_libre", "is not one of openpi's training configs that pi0-torch follows: "
                                        + ", ".join(OPENPI_CONFIGS)), ("pi0_droid", "an inference config in openpi")):
        with pytest.raises(ValueError, match=re.escape(message)):
            TrainSettings.from_openpi_config(name, dataset="d", model="m", output_dir="o")


def _two_dim_dataset(root: Path, moving_second_dim: bool) -> Path:
    rng = np.random.default_rng(1)
    episodes = []
    for _ in range(4):
        actions = rng.uniform(-1, 1, (10, 2))
        if not moving_second_dim:
            actions[:, 1] = 0.0  # (a gripper the first task never moves)
        episodes.append(EpisodeRecord("go", {"observation.images.top": rng.integers(0, 256, (10, 16, 16, 3), np.uint8)},
                                      {"observation.state": rng.uniform(-1, 1, (10, 2)), "action": actions}))
    return write_lerobot_dataset(root, episodes, fps=10, storage="image",
                                 vector_names={"observation.state": ["x", "y"], "action": ["x", "y"]})


def test_auto_norm_stats_leave_a_model_whose_statistics_do_not_describe_the_data(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """`--norm-stats auto` keeps a trained model's statistics for data of its robot space; but a dim that never moved
    in the model's data (its scale floored at min_norm_scale) and moves in the dataset normalized to hundreds: the
    demo policy's curriculum, Reach then PickPlace, trained at a loss of 5.7e5. Such a dataset trains with its own
    statistics, saying why."""
    first = train_policy(settings(_two_dim_dataset(tmp_path / "still", False), tmp_path / "first", max_steps=1,
                                  train_split=None, config_overrides={**TINY, "action_dim": 2}))
    with caplog.at_level(logging.WARNING, logger="pi0_torch.training.model_setup"):
        train_policy(settings(_two_dim_dataset(tmp_path / "moving", True), tmp_path / "second", max_steps=1,
                              train_split=None, model=first["output_dir"], config_overrides={}))
    assert re.search(r"norm stats: the dataset's actions dim 1 lies [\d.e+]+ of the model's scale from its centre with "
                     r"a spread of [\d.e+]+ times its own \(beyond 10\); .* trains with the dataset's", caplog.text)
    saved = PI0Processor.from_pretrained(tmp_path / "second").norm_stats["actions"]
    assert saved.std[1] > 0.1  # (the dataset's, not the model's floored 0)
