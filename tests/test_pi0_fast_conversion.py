"""`pi0-torch convert --from openpi` on openpi's π0-FAST checkpoint: model and processor load from the output and
reproduce openpi's outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from transformers import AutoModel, AutoProcessor

from pi0_torch import PI0FastForActionGeneration, PI0FastProcessor
from pi0_torch.cli import main as cli_main
from pi0_torch.conversion.convert import ConversionError, convert_openpi_checkpoint
from pi0_torch.models.modeling_pi0_fast import token_log_probs

from conftest import FIXTURES, relative_error
from test_pi0_fast import FAST_DIR, FastReference


@pytest.fixture(scope="module")
def fast_reference() -> FastReference:
    return FastReference()


def test_convert_command_gives_model_and_processor(tmp_path: Path, fast_reference: FastReference, capsys: pytest.CaptureFixture) -> None:
    output = tmp_path / "pi0_fast"
    code = cli_main([
        "convert", "--from", "openpi", "--input", str(FAST_DIR / "ckpt" / "0"), "--output-dir", str(output),
        "--tokenizer", str(FAST_DIR / "tokenizer.model"), "--fast-tokenizer", str(FAST_DIR / "fast_tokenizer"),
        "--max-token-len", "96", "--no-progress",
    ])
    printed = capsys.readouterr().out
    assert code == 0 and "π0-FAST" in printed
    assert "processor: written (PI0FastProcessor.from_pretrained loads it)" in printed  # (said PI0Processor: issue 63)
    assert sorted(p.name for p in output.iterdir()) == [
        ".pi0-torch-manifest.json", "config.json", "fast_tokenizer", "model.safetensors", "norm_stats.json",
        "processor_config.json", "tokenizer.model",
    ]
    model = AutoModel.from_pretrained(output).eval()
    assert isinstance(model, PI0FastForActionGeneration)
    # action chunk shape from the FAST tokenizer's settings, prompt length from the command line
    assert (model.config.action_dim, model.config.action_horizon, model.config.max_token_len) == (8, 10, 96)
    processor = AutoProcessor.from_pretrained(output)
    assert isinstance(processor, PI0FastProcessor) and processor.norm_mode == "quantile"

    train = fast_reference.inputs("train")
    loss_mask = torch.from_numpy(fast_reference["inputs/train/loss_mask"])
    with torch.no_grad():
        output_fp32 = model(**train, token_loss_mask=loss_mask)
    assert relative_error(output_fp32.loss, fast_reference["fp32/loss"].mean()) < 1e-5
    target_logp = token_log_probs(output_fp32.logits, train["input_ids"][:, 1:])
    assert relative_error(target_logp, fast_reference["fp32/target_logp"]) < 1e-5

    # raw observation -> processor -> tokens -> robot actions (a random model: whatever chunk it decodes, decoded)
    frame = np.zeros((96, 128, 3), np.uint8)
    inputs = processor(images={"base_0_rgb": frame, "base_1_rgb": frame, "wrist_0_rgb": frame}, prompt="pick up the cube", state=np.zeros(8))
    tokens = model.generate_tokens(**inputs, max_new_tokens=4)
    assert tokens.shape == (1, 4)
    assert processor.decode_actions(tokens).shape == (1, 10, 8)
    chunk = model.generate_actions(**inputs, processor=processor, max_new_tokens=4)
    assert chunk.shape == (1, 10, 8) and chunk.dtype == torch.float32


def test_bfloat16_conversion(tmp_path: Path, fast_reference: FastReference) -> None:
    result = convert_openpi_checkpoint(FAST_DIR / "ckpt" / "0", tmp_path / "bf16", dtype="bfloat16", progress=False, max_token_len=96,
                                       action_dim=8, action_horizon=10)
    assert result.norm_stats is not None and not (result.output_dir / "fast_tokenizer").exists()  # no tokenizer given
    model = PI0FastForActionGeneration.from_pretrained(result.output_dir).eval()
    assert model.dtype == torch.bfloat16
    with torch.no_grad():
        loss = model(**fast_reference.inputs("train"), token_loss_mask=torch.from_numpy(fast_reference["inputs/train/loss_mask"])).loss
    assert relative_error(loss, fast_reference["bf16_infer/loss"].mean()) < 1e-2


def test_fast_tokenizer_for_a_pi0_checkpoint_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConversionError, match="--fast-tokenizer is for π0-FAST"):
        convert_openpi_checkpoint(FIXTURES / "pi0_small" / "ckpt" / "0", tmp_path / "out", fast_tokenizer=FAST_DIR / "fast_tokenizer", progress=False)
    with pytest.raises(ConversionError, match="unusable FAST tokenizer"):
        convert_openpi_checkpoint(FAST_DIR / "ckpt" / "0", tmp_path / "out", fast_tokenizer=tmp_path, progress=False)
    assert not (tmp_path / "out").exists()


def test_the_summary_names_what_the_processor_lacks_and_tokenizers_by_name(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Issue 38.18: with norm stats and --tokenizer found, the summary said the processor needed them (it lacked
    --fast-tokenizer); `--tokenizer test` with --fast-tokenizer was refused naming an object repr."""
    common = ["convert", "--from", "openpi", "--input", str(FAST_DIR / "ckpt" / "0"), "--no-progress"]
    assert cli_main([*common, "--output-dir", str(tmp_path / "a"), "--tokenizer", str(FAST_DIR / "tokenizer.model")]) == 0
    assert "processor: none: it needs --fast-tokenizer\n" in capsys.readouterr().out
    assert cli_main([*common, "--output-dir", str(tmp_path / "b"), "--tokenizer", "test", "--fast-tokenizer",
                     str(FAST_DIR / "fast_tokenizer")]) == 1
    error = capsys.readouterr().err
    assert error.startswith("error: cannot build the processor with --tokenizer test: FAST ids") and " object at 0x" not in error


def test_an_openpi_gemma_2b_lora_tree_loads_merged(fast_reference: FastReference) -> None:
    """π0-FAST's LoRA fine-tunes (`gemma_2b_lora` on its Gemma) load with the adapters merged, by the map π0's LoRA
    fixture checks against openpi (tests/test_openpi_training.py): zero `lora_b` leaves the weights as they are,
    others move exactly the Gemma projections."""
    from pi0_torch.conversion.openpi_paligemma import gemma_lora_openpi_shapes, openpi_lora_ranks
    from pi0_torch.conversion.openpi_weights import load_openpi_params

    config = fast_reference.config
    ranks = {(0, "attn"): 4, (0, "ffn"): 4}
    shapes = gemma_lora_openpi_shapes(config, 0, config.hidden_size, config.intermediate_size, ranks)
    generator = np.random.default_rng(0)
    adapters = {path: generator.normal(0, 0.1, shape).astype(np.float32) for path, shape in shapes.items()}
    assert openpi_lora_ranks({path: array.shape for path, array in adapters.items()}) == ranks

    plain = PI0FastForActionGeneration(config)
    load_openpi_params(plain, fast_reference.params)
    untouched = PI0FastForActionGeneration(config)
    load_openpi_params(untouched, {**fast_reference.params, **{
        path: np.zeros_like(array) if path.endswith("lora_b") else array for path, array in adapters.items()}})
    merged = PI0FastForActionGeneration(config)
    load_openpi_params(merged, {**fast_reference.params, **adapters})
    projections = tuple(f"{name}.weight" for name in ("qkv_proj", "o_proj", "gate_up_proj", "down_proj"))
    untouched, merged = untouched.state_dict(), merged.state_dict()
    for name, tensor in plain.state_dict().items():
        assert torch.equal(untouched[name], tensor), name
        assert torch.equal(merged[name], tensor) != name.endswith(projections), name
