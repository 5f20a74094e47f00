"""FSDP2 fine-tuning (`pi0-torch train --fsdp`) on gloo processes on CPU: the losses of one process with the same
global batch, the consolidated model, resume on another number of processes, sharded checkpoints, refusals."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from test_training import TINY, losses, settings

from conftest import HANG_S
from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.cli import build_parser
from pi0_torch.data.synthetic_data import write_synthetic_dataset
from pi0_torch.training import fsdp
from pi0_torch.utils import files
from pi0_torch.training.checkpoints import checkpoint_problem, resolve_resume_checkpoint
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.lora import apply_lora
from pi0_torch.training.trainable import freeze
from pi0_torch.training.trainer import train_policy

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(
        tmp_path_factory.mktemp("data") / "reach", num_episodes=8, num_heldout=2, episode_length=8, image_size=32,
        storage="image", seed=1,
    )


def cli_arguments(run: TrainSettings, cpu: bool = True) -> list[str]:
    """`pi0-torch train` options of the settings these tests vary (on the CPU unless `cpu` is False)."""
    arguments = [
        "--dataset", run.dataset, "--model", run.model, "--output-dir", run.output_dir,
        "--config-overrides", json.dumps(run.config_overrides), "--tokenizer", run.tokenizer, "--train-split", run.train_split,
        "--max-steps", str(run.max_steps), "--batch-size", str(run.batch_size), "--learning-rate", str(run.learning_rate),
        "--warmup-steps", str(run.warmup_steps), "--end-learning-rate", str(run.end_learning_rate),
        "--logging-steps", "1", "--save-steps", str(run.save_steps), "--seed", str(run.seed),
    ]
    flags = {"--fsdp": run.fsdp, "--gradient-checkpointing": run.gradient_checkpointing, "--lora": run.lora, "--bf16": run.bf16}
    flags["--cpu"] = cpu
    arguments += [flag for flag, on in flags.items() if on]
    if run.ema_decay is not None:
        arguments += ["--ema-decay", str(run.ema_decay)]
    if run.lora:
        arguments += ["--lora-rank-vlm", str(run.lora_rank_vlm), "--lora-rank-expert", str(run.lora_rank_expert)]
    for group in run.freeze:
        arguments += ["--freeze", group]
    if run.resume_from_checkpoint:
        arguments += ["--resume-from-checkpoint", run.resume_from_checkpoint]
    return arguments


def launch(launcher: list[str], run: TrainSettings, cpu: bool = True) -> dict[int, dict]:
    """Run `pi0_torch.training` under `launcher`; the log entry of each step from the last checkpoint's trainer state."""
    command = [sys.executable, *launcher, "-m", "pi0_torch.training", *cli_arguments(run, cpu)]
    finished = subprocess.run(command, check=False, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                              text=True, timeout=HANG_S)
    assert finished.returncode == 0, finished.stderr[-3000:]
    state = json.loads((Path(run.output_dir) / f"checkpoint-{run.max_steps}" / "trainer_state.json").read_text())
    return {entry["step"]: entry for entry in state["log_history"] if "loss" in entry}


def torchrun(processes: int) -> list[str]:
    return ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(processes)]


def weights(folder: str | Path) -> dict[str, torch.Tensor]:
    return PI0ForActionGeneration.from_pretrained(folder).state_dict()


# SigLIP's attention key bias has no gradient in exact arithmetic (it adds q . b_k to every logit of a query's row,
# which softmax ignores), so its float gradient is rounding noise that AdamW normalises into steps of up to ~1e-5
# here: any change of summation order (two processes instead of one, with or without FSDP) moves it by that much.
GRADIENT_FREE = "self_attn.k_proj.bias"


def assert_same_model(got: dict[str, torch.Tensor], expected: dict[str, torch.Tensor], atol: float) -> None:
    assert got.keys() == expected.keys()
    for name, tensor in expected.items():
        if not name.endswith(GRADIENT_FREE):
            torch.testing.assert_close(got[name], tensor, rtol=0, atol=atol, msg=name)


def one_process(run: TrainSettings) -> dict[int, float]:
    """The reference: `train_policy` in this process (no launcher), one thread; the loss per step."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return losses(train_policy(run)["log_history"])
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def runs(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """π0.5 (its adaRMS modulations are units of their own) with EMA and activation checkpointing, 6 steps of global
    batch 4, checkpoints at 3 and 6: one plain process; two FSDP processes; one FSDP process resuming the
    two-process run from its checkpoint-3."""
    root = tmp_path_factory.mktemp("fsdp")
    recipe = {"model": "pi05_small", "config_overrides": {**TINY, "max_token_len": 32},  # (π0.5's prompt holds the state)
              "max_steps": 6, "save_steps": 3, "ema_decay": 0.9, "gradient_checkpointing": True}
    one = one_process(settings(dataset, root / "one", **recipe))
    two_processes = settings(dataset, root / "two", fsdp=True, **recipe)
    two = launch(torchrun(2), two_processes)
    resumed = launch(torchrun(1), replace(two_processes, output_dir=str(root / "resumed"),
                                          resume_from_checkpoint=str(root / "two" / "checkpoint-3")))
    return {"root": root, "one": one, "two": two, "resumed": resumed}


def test_two_processes_give_the_one_process_run(runs: dict) -> None:
    """The losses and gradient norms (clipping at 1.0 uses the global norm across shards) of every step, and the
    final (consolidated, EMA) model."""
    one, two = runs["one"], runs["two"]
    assert sorted(two) == list(range(1, 7))
    for step in range(1, 7):
        assert two[step]["loss"] == pytest.approx(one[step], rel=1e-4)
    reference = json.loads((runs["root"] / "one" / "checkpoint-6" / "trainer_state.json").read_text())["log_history"]
    for entry in reference:
        if "grad_norm" in entry:
            assert two[entry["step"]]["grad_norm"] == pytest.approx(entry["grad_norm"], rel=1e-4)
    assert_same_model(weights(runs["root"] / "two"), weights(runs["root"] / "one"), atol=1e-6)


def test_sharded_checkpoints_resume_and_consolidate(runs: dict, tmp_path: Path) -> None:
    """checkpoint-N holds DCP shards; a resume on one process continues the two-process run (its losses and final
    model); `pi0-torch consolidate` writes the raw or EMA weights of a checkpoint as a model folder."""
    two = runs["root"] / "two"
    for step in (3, 6):
        checkpoint = two / f"checkpoint-{step}"
        names = {p.name for p in checkpoint.iterdir()}
        assert {"model_sharded", "optimizer_sharded", "ema_sharded", "config.json", "processor_config.json",
                "trainer_state.json", "scheduler.pt", "rng_state_0.pth", "rng_state_1.pth"} <= names
        assert "model.safetensors" not in names
        assert sorted(p.name for p in (checkpoint / "model_sharded").iterdir()) == [".metadata", "__0_0.distcp", "__1_0.distcp"]
        assert checkpoint_problem(checkpoint) is None and fsdp.is_sharded_checkpoint(checkpoint)
    assert resolve_resume_checkpoint(two, "latest") == str(two / "checkpoint-6")
    assert [p.name for p in two.iterdir() if p.name.startswith(".")] == [files.MANIFEST_FILE]  # all published whole

    resumed = runs["resumed"]
    assert sorted(resumed) == list(range(1, 7))  # steps 1-3 from the checkpoint's trainer state
    for step in (4, 5, 6):
        assert resumed[step]["loss"] == pytest.approx(runs["two"][step]["loss"], rel=1e-6)
    assert_same_model(weights(runs["root"] / "resumed"), weights(two), atol=1e-6)  # EMA restored from its shards

    final = weights(two)  # the EMA of the run
    fsdp.consolidate_checkpoint(two / "checkpoint-6", tmp_path / "ema", ema=True)
    for name, tensor in weights(tmp_path / "ema").items():
        assert torch.equal(tensor, final[name]), name
    main_args = build_parser(["consolidate"]).parse_args(["consolidate", str(two / "checkpoint-6"), "--output-dir", str(tmp_path / "raw")])
    assert fsdp.run(main_args) == 0
    raw = weights(tmp_path / "raw")
    assert any(not torch.equal(raw[name], final[name]) for name in final)
    assert (tmp_path / "raw" / "processor_config.json").is_file()
    with pytest.raises(ValueError, match="is neither a sharded checkpoint .* nor a LoRA checkpoint"):
        fsdp.consolidate_checkpoint(tmp_path / "raw", tmp_path / "again")


def test_refusals(runs: dict, dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sharded, plain = runs["root"] / "two" / "checkpoint-3", runs["root"] / "one" / "checkpoint-3"
    monkeypatch.delenv("LOCAL_RANK", raising=False)
    with pytest.raises(ValueError, match="--fsdp shards over the processes of a distributed launch"):
        train_policy(settings(dataset, tmp_path / "out", fsdp=True))
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="is a sharded \\(--fsdp\\) checkpoint: resume it with --fsdp"):
        fsdp.check_settings(False, "pi0_small", str(sharded))
    with pytest.raises(ValueError, match="is a sharded checkpoint: make a model folder of it"):
        fsdp.check_settings(False, str(sharded), None)
    monkeypatch.setenv("LOCAL_RANK", "0")
    with pytest.raises(ValueError, match="was written without --fsdp"):
        fsdp.check_settings(True, "pi0_small", str(plain))
    monkeypatch.setenv("ACCELERATE_USE_FSDP", "true")
    with pytest.raises(ValueError, match="accelerate FSDP config"):
        fsdp.check_settings(True, "pi0_small", None)


def test_wrap_units() -> None:
    """Each SigLIP encoder layer, each joint decoder layer, the text embedding; π0.5 adds the two adaRMS modulations
    of every layer; LoRA keeps them (its adapters live inside the layers)."""
    for preset, modulations in (("pi0_small", 0), ("pi05_small", 2)):
        config = PI0Config.from_preset(preset, **TINY)
        model = PI0ForActionGeneration(config)
        layers = config.vision_num_layers + config.num_hidden_layers
        units = fsdp.wrap_units(model)
        assert len(units) == layers + 1 + modulations * config.num_hidden_layers
        assert len({id(unit) for unit in units}) == len(units)
        freeze(model)
        lora_units = fsdp.wrap_units(apply_lora(model, 2, 4))
        assert len(lora_units) == len(units)


def test_cli_and_examples() -> None:
    """`--fsdp` parses; the SLURM script's options are `pi0-torch train` options; the accelerate config only launches."""
    args = build_parser(["train"]).parse_args(["train", "--dataset", "d", "--model", "pi0", "--output-dir", "o", "--fsdp"])
    assert args.fsdp
    sbatch = (EXAMPLES / "slurm" / "train_fsdp.sbatch").read_text()
    assert "torchrun" in sbatch and "--rdzv-backend c10d" in sbatch
    train_options = shlex.split(sbatch.split("-m pi0_torch.training", 1)[1].replace("\\\n", " "))
    parsed = build_parser(["train"]).parse_args(["train", *train_options])
    assert parsed.fsdp and parsed.bf16 and parsed.resume_from_checkpoint == "latest"
    config = (EXAMPLES / "accelerate" / "fsdp2.yaml").read_text()
    assert "distributed_type: MULTI_GPU" in config and "mixed_precision: 'no'" in config


# ---------------------------------------------------------------------------------------------------- slow


@pytest.mark.slow  # (~40 s, over the CI budget of the FSDP tests that the module fixture's runs take)
def test_lora_with_frozen_vision_through_accelerate_launch(dataset: Path, tmp_path: Path) -> None:
    """π0, LoRA + `--freeze vision`, launched with the shipped accelerate config on 2 CPU processes: the one-process
    losses, the merged model, and a consolidated LoRA checkpoint equal to the final model."""
    recipe = {"max_steps": 4, "save_steps": 4, "lora": True, "lora_rank_vlm": 2, "lora_rank_expert": 4,
              "freeze": ["vision"], "learning_rate": 1e-2, "warmup_steps": 0}
    one = one_process(settings(dataset, tmp_path / "one", **recipe))
    launcher = ["-m", "accelerate.commands.launch", "--config_file", str(EXAMPLES / "accelerate" / "fsdp2.yaml"),
                "--num_processes", "2", "--main_process_port", "0"]
    two = launch(launcher, settings(dataset, tmp_path / "two", fsdp=True, **recipe))
    for step in range(1, 5):
        assert two[step]["loss"] == pytest.approx(one[step], rel=1e-4)
    final = weights(tmp_path / "two")
    assert_same_model(final, weights(tmp_path / "one"), atol=1e-6)
    fsdp.consolidate_checkpoint(tmp_path / "two" / "checkpoint-4", tmp_path / "merged")
    for name, tensor in weights(tmp_path / "merged").items():
        assert torch.equal(tensor, final[name]), name


@pytest.mark.slow
def test_bf16_mixed_precision(dataset: Path, tmp_path: Path) -> None:
    """π0 with `--bf16` on 2 FSDP processes (bf16 compute, float32 master weights and reduction) follows the float32
    loss curve of one process to bf16 precision; the saved model is float32."""
    recipe = {"max_steps": 4, "save_steps": 4}
    one = one_process(settings(dataset, tmp_path / "one", **recipe))
    two = launch(torchrun(2), settings(dataset, tmp_path / "two", fsdp=True, bf16=True, **recipe))
    for step in range(1, 5):
        assert two[step]["loss"] == pytest.approx(one[step], rel=1e-2)
    assert all(t.dtype == torch.float32 for t in weights(tmp_path / "two").values())


# ---------------------------------------------------------------------------------------------------- GPUs


@pytest.mark.gpu
def test_two_gpus_give_the_one_gpu_run(dataset: Path, tmp_path: Path) -> None:
    """On a machine with 2+ GPUs (`make test-gpu`): NCCL, a CUDA device mesh, bf16 compute; the loss curve of one GPU
    running the same recipe without FSDP (bf16 autocast) to bf16 precision, and the resume path on the GPU."""
    if torch.cuda.device_count() < 2:
        pytest.skip("needs 2 GPUs")
    recipe = {"max_steps": 4, "save_steps": 2, "bf16": True}
    one = launch(torchrun(1), settings(dataset, tmp_path / "one", **recipe), cpu=False)
    two_gpus = settings(dataset, tmp_path / "two", fsdp=True, **recipe)
    two = launch(torchrun(2), two_gpus, cpu=False)
    for step in range(1, 5):
        assert two[step]["loss"] == pytest.approx(one[step]["loss"], rel=1e-2)
    resumed = launch(torchrun(2), replace(two_gpus, output_dir=str(tmp_path / "resumed"),
                                          resume_from_checkpoint=str(tmp_path / "two" / "checkpoint-2")), cpu=False)
    for step in (3, 4):
        assert resumed[step]["loss"] == pytest.approx(two[step]["loss"], rel=1e-3)
