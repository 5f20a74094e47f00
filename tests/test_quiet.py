"""Library calls print nothing unless asked: loading, saving and running a model (transformers' progress bars off)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from conftest import FIXTURES, HANG_S
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


@pytest.mark.slow
def test_a_notebook_cell_that_loads_and_runs_a_model_shows_nothing(tmp_path: Path) -> None:
    """The same in Jupyter (nbclient + ipykernel): no "Loading weights" widget or text in the cell's outputs."""
    nbclient = pytest.importorskip("nbclient")
    nbformat = pytest.importorskip("nbformat")
    pytest.importorskip("ipykernel")
    config = PI0Config.from_preset("pi0_small")
    PI0ForActionGeneration(config).save_pretrained(tmp_path / "model")
    imports = "import torch, transformers"  # no IProgress warning from tqdm: [dev] brings ipywidgets
    cell = f"""from pi0_torch import PI0ForActionGeneration
model = PI0ForActionGeneration.from_pretrained({str(tmp_path / "model")!r}).eval()
c = model.config
with torch.no_grad():
    chunk = model.generate_actions(pixel_values=torch.zeros(1, c.num_cameras, 3, 224, 224),
        image_masks=torch.ones(1, c.num_cameras, dtype=torch.bool), input_ids=torch.ones(1, 8, dtype=torch.long),
        attention_mask=torch.ones(1, 8, dtype=torch.bool), state=torch.zeros(1, c.action_dim), num_steps=2)"""
    notebook = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(source) for source in (imports, cell, "tuple(chunk.shape)")])
    nbclient.NotebookClient(notebook, timeout=HANG_S, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    assert notebook.cells[0].outputs == [] and notebook.cells[1].outputs == []
    assert notebook.cells[2].outputs[0]["data"]["text/plain"] == f"(1, {config.action_horizon}, {config.action_dim})"


def test_saved_weights_have_the_permissions_of_the_other_files(tmp_path: Path) -> None:
    """safetensors creates its files 0600; save_pretrained gives the weights the mode of the config beside them
    (the umask's, as every file the converter writes)."""
    PI0ForActionGeneration(PI0Config.from_preset("pi0_small")).save_pretrained(tmp_path / "model")
    mode = (tmp_path / "model" / "config.json").stat().st_mode & 0o777
    assert (tmp_path / "model" / "model.safetensors").stat().st_mode & 0o777 == mode == 0o666 & ~_umask()
    assert sorted(p.name for p in (tmp_path / "model").iterdir()) == ["config.json", "model.safetensors"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
