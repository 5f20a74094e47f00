"""Library calls print nothing unless asked: loading, saving and running a model (transformers' progress bars off)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import FIXTURES
from transformers.utils import logging as hf_logging

from pi0_torch import PI0Config, PI0ForActionGeneration, PI0Processor
from pi0_torch.processing.tokenization import build_test_tokenizer


def test_load_save_and_generate_print_nothing(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    """What a notebook cell does (save, load model and processor, process an observation, generate a chunk) writes
    nothing to stdout or stderr; `verbose=True` brings transformers' bar back; the process-wide setting is kept."""
    config = PI0Config.from_preset("pi0_small")
    torch.manual_seed(0)
    PI0ForActionGeneration(config).save_pretrained(tmp_path / "model")
    norm_stats = FIXTURES / "pi0_small" / "ckpt" / "0" / "assets" / "reference" / "norm_stats.json"
    PI0Processor.from_config(config, tokenizer=build_test_tokenizer(), norm_stats=norm_stats).save_pretrained(tmp_path / "model")
    capfd.readouterr()
    bars_before = hf_logging.is_progress_bar_enabled()

    model = PI0ForActionGeneration.from_pretrained(tmp_path / "model").eval()
    processor = PI0Processor.from_pretrained(tmp_path / "model")
    inputs = processor(images={name: torch.zeros(32, 48, 3, dtype=torch.uint8) for name in config.camera_names},
                       prompt="pick up the fork", state=torch.zeros(processor.state_dim))
    with torch.no_grad():
        chunk = model.generate_actions(**inputs, num_steps=2)
    model.save_pretrained(tmp_path / "again")
    assert chunk.shape == (1, config.action_horizon, config.action_dim) and torch.isfinite(chunk).all()
    assert capfd.readouterr() == ("", "")

    PI0ForActionGeneration.from_pretrained(tmp_path / "model", verbose=True)
    assert "Loading weights" in capfd.readouterr().err
    assert hf_logging.is_progress_bar_enabled() == bars_before
