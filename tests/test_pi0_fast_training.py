"""`pi0-torch train` on π0-FAST: a run from a preset with a FAST tokenizer fitted to the episodes, its outputs, and
openpi's `gemma_2b_lora` (adapters on the Gemma, the vision tower trained in full)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pi0_torch import PI0FastConfig, PI0FastForActionGeneration, PI0FastProcessor
from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.training.model_setup import build_processor, load_config
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.lora import LoRALinear, apply_lora, merge_lora
from pi0_torch.training.trainer import train_policy

from conftest import enable_checkpointing
from test_training import dataset_root, one_thread  # noqa: F401  (fixtures: a tiny synthetic LeRobot dataset)

TINY_FAST = dict(
    image_size=28, vision_hidden_size=16, vision_intermediate_size=32, vision_num_layers=1, vision_num_heads=2,
    hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1, head_dim=8,
    vocab_size=512, action_dim=2, action_horizon=4, max_token_len=48, camera_names=["base_0_rgb", "wrist_0_rgb"],
)


def fast_settings(dataset_root: Path, output: Path, **overrides) -> TrainSettings:  # noqa: F811
    values = dict(
        dataset=str(dataset_root), model="pi0_fast_small", output_dir=str(output), config_overrides=dict(TINY_FAST),
        tokenizer="test", fast_tokenizer="fit", train_split="train", max_steps=6, batch_size=4, learning_rate=3e-3,
        warmup_steps=1, end_learning_rate=1e-4, logging_steps=1, save_steps=3, seed=0, progress=False,
    )
    values.update(overrides)
    return TrainSettings(**values)


def test_fast_run_fits_its_tokenizer_trains_and_saves(dataset_root: Path, tmp_path: Path) -> None:  # noqa: F811
    result = train_policy(fast_settings(dataset_root, tmp_path / "run"))
    losses = [entry["loss"] for entry in result["log_history"] if "loss" in entry]
    assert len(losses) == 6 and all(np.isfinite(losses)) and losses[-1] < losses[0]
    output = Path(result["output_dir"])
    for folder in (output, output / "checkpoint-3"):
        assert (folder / "fast_tokenizer" / "tokenizer.json").is_file()
    model = PI0FastForActionGeneration.from_pretrained(output).eval()
    processor = PI0FastProcessor.from_pretrained(output)
    assert processor.norm_mode == "quantile" and processor.action_tokenizer.time_horizon == 4
    frame = np.zeros((32, 32, 3), np.uint8)
    inputs = processor(images={"base_0_rgb": frame}, prompt="move to the red object", state=np.zeros(2), actions=np.zeros((4, 2)))
    assert inputs["token_loss_mask"].any() and not inputs["token_loss_mask"][0, :5].any()
    with torch.no_grad():
        loss = model(**inputs).loss  # the saved model gives openpi's loss on a processed sample
    assert torch.isfinite(loss)
    inference = {k: v for k, v in inputs.items() if k != "token_loss_mask"}
    assert processor.extract_actions(model.generate_tokens(**inference, max_new_tokens=8)).shape == (1, 4, 2)


def test_fast_lora_is_openpi_gemma_2b_lora(dataset_root: Path, tmp_path: Path) -> None:  # noqa: F811
    settings = fast_settings(dataset_root, tmp_path / "lora", lora=True)
    config = load_config(settings)
    assert isinstance(config, PI0FastConfig)
    torch.manual_seed(0)
    lora = apply_lora(PI0FastForActionGeneration(config))
    trainable = {name for name, p in lora.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n or n.startswith(("vision_tower.", "image_projection.")) for n in trainable)
    assert {n.split("lora_")[0] for n in trainable if "lora_" in n} == {
        f"layers.{i}.block.{proj}." for i in range(2) for proj in ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")
    }
    heads = config.num_attention_heads + 2 * config.num_key_value_heads
    assert lora.layers[0].block.qkv_proj.lora_a.shape == (heads, config.hidden_size, 16)  # per head, rank 16: gemma_2b_lora
    assert lora.layers[0].block.o_proj.lora_b.shape == (config.num_attention_heads, 16, config.hidden_size)
    assert lora.embed_tokens.weight.dtype == torch.float32 and lora.layers[0].block.down_proj.weight.dtype == torch.bfloat16
    merged = merge_lora(lora)
    assert isinstance(merged, PI0FastForActionGeneration) and not any(isinstance(m, LoRALinear) for m in merged.modules())
    train_policy(fast_settings(dataset_root, tmp_path / "lora", lora=True, max_steps=2))  # (the tied head reads the
    assert PI0FastForActionGeneration.from_pretrained(tmp_path / "lora").dtype == torch.float32  # rounded embedding)
    processor = build_processor(settings, config, LeRobotEpisodeDataset(str(dataset_root), config.action_horizon, progress=False))
    assert isinstance(processor, PI0FastProcessor) and processor.action_tokenizer.action_dim == 2
    with pytest.raises(ValueError, match="π0-FAST needs a FAST tokenizer"):
        train_policy(fast_settings(dataset_root, tmp_path / "none", fast_tokenizer=None, max_steps=1))


def test_gradient_checkpointing_gives_the_same_gradients() -> None:
    torch.manual_seed(0)
    model = PI0FastForActionGeneration(PI0FastConfig(**{**TINY_FAST, "camera_names": ["base_0_rgb"]})).train()
    length = 12
    batch = dict(
        pixel_values=torch.rand(2, 1, 3, 28, 28) * 2 - 1, image_masks=torch.ones(2, 1, dtype=torch.bool),
        input_ids=torch.randint(2, 512, (2, length)), attention_mask=torch.ones(2, length, dtype=torch.bool),
        token_ar_mask=torch.arange(length).expand(2, -1) >= 6, token_loss_mask=torch.arange(length).expand(2, -1) >= 6,
    )

    def gradients() -> dict[str, torch.Tensor]:
        model.zero_grad()
        model(**batch).loss.backward()
        return {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}

    plain = gradients()
    enable_checkpointing(model)
    assert all(layer.gradient_checkpointing for layer in model.layers)
    assert all(layer.gradient_checkpointing for layer in model.vision_tower.encoder.layers)
    checkpointed = gradients()
    assert plain.keys() == checkpointed.keys() and len(plain) == len(list(model.parameters()))
    for name in plain:
        torch.testing.assert_close(checkpointed[name], plain[name], rtol=1e-5, atol=1e-7, msg=name)
