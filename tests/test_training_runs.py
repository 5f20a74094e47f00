"""Issue 28, classes 2, 5, 6 and 9: what `pi0-torch train` does with its output folder, its checkpoints and the
model folder it fine-tunes.

- a fresh run never writes into another run's folder (unless `--overwrite`, which removes that run first);
- re-running a finished run with `latest` trains nothing and rewrites nothing;
- `latest` skips any checkpoint that cannot be resumed from, naming it, and never suggests unpickling;
- resuming with other model settings names them;
- fine-tuning from a model folder keeps every processor setting unless a flag overrides it (with a warning);
- one corrupt value in a dataset is refused, naming its episode and frame.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from test_training import TINY, settings

from pi0_torch.data.lerobot_dataset import LeRobotDatasetError, LeRobotEpisodeDataset
from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.data.synthetic_data import write_synthetic_dataset
from pi0_torch.envs.demos import record_demos
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.training.checkpoints import TRAIN_SETTINGS_FILE, resolve_resume_checkpoint
from pi0_torch.training.model_setup import run_processor_settings
from pi0_torch.training.pi0_trainer import EMA_FILE
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import train_policy
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
    aloha = PI0Processor(build_test_tokenizer(), norm_stats=stats, value_conversion="aloha", delta_action_mask=[True] * 6)
    base = settings_from(dict(dataset="d", model="m", output_dir="o"))
    assert run_processor_settings(base, aloha)["value_conversion"] == "aloha"
    assert run_processor_settings(base, aloha)["delta_action_mask"] == [True] * 6
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
