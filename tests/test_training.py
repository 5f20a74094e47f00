"""Fine-tuning with the HF Trainer: outputs, openpi's schedule, resume, LoRA / freezing, gradient checkpointing."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from conftest import HANG_S, enable_checkpointing
from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.processing.normalization import NormStats, save_openpi_norm_stats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.data.synthetic_data import CAMERA_KEY, write_synthetic_dataset
from pi0_torch.utils import files
from pi0_torch.training.batches import PI0DataCollator, default_camera_map, flow_draws
from pi0_torch.training.checkpoints import resolve_resume_checkpoint
from pi0_torch.training.evaluation import evaluate_policy
from pi0_torch.training.model_setup import build_processor, load_config
from pi0_torch.training.pi0_trainer import EMA_FILE, EMACallback, openpi_learning_rate
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.fsdp import consolidate_checkpoint
from pi0_torch.training.lora import GEMMA_PREFIXES, LoRALinear, apply_lora, merge_lora, merge_lora_state
from pi0_torch.training.trainable import count_trainable, freeze, loss_free_parameter_names
from pi0_torch.training.trainer import add_arguments, settings_from_args, train_policy

# a very small π0: two cameras (the dataset has one, so the second is fed as absent), 2 layers
TINY = dict(
    image_size=28, vision_hidden_size=16, vision_intermediate_size=32, vision_num_layers=1, vision_num_heads=2,
    vlm_hidden_size=32, vlm_intermediate_size=64, expert_hidden_size=16, expert_intermediate_size=32,
    num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1, head_dim=8, vocab_size=512,
    action_dim=4, action_horizon=4, max_token_len=12, camera_names=["base_0_rgb", "left_wrist_0_rgb"],
)


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(
        tmp_path_factory.mktemp("data") / "reach", num_episodes=8, num_heldout=2, episode_length=8, image_size=32,
        storage="image", seed=1,
    )


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny matrices: threads only add overhead
    yield
    torch.set_num_threads(threads)


def settings(dataset_root: Path, output: Path, **overrides) -> TrainSettings:
    values = dict(
        dataset=str(dataset_root), model="pi0_small", output_dir=str(output), config_overrides=dict(TINY),
        tokenizer="test", train_split="train", max_steps=4, batch_size=4, learning_rate=1e-3, warmup_steps=2,
        end_learning_rate=1e-4, logging_steps=1, save_steps=1000, seed=0, progress=False,
    )
    values.update(overrides)
    return TrainSettings(**values)


def losses(log_history: list[dict]) -> dict[int, float]:
    return {entry["step"]: entry["loss"] for entry in log_history if "loss" in entry}


def tiny_model(pi05: bool = False) -> PI0ForActionGeneration:
    torch.manual_seed(0)
    return PI0ForActionGeneration(PI0Config.from_preset("pi05_small" if pi05 else "pi0_small", **TINY))


def tiny_batch(config: PI0Config, batch: int = 3) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(1)
    shape = (batch, config.action_horizon, config.action_dim)
    return dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, config.image_size, config.image_size, generator=generator) * 2 - 1,
        image_masks=torch.tensor([[True, False]] * batch),
        input_ids=torch.randint(3, 100, (batch, config.max_token_len), generator=generator),
        attention_mask=torch.arange(config.max_token_len).expand(batch, -1) < 7,
        state=torch.randn(batch, config.action_dim, generator=generator),
        actions=torch.randn(shape, generator=generator),
        noise=torch.randn(shape, generator=generator),
        time=torch.rand(batch, generator=generator) * 0.9 + 0.05,
    )


# ---------------------------------------------------------------------------------------------------- recipe


def test_openpi_schedule() -> None:
    """optax.warmup_cosine_decay_schedule(peak/(w+1), peak, w, decay, end), written out independently."""
    peak, warmup, decay, end = 2.5e-5, 1000, 30_000, 2.5e-6

    def optax_reference(step: int) -> float:
        if step < warmup:
            init = peak / (warmup + 1)
            return init + (peak - init) * step / warmup
        count = min(step - warmup, decay - warmup)
        alpha = end / peak
        return peak * ((1 - alpha) * 0.5 * (1 + np.cos(np.pi * count / (decay - warmup))) + alpha)

    for step in (0, 1, 500, 999, 1000, 1001, 15_000, 29_999, 30_000, 40_000):
        assert openpi_learning_rate(step, peak, warmup, decay, end) == pytest.approx(optax_reference(step), rel=1e-12)
    assert openpi_learning_rate(0, peak, warmup, decay, end) == pytest.approx(peak / 1001)


def test_flow_draws_are_keyed_per_sample() -> None:
    config = PI0Config.from_preset("pi0_small", **TINY)
    noise, time, delay = flow_draws(config, [(0, 0, 5, 1), (0, 0, 5, 2)])
    again, time_again, _ = flow_draws(config, [(0, 0, 5, 2)])
    assert noise.shape == (2, config.action_horizon, config.action_dim)
    torch.testing.assert_close(again[0], noise[1], rtol=0, atol=0)
    assert time_again[0] == time[1]
    _, many, _ = flow_draws(config, [(0, 0, 0, i) for i in range(4000)])
    assert 0.001 <= float(many.min()) and float(many.max()) <= 1.0
    assert float(many.mean()) == pytest.approx(0.6 * 0.999 + 0.001, abs=0.01)  # Beta(1.5, 1) has mean 0.6
    assert delay is None  # no delays unless the model trains for real-time chunking
    rtc_config = PI0Config.from_preset("pi0_small", **TINY, rtc_max_delay=3)
    _, rtc_time, delays = flow_draws(rtc_config, [(0, 0, 0, i) for i in range(4000)])
    torch.testing.assert_close(rtc_time, many, rtol=0, atol=0)  # drawn after noise and time: those are unchanged
    assert torch.bincount(delays).tolist() == pytest.approx([1000] * 4, abs=100)


# ---------------------------------------------------------------------------------------------------- a run


def test_train_writes_policy_checkpoints_processor_and_ema(dataset_root: Path, tmp_path: Path) -> None:
    result = train_policy(settings(dataset_root, tmp_path / "run", max_steps=4, save_steps=2, ema_decay=0.9))
    output = Path(result["output_dir"])
    for folder in (output, output / "checkpoint-2", output / "checkpoint-4"):
        for name in ("config.json", "model.safetensors", "processor_config.json", "norm_stats.json", "tokenizer.model"):
            assert (folder / name).is_file(), f"{folder / name} missing"
        model = PI0ForActionGeneration.from_pretrained(folder)
        processor = PI0Processor.from_pretrained(folder)
        assert processor.state_dim == processor.action_dim_robot == 2 and model.config.action_horizon == 4
    assert (output / "checkpoint-4" / EMA_FILE).is_file()
    # the final model holds the EMA weights; the checkpoint holds the raw weights (for resuming)
    final = PI0ForActionGeneration.from_pretrained(output).state_dict()
    ema = load_file(str(output / "checkpoint-4" / EMA_FILE))
    raw = load_file(str(output / "checkpoint-4" / "model.safetensors"))
    for name, average in ema.items():
        torch.testing.assert_close(final[name], average)
    assert any(not torch.equal(raw[name], ema[name]) for name in ema)
    # the logged learning rate of step k is openpi's schedule at optimizer step k - 1
    for entry in result["log_history"]:
        if "learning_rate" in entry:
            assert entry["learning_rate"] == pytest.approx(openpi_learning_rate(entry["step"] - 1, 1e-3, 2, 4, 1e-4), rel=1e-6)
    assert json.loads((output / "pi0_train_settings.json").read_text())["ema_decay"] == 0.9


def test_resume_continues_the_same_run(dataset_root: Path, tmp_path: Path) -> None:
    whole = train_policy(settings(dataset_root, tmp_path / "whole", max_steps=6, save_steps=3, ema_decay=0.9))
    resumed = train_policy(
        settings(dataset_root, tmp_path / "resumed", max_steps=6, save_steps=3, ema_decay=0.9,
                 resume_from_checkpoint=str(tmp_path / "whole" / "checkpoint-3"))
    )
    expected, got = losses(whole["log_history"]), losses(resumed["log_history"])
    assert sorted(got) == [1, 2, 3, 4, 5, 6]  # steps 1-3 come from the checkpoint's trainer state
    for step in (4, 5, 6):
        assert got[step] == pytest.approx(expected[step], rel=1e-6, abs=1e-7)
    a = PI0ForActionGeneration.from_pretrained(tmp_path / "whole").state_dict()
    b = PI0ForActionGeneration.from_pretrained(tmp_path / "resumed").state_dict()
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=1e-5, atol=1e-6)


KILL_POINTS = {  # Trainer method -> what is on disk when the process dies right after it
    "save_model": "weights",
    "_save_optimizer_and_scheduler": "weights, optimizer, scheduler",
    "_save_rng_state": "everything but the trainer state",
    "save_to_json": "everything but the processor and EMA files",
}


@pytest.fixture(scope="module")
def uninterrupted_run(dataset_root: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    return train_policy(settings(dataset_root, tmp_path_factory.mktemp("whole"), max_steps=6, save_steps=3, ema_decay=0.9))


@pytest.mark.parametrize("kill_after", sorted(KILL_POINTS))
def test_checkpoints_appear_whole_and_resume_skips_a_killed_save(
    kill_after: str, dataset_root: Path, tmp_path: Path, uninterrupted_run: dict, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 17.2: a SIGKILL inside the Trainer's save of checkpoint-6 leaves no `checkpoint-6` (only a hidden
    partial folder); `--resume-from-checkpoint latest` resumes from checkpoint-3 and continues the same run, and
    removes the dead run's partial folder."""
    output = tmp_path / "run"
    run_settings = settings(dataset_root, output, max_steps=6, save_steps=3, ema_decay=0.9)
    owner = "TrainerState" if kill_after == "save_to_json" else "Trainer"
    script = f"""
import os, signal, json
from transformers import Trainer, TrainerState
from pi0_torch.training import TrainSettings, train_policy
original = {owner}.{kill_after}
def then_die(self, *args, **kwargs):
    result = original(self, *args, **kwargs)
    if "checkpoint-6" in str(args[0] if args else kwargs):
        os.kill(os.getpid(), signal.SIGKILL)
    return result
{owner}.{kill_after} = then_die
train_policy(TrainSettings(**json.loads({json.dumps(json.dumps(vars(run_settings)))})))
"""
    finished = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=HANG_S,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert finished.returncode == -9, finished.stderr[-2000:]
    names = sorted(p.name for p in output.iterdir())
    assert "checkpoint-3" in names and "checkpoint-6" not in names, names
    assert [n for n in names if n.startswith(".")] == [".checkpoint-6.partial-save", files.MANIFEST_FILE]

    with caplog.at_level("INFO"):
        resumed = train_policy(replace(run_settings, resume_from_checkpoint="latest"))
    assert f"resuming from {output / 'checkpoint-3'}" in caplog.text
    expected, got = losses(uninterrupted_run["log_history"]), losses(resumed["log_history"])
    for step in (4, 5, 6):
        assert got[step] == pytest.approx(expected[step], rel=1e-6, abs=1e-7)
    assert sorted(p.name for p in output.iterdir() if p.name.startswith((".", "checkpoint"))) == [
        files.MANIFEST_FILE, "checkpoint-3", "checkpoint-6"]


def test_resume_falls_back_from_an_incomplete_checkpoint(dataset_root: Path, tmp_path: Path, uninterrupted_run: dict,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A `checkpoint-N` without trainer state (as the Trainer's in-place saving left it) is skipped with a log line,
    explicitly named or found as "latest"; a fresh output folder with "latest" starts from scratch."""
    whole = Path(uninterrupted_run["output_dir"])
    output = tmp_path / "run"
    output.mkdir()
    shutil.copytree(whole / "checkpoint-3", output / "checkpoint-3")
    shutil.copytree(whole / "checkpoint-6", output / "checkpoint-6")
    (output / "checkpoint-6" / "trainer_state.json").unlink()
    with caplog.at_level("INFO"):
        assert resolve_resume_checkpoint(output, str(output / "checkpoint-6")) == str(output / "checkpoint-3")
        assert resolve_resume_checkpoint(output, "latest") == str(output / "checkpoint-3")
    assert "checkpoint-6 cannot be resumed from (no trainer_state.json)" in caplog.text and "skipping" in caplog.text
    assert resolve_resume_checkpoint(tmp_path / "fresh", "latest") is None
    (output / "checkpoint-3" / "model.safetensors").unlink()
    with pytest.raises(ValueError, match="holds no readable checkpoint before it"):
        resolve_resume_checkpoint(output, str(output / "checkpoint-6"))


def test_global_batch_split_gives_the_same_losses(dataset_root: Path, tmp_path: Path) -> None:
    """Batch 4 in one piece or as 2 accumulated micro-batches of 2: the same samples, noise and times per step
    (the same keying makes 1 vs N processes agree; see the accelerate test)."""
    one = train_policy(settings(dataset_root, tmp_path / "one", max_steps=3))
    two = train_policy(settings(dataset_root, tmp_path / "two", max_steps=3, gradient_accumulation_steps=2))
    a, b = losses(one["log_history"]), losses(two["log_history"])
    for step in (1, 2, 3):
        assert b[step] == pytest.approx(a[step], rel=1e-4)


def test_bf16_gradient_checkpointing_and_rtc_delays_run(dataset_root: Path, tmp_path: Path) -> None:
    result = train_policy(settings(dataset_root, tmp_path / "bf16", max_steps=2, bf16=True, gradient_checkpointing=True,
                                   rtc_max_delay=2))
    assert all(np.isfinite(v) for v in losses(result["log_history"]).values())
    assert PI0Config.from_pretrained(result["output_dir"]).rtc_max_delay == 2  # conditioning sampling may use it


def test_rtc_max_delay_applies_when_fine_tuning_a_checkpoint(dataset_root: Path, tmp_path: Path) -> None:
    """`--rtc-max-delay` on a model folder (trained without it) trains with delays, not silently without them."""
    base = train_policy(settings(dataset_root, tmp_path / "base", max_steps=1))["output_dir"]
    from_folder = dict(model=base, config_overrides={}, tokenizer=None, max_steps=2)
    plain = losses(train_policy(settings(dataset_root, tmp_path / "plain", **from_folder))["log_history"])
    rtc = train_policy(settings(dataset_root, tmp_path / "rtc", rtc_max_delay=2, **from_folder))
    assert PI0Config.from_pretrained(rtc["output_dir"]).rtc_max_delay == 2
    assert losses(rtc["log_history"])[1] != pytest.approx(plain[1], rel=1e-6)  # the delayed tokens carry no loss


# ---------------------------------------------------------------------------------------------------- what trains


def test_loss_free_parameters_are_exactly_those_without_gradient() -> None:
    for pi05 in (False, True):
        model = tiny_model(pi05)
        model(**tiny_batch(model.config)).loss.backward()
        no_grad = sorted(name for name, p in model.named_parameters() if p.grad is None)
        assert no_grad == sorted(loss_free_parameter_names(model))
        assert no_grad  # the last layer's VLM MLP and the VLM final norm


def _expected_counts(model: PI0ForActionGeneration) -> dict[str, int]:
    def size(prefixes: tuple[str, ...]) -> int:
        return sum(p.numel() for n, p in model.named_parameters() if n.startswith(prefixes))

    layers = len(model.layers)
    return {
        "all": size(("",)),
        "vision": size(("vision_tower.", "image_projection.")),
        "vlm_side": size(("vision_tower.", "image_projection.", "embed_tokens.", "vlm_final_norm."))
        + size(tuple(f"layers.{i}.vlm." for i in range(layers))),
        "loss_free": sum(p.numel() for n, p in model.named_parameters() if n in set(loss_free_parameter_names(model))),
    }


def test_freeze_groups_train_only_what_they_should(dataset_root: Path, tmp_path: Path) -> None:
    counts = _expected_counts(tiny_model())
    assert freeze(tiny_model(), []) == counts["all"] - counts["loss_free"]
    assert freeze(tiny_model(), ["vision"]) == counts["all"] - counts["loss_free"] - counts["vision"]
    # vlm: everything of the PaliGemma side (the loss-free parameters are all on that side)
    assert freeze(tiny_model(), ["vlm"]) == counts["all"] - counts["vlm_side"]

    run = settings(dataset_root, tmp_path / "frozen", max_steps=2, freeze=["vlm"], learning_rate=1e-2, warmup_steps=0)
    result = train_policy(run)
    assert result["trainable_parameters"] == counts["all"] - counts["vlm_side"]
    config = load_config(run)
    torch.manual_seed(run.seed)  # the run initialises the preset model from its seed
    before = PI0ForActionGeneration(config).state_dict()
    after = PI0ForActionGeneration.from_pretrained(tmp_path / "frozen").state_dict()
    vlm_side = ("vision_tower.", "image_projection.", "embed_tokens.", "vlm_final_norm.") + tuple(
        f"layers.{i}.vlm." for i in range(config.num_hidden_layers)
    )
    for name in before:
        assert torch.equal(before[name], after[name]) == name.startswith(vlm_side), name


def openpi_lora_size(config: PI0Config, kind: str, target: str, rank: int) -> int:
    """Both factors of openpi's adapters on one projection: per head on q, k and v (`lora_b` per head too on the
    attention output), per half on gate and up."""
    width, mlp = ((config.vlm_hidden_size, config.vlm_intermediate_size) if kind == "vlm"
                  else (config.expert_hidden_size, config.expert_intermediate_size))
    heads, kv_heads, head_dim = config.num_attention_heads, config.num_key_value_heads, config.head_dim
    return rank * {"qkv_proj": (heads + 2 * kv_heads) * (width + head_dim), "o_proj": heads * head_dim + heads * width,
                   "gate_up_proj": 2 * (width + mlp), "down_proj": mlp + width}[target]


def test_lora_trains_openpis_adapters_vision_and_heads_only(dataset_root: Path, tmp_path: Path) -> None:
    model = tiny_model()
    freeze(model)
    config, rank_vlm, rank_expert = model.config, 2, 4
    unused = {name.rsplit(".", 1)[0] for name in loss_free_parameter_names(model)}
    expected = sum(openpi_lora_size(config, kind, target, rank_vlm if kind == "vlm" else rank_expert)
                   for layer in range(config.num_hidden_layers) for kind in ("vlm", "expert")
                   for target in ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")
                   if f"layers.{layer}.{kind}.{target}" not in unused)
    full = ("vision_tower", "image_projection", "action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in", "action_time_mlp_out")
    expected += sum(p.numel() for n, p in model.named_parameters() if n.split(".")[0] in full)
    initial = {name: value.clone() for name, value in model.state_dict().items()}
    adapted = apply_lora(model, rank_vlm, rank_expert)
    assert count_trainable(adapted) == expected
    for name, param in adapted.named_parameters():  # the Gemma frozen but its adapters, rounded to bf16 (openpi)
        gemma = name.startswith(GEMMA_PREFIXES)
        assert param.requires_grad == ((not gemma or ".lora_" in name) and name.rsplit(".", 1)[0] not in unused), name
        if gemma and ".lora_" not in name:  # (the adapters' dtype: float32)
            assert param.dtype == (torch.bfloat16 if name.endswith("_proj.weight") else torch.float32), name
            assert torch.equal(param.float(), initial[name].bfloat16().float()), name
    # with the vision tower frozen, only adapters and the action/state/time heads train
    frozen_vision = apply_lora(freeze(m := tiny_model(), ["vision"]) and m, rank_vlm, rank_expert, ["vision"])
    vision = sum(p.numel() for n, p in tiny_model().named_parameters() if n.split(".")[0] in ("vision_tower", "image_projection"))
    assert count_trainable(frozen_vision) == expected - vision
    with pytest.raises(ValueError, match="already has LoRA adapters"):
        apply_lora(frozen_vision)

    # a LoRA run: the merged final model in float32, frozen weights as initialised (rounded to bf16), the rest trained
    result = train_policy(settings(dataset_root, tmp_path / "lora", max_steps=3, lora=True, lora_rank_vlm=2,
                                   lora_rank_expert=4, learning_rate=1e-2, warmup_steps=0))
    assert result["trainable_parameters"] == expected
    merged = PI0ForActionGeneration.from_pretrained(tmp_path / "lora").state_dict()
    assert all(value.dtype == torch.float32 for value in merged.values() if value.is_floating_point())
    assert torch.equal(merged["embed_tokens.weight"], initial["embed_tokens.weight"].bfloat16().float())
    assert torch.equal(merged["layers.0.vlm.attn_norm.weight"], initial["layers.0.vlm.attn_norm.weight"].bfloat16().float())
    assert not torch.equal(merged["layers.0.expert.qkv_proj.weight"], initial["layers.0.expert.qkv_proj.weight"])
    assert not torch.equal(merged["action_out_proj.weight"], initial["action_out_proj.weight"])
    # π0.5 under bf16 autocast with gradient checkpointing: the bf16-stored projections and float32 adapters mix
    train_policy(settings(dataset_root, tmp_path / "pi05", model="pi05_small", lora=True, lora_rank_vlm=2, lora_rank_expert=4,
                          bf16=True, gradient_checkpointing=True, max_steps=2))
    assert all(p.dtype == torch.float32 for p in PI0ForActionGeneration.from_pretrained(tmp_path / "pi05").parameters())


def test_lora_resume_continues_the_same_run_and_ema_is_refused(dataset_root: Path, tmp_path: Path) -> None:
    """A LoRA checkpoint holds the adapted model, optimizer and trainer state: resuming gives the uninterrupted run,
    and `consolidate` makes the final model of its last checkpoint."""
    lora = dict(lora=True, lora_rank_vlm=2, lora_rank_expert=4, max_steps=4, save_steps=2, learning_rate=1e-2)
    whole = train_policy(settings(dataset_root, tmp_path / "whole", **lora))
    with pytest.raises(ValueError, match="LoRA run, adapters not merged: `pi0-torch consolidate"):
        PI0ForActionGeneration.from_pretrained(tmp_path / "whole" / "checkpoint-2")
    resumed = train_policy(settings(dataset_root, tmp_path / "resumed", **lora,
                                    resume_from_checkpoint=str(tmp_path / "whole" / "checkpoint-2")))
    expected, got = losses(whole["log_history"]), losses(resumed["log_history"])
    assert sorted(got) == [1, 2, 3, 4]
    for step in (3, 4):
        assert got[step] == pytest.approx(expected[step], rel=1e-6, abs=1e-7)
    a = PI0ForActionGeneration.from_pretrained(tmp_path / "whole").state_dict()
    b = PI0ForActionGeneration.from_pretrained(tmp_path / "resumed").state_dict()
    consolidate_checkpoint(tmp_path / "whole" / "checkpoint-4", tmp_path / "consolidated")
    c = PI0ForActionGeneration.from_pretrained(tmp_path / "consolidated").state_dict()
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=1e-5, atol=1e-6)
        assert torch.equal(a[name], c[name]), name
    with pytest.raises(ValueError, match="--ema-decay with --lora"):
        train_policy(settings(dataset_root, tmp_path / "ema", **lora, ema_decay=0.9))
    assert not (tmp_path / "ema").exists()
    with pytest.raises(ValueError, match="neither a sharded checkpoint .* nor a LoRA checkpoint"):
        consolidate_checkpoint(tmp_path / "whole", tmp_path / "again")


@pytest.mark.parametrize("pi05", [False, True])
def test_merged_lora_model_matches_the_adapted_model(pi05: bool) -> None:
    model = tiny_model(pi05)
    with torch.no_grad():  # (a trained base: π0.5's adaRMS gates start at zero, where the layers would add nothing)
        for param in model.parameters():
            param.add_(torch.randn_like(param) * 0.05)
    freeze(model)
    adapted = apply_lora(model, 2, 4, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        for name, param in adapted.named_parameters():
            if param.requires_grad:  # (as after training)
                param.add_(torch.randn_like(param) * 0.05)
    batch = tiny_batch(model.config)
    sampling = {name: batch[name] for name in ("pixel_values", "image_masks", "input_ids", "attention_mask", "state")}
    noise = torch.randn(batch["actions"].shape, generator=torch.Generator().manual_seed(2))
    expected = adapted(**batch).velocity
    expected_actions = adapted.generate_actions(**sampling, noise=noise, num_steps=2)
    state = merge_lora_state(adapted.state_dict())
    factors = [m.lora_b for m in adapted.modules() if isinstance(m, LoRALinear)]
    saved = [b.detach().clone() for b in factors]
    with torch.no_grad():  # the adapters take part in sampling (no layer bypasses its module)
        for b in factors:
            b.zero_()
        assert not torch.allclose(adapted.generate_actions(**sampling, noise=noise, num_steps=2), expected_actions, atol=1e-4)
        for b, value in zip(factors, saved):
            b.copy_(value)
    merged = merge_lora(adapted)
    assert type(merged) is PI0ForActionGeneration
    assert not any(isinstance(m, LoRALinear) for m in merged.modules())
    assert merged.state_dict().keys() == state.keys()
    assert all(torch.equal(value, state[name]) for name, value in merged.state_dict().items())
    torch.testing.assert_close(merged(**batch).velocity, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(merged.generate_actions(**sampling, noise=noise, num_steps=2), expected_actions, rtol=1e-5, atol=1e-5)


def test_gradient_checkpointing_gives_the_same_gradients() -> None:
    batch = tiny_batch(tiny_model().config)
    grads = []
    for checkpointing in (False, True):
        model = tiny_model().train()
        if checkpointing:
            enable_checkpointing(model)
        loss = model(**batch).loss
        loss.backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys()
    for name in grads[0]:
        torch.testing.assert_close(grads[1][name], grads[0][name], rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------------------------------- pieces


def test_ema_callback_math_and_resume(tmp_path: Path) -> None:
    model = torch.nn.Linear(2, 2)
    args, state = argparse.Namespace(output_dir=str(tmp_path)), argparse.Namespace(global_step=1, is_world_process_zero=True)
    callback = EMACallback(0.5)
    start = model.weight.detach().clone()
    callback.on_train_begin(args, state, None, model=model)
    with torch.no_grad():
        model.weight.add_(2.0)
    callback.on_step_end(args, state, None, model=model)
    torch.testing.assert_close(callback.shadow["weight"], start + 1.0)
    (tmp_path / "checkpoint-1").mkdir()
    callback.write_checkpoint(tmp_path / "checkpoint-1", state)
    resumed = EMACallback(0.5, resume_from=tmp_path / "checkpoint-1")
    resumed.on_train_begin(args, state, None, model=model)
    torch.testing.assert_close(resumed.shadow["weight"], start + 1.0)
    resumed.on_train_end(args, state, None, model=model)
    torch.testing.assert_close(model.weight.detach(), start + 1.0)
    with pytest.raises(ValueError, match="EMA decay"):
        EMACallback(1.0)


def test_collator_and_camera_map(dataset_root: Path, tmp_path: Path) -> None:
    run = settings(dataset_root, tmp_path)
    config = load_config(run)
    dataset = LeRobotEpisodeDataset(dataset_root, config.action_horizon, progress=False)
    processor = build_processor(run, config, dataset)
    camera_map = default_camera_map(dataset.camera_keys, config.camera_names)
    assert camera_map == {CAMERA_KEY: "base_0_rgb"}
    batch = PI0DataCollator(processor, camera_map)([dataset[0], dataset[9]])
    assert batch["pixel_values"].shape == (2, 2, 3, 28, 28) and batch["image_masks"].tolist() == [[True, False]] * 2
    assert batch["actions"].shape == (2, 4, 4) and batch["state"].shape == (2, 4)
    assert batch["sample_index"].tolist() == [0, 9]
    # normalized with stats of the data: z-scored, zero-padded to the model's action dim
    stats = processor.norm_stats["actions"]
    expected = (dataset[9]["actions"] - stats.mean) / (stats.std + 1e-6)
    np.testing.assert_allclose(batch["actions"][1, :, :2].numpy(), expected, rtol=1e-5, atol=1e-5)
    assert torch.all(batch["actions"][:, :, 2:] == 0)
    assert default_camera_map([CAMERA_KEY], config.camera_names, {"left_wrist_0_rgb": CAMERA_KEY}) == {CAMERA_KEY: "left_wrist_0_rgb"}
    with pytest.raises(ValueError, match="model cameras \\['wrist'\\]"):
        default_camera_map([CAMERA_KEY], config.camera_names, {"wrist": CAMERA_KEY})
    with pytest.raises(ValueError, match="the dataset has 3 cameras"):
        default_camera_map(["a", "b", "c"], config.camera_names)


def test_norm_stats_sources(dataset_root: Path, tmp_path: Path) -> None:
    config = load_config(settings(dataset_root, tmp_path))
    dataset = LeRobotEpisodeDataset(dataset_root, config.action_horizon, progress=False)
    computed = build_processor(settings(dataset_root, tmp_path), config, dataset).norm_stats
    chunks = np.concatenate([b["actions"] for b in dataset.iter_state_action_chunks()]).reshape(-1, 2)
    np.testing.assert_allclose(computed["actions"].mean, chunks.mean(0), rtol=1e-6)
    given = {"state": NormStats(mean=[0.5, 0.5], std=[2.0, 2.0]), "actions": NormStats(mean=[0.0, 0.0], std=[0.1, 0.1])}
    path = save_openpi_norm_stats(tmp_path / "stats", given)
    loaded = build_processor(settings(dataset_root, tmp_path, norm_stats=str(path)), config, dataset).norm_stats
    np.testing.assert_array_equal(loaded["state"].std, [2.0, 2.0])
    with pytest.raises(ValueError, match="no tokenizer"):
        build_processor(settings(dataset_root, tmp_path, tokenizer=None), config, dataset)
    with pytest.raises(ValueError, match="neither a checkpoint folder"):
        load_config(settings(dataset_root, tmp_path, model="pi0_tiny"))


class _AlohaEpisodes:
    """What `build_processor` reads of a dataset, for a 14-dim (ALOHA) robot: two episodes, no images."""

    def __init__(self) -> None:
        rng = np.random.default_rng(3)
        self.chunks = [{"state": rng.uniform(0.1, 0.9, (5, 14)), "actions": rng.uniform(0.1, 0.9, (5, 4, 14))} for _ in range(2)]
        self.episodes, self.tasks, self.state_dim, self.action_dim = [0, 1], {0: "fold the towel"}, 14, 14

    def iter_state_action_chunks(self):
        return iter(self.chunks)

    def check_value_spread(self) -> None:  # what build_processor asks first: no corrupt values here
        pass


def test_value_conversion_norm_stats_describe_the_converted_values(dataset_root: Path, tmp_path: Path) -> None:
    """`--value-conversion aloha`: the processor converts (as openpi's ALOHA data configs do) and its statistics are
    those of the converted state and actions, deltas included, as openpi computes them."""
    from pi0_torch.processing.robot_spaces import get_conversion

    aloha, episodes = get_conversion("aloha"), _AlohaEpisodes()
    mask = [True] * 6 + [False] + [True] * 6 + [False]
    config = PI0Config.from_preset("pi0_small")  # 32 action dims: room for ALOHA's 14
    processor = build_processor(settings(dataset_root, tmp_path, value_conversion="aloha", delta_action_mask=mask), config, episodes)
    assert processor.value_conversion == "aloha"
    states = np.concatenate([aloha.state_to_model(c["state"]) for c in episodes.chunks])
    targets = np.concatenate([
        (aloha.actions_to_model(c["actions"]) - np.where(mask, aloha.state_to_model(c["state"]), 0)[:, None]).reshape(-1, 14)
        for c in episodes.chunks
    ])
    np.testing.assert_allclose(processor.norm_stats["state"].mean, states.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(processor.norm_stats["actions"].mean, targets.mean(0), rtol=1e-5, atol=1e-6)


def test_cli_arguments_map_to_settings(dataset_root: Path, tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([
        "--dataset", str(dataset_root), "--model", "pi0_small", "--output-dir", str(tmp_path / "cli"),
        "--config-overrides", json.dumps(TINY), "--tokenizer", "test", "--max-steps", "2", "--batch-size", "2",
        "--lora", "--freeze", "vision", "--bf16", "--gradient-checkpointing", "--ema-decay",
        "--camera", f"base_0_rgb={CAMERA_KEY}", "--delta-action-mask", "1,0", "--value-conversion", "aloha",
        "--rtc-max-delay", "3",
    ])
    run = settings_from_args(args)
    assert run.lora and run.bf16 and run.gradient_checkpointing and run.freeze == ["vision"] and run.ema_decay == 0.99
    assert run.camera_map == {"base_0_rgb": CAMERA_KEY} and run.delta_action_mask == [True, False]
    assert run.value_conversion == "aloha" and run.rtc_max_delay == 3
    assert run.learning_rate == 2.5e-5 and run.warmup_steps == 1000 and run.weight_decay == 1e-10 and run.max_grad_norm == 1.0


def test_evaluate_policy_against_ground_truth(dataset_root: Path, tmp_path: Path) -> None:
    run = settings(dataset_root, tmp_path)
    config = load_config(run)
    dataset = LeRobotEpisodeDataset(dataset_root, config.action_horizon, episodes=[7], progress=False)
    processor = build_processor(run, config, dataset)
    evaluation = evaluate_policy(tiny_model(), processor, dataset, batch_size=3, progress=False)
    assert evaluation.predictions.shape == evaluation.targets.shape == (8, 4, 2)
    np.testing.assert_allclose(evaluation.baseline[0, 0], processor.norm_stats["actions"].mean, rtol=1e-6)
    again = evaluate_policy(tiny_model(), processor, dataset, batch_size=3, progress=False)
    np.testing.assert_array_equal(again.predictions, evaluation.predictions)  # seeded noise
    assert evaluation.error_ratio > 0 and "mean-action baseline MSE" in evaluation.summary()


# ---------------------------------------------------------------------------------------------------- processes


def test_accelerate_two_processes_match_one(dataset_root: Path, tmp_path: Path) -> None:
    """`accelerate launch --multi_gpu --num_processes 2 ... --cpu` (torch.distributed over gloo on CPU) gives the loss
    curve of one process with the same global batch; pi0-torch's INFO lines come once, from the first process."""
    curves = {}
    for processes in (1, 2):
        output = tmp_path / f"p{processes}"
        launcher = ["--multi_gpu", "--num_processes", "2"] if processes == 2 else ["--num_processes", "1"]
        command = [
            sys.executable, "-m", "accelerate.commands.launch", *launcher,
            "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no",
            "-m", "pi0_torch.training",
            "--dataset", str(dataset_root), "--model", "pi0_small", "--output-dir", str(output),
            "--config-overrides", json.dumps(TINY), "--tokenizer", "test", "--train-split", "train",
            "--max-steps", "6", "--batch-size", "4", "--learning-rate", "1e-3", "--warmup-steps", "2",
            "--logging-steps", "1", "--save-steps", "1000", "--seed", "0", "--cpu",
        ]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        finished = subprocess.run(command, check=True, env=env, capture_output=True, text=True, timeout=HANG_S)
        assert finished.stderr.count("trainable parameters") == 1  # logged by the first process only
        state = json.loads((output / "checkpoint-6" / "trainer_state.json").read_text())
        curves[processes] = losses(state["log_history"])
    assert sorted(curves[1]) == sorted(curves[2]) == list(range(1, 7))
    for step in range(1, 7):
        assert curves[2][step] == pytest.approx(curves[1][step], rel=1e-4)


def test_short_run_scales_the_warmup_logs_numbers_and_plots_the_loss(
    dataset_root: Path, tmp_path: Path, capfd: pytest.CaptureFixture, caplog: pytest.LogCaptureFixture
) -> None:
    """A run shorter than openpi's 1,000 warm-up steps gets a proportional warm-up (said in a log line) and reaches
    its peak learning rate; the Trainer's log lines print numbers as numbers, without transformers' "Writing model
    shards" bars; `loss.png` (training and eval loss) is written beside the final model."""
    import ast
    import logging

    run = settings(dataset_root, tmp_path / "short", max_steps=3, warmup_steps=1_000, eval_split="heldout", eval_steps=3,
                   progress=True)
    with caplog.at_level(logging.INFO, logger="pi0_torch.training.trainer"):
        result = train_policy(run)
    assert "scaled to 1 steps" in caplog.text
    rates = [entry["learning_rate"] for entry in result["log_history"] if "learning_rate" in entry]
    assert rates[1] == pytest.approx(1e-3, rel=1e-6)  # the peak, at optimizer step 1 (warm-up of 1 step)
    out, err = capfd.readouterr()
    lines = [ast.literal_eval(line) for line in out.splitlines() if line.startswith("{")]
    assert [line["loss"] for line in lines if "loss" in line] == pytest.approx(list(losses(result["log_history"]).values()), rel=1e-3)
    assert all(isinstance(value, (int, float)) for line in lines for value in line.values())
    assert "Writing model shards" not in err
    assert (tmp_path / "short" / "loss.png").read_bytes().startswith(b"\x89PNG")
