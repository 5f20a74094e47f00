"""Quantized models (`pi0_torch.conversion.quantize`, torchao through transformers' `TorchAoConfig`): a quantized
folder loads quantized and acts through every path that can take it (generate_actions, RTC guidance for weight-only
schemes, the training forward and LoRA on it, the policy), and what cannot is refused by name."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from transformers.quantizers.quantizers_utils import should_convert_module

pytest.importorskip("torchao", reason="needs torchao: pip install 'pi0-torch[quant]'")

from pi0_torch import PI0ForActionGeneration  # noqa: E402
from pi0_torch.conversion.quantize import QuantizationError, quantize_folder, quantized_widths, torchao_config  # noqa: E402
from pi0_torch.runtime.policy import PI0Policy  # noqa: E402
from pi0_torch.shipped_policy import demo_policy_dir  # noqa: E402

OBSERVATION = {"images": {"base_0_rgb": np.full((48, 48, 3), 120, np.uint8)}, "state": np.zeros(3), "prompt": "pick"}


def relative(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.abs(got - want).max() / np.abs(want).max())


@pytest.fixture(scope="module")
def int8_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return quantize_folder("demo", tmp_path_factory.mktemp("quant") / "demo_int8", "int8")


def test_a_quantized_folder_loads_quantized_and_acts_like_the_float_model(int8_folder: Path) -> None:
    config = json.loads((int8_folder / "config.json").read_text())
    assert config["quantization_config"]["quant_method"] == "torchao"
    assert (int8_folder / "tokenizer.model").is_file() and (int8_folder / "policy_settings.json").is_file()
    quantized = PI0Policy.from_pretrained(int8_folder, noise_scale=0.0)
    model = quantized.model
    assert type(model.layers[0].expert.qkv_proj.weight).__name__ == "Int8Tensor"
    assert type(model.vision_tower.encoder.layers[0].mlp.fc1.weight).__name__ == "Int8Tensor"
    for kept in (model.action_in_proj, model.action_out_proj, model.state_proj, model.image_projection, model.embed_tokens):
        assert type(kept.weight) is torch.nn.Parameter  # the action head, embeddings and projections stay as they were
    float_actions = PI0Policy.from_pretrained("demo", noise_scale=0.0).infer(OBSERVATION)["actions"]
    assert relative(quantized.infer(OBSERVATION)["actions"], float_actions) < 0.05
    assert model.last_sampling_route.steps == "torch"


def test_quantizing_while_loading_gives_what_the_folder_holds(int8_folder: Path) -> None:
    loaded = PI0ForActionGeneration.from_pretrained(demo_policy_dir(), quantization_config=torchao_config("int8")).eval()
    saved = PI0ForActionGeneration.from_pretrained(int8_folder).eval()
    inputs = loaded.sampling_program(1).example_inputs()
    assert torch.equal(loaded.generate_actions(*inputs[:5], noise=inputs[5]), saved.generate_actions(*inputs[:5], noise=inputs[5]))


def test_weight_only_models_run_rtc_guidance_and_train_with_lora(int8_folder: Path) -> None:
    from pi0_torch.training.lora import apply_lora, merge_lora

    model = PI0ForActionGeneration.from_pretrained(int8_folder).eval()
    pixels, masks, ids, valid, state, noise = model.sampling_program(1).example_inputs()
    guided = model.generate_actions(pixels, masks, ids, valid, state, noise=noise, previous_actions=torch.zeros_like(noise),
                                    inference_delay=2, execution_horizon=4)
    assert torch.isfinite(guided).all()
    adapted = apply_lora(model.train(), 4, 4)
    draws = dict(actions=torch.zeros_like(noise), noise=noise, time=torch.full(noise.shape[:1], 0.5))
    loss = adapted(pixels, masks, ids, valid, state, **draws).loss
    loss.backward()
    assert any(parameter.grad is not None for name, parameter in adapted.named_parameters() if "lora_" in name)
    merged = merge_lora(adapted)  # (the adapted projections dequantized, the update added: float weights)
    assert type(merged.layers[0].expert.qkv_proj.weight.data) is torch.Tensor
    with torch.no_grad():
        torch.testing.assert_close(merged(pixels, masks, ids, valid, state, **draws).loss, loss.detach(), rtol=1e-4,
                                   atol=1e-6)


def test_what_a_quantized_model_cannot_do_is_refused_by_name(int8_folder: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(QuantizationError, match="is quantized already"):
        quantize_folder(int8_folder, tmp_path / "again", "int8")
    with pytest.raises(ValueError, match="is quantized already"):
        PI0ForActionGeneration.from_pretrained(int8_folder, quantization_config=torchao_config("int8"))
    with pytest.raises(QuantizationError, match="fp8 .* runs on CUDA GPUs of compute capability 8.9 or more .* a CPU"):
        quantize_folder("demo", tmp_path / "fp8", "fp8")
    with pytest.raises(QuantizationError, match="--modules must name some of vlm, expert, vision"):
        torchao_config("int8", modules=("action_head",))
    from pi0_torch.deploy.export import ExportError, export_model

    with pytest.raises(ExportError, match="is quantized"):
        export_model(int8_folder, tmp_path / "exported", "onnx")
    dynamic = PI0ForActionGeneration.from_pretrained(demo_policy_dir(), quantization_config=torchao_config("int8-dynamic"))
    noise = torch.zeros(1, 16, 3)
    inputs = dynamic.sampling_program(1).example_inputs()
    with pytest.raises(ValueError, match="rtc_method='guidance' differentiates every step .* activation-quantized"):
        dynamic.generate_actions(*inputs[:5], noise=noise, previous_actions=noise, inference_delay=1, execution_horizon=4)
    with pytest.raises(ValueError, match="capture_sampling: .*pytorch/ao#4872"):
        dynamic.capture_sampling()
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *rest: None if name == "torchao" else real(name, *rest))
    with pytest.raises(ImportError, match=r"\(a quantized model\) needs torchao: pip install 'pi0-torch\[quant\]'"):
        PI0ForActionGeneration.from_pretrained(int8_folder)


def test_only_the_chosen_groups_are_quantized(tmp_path: Path) -> None:
    folder = quantize_folder("demo", tmp_path / "expert_only", "int8", modules=("expert",))
    model = PI0ForActionGeneration.from_pretrained(folder)
    assert type(model.layers[0].expert.gate_up_proj.weight).__name__ == "Int8Tensor"
    assert type(model.layers[0].vlm.gate_up_proj.weight) is torch.nn.Parameter
    assert type(model.vision_tower.encoder.layers[0].mlp.fc1.weight) is torch.nn.Parameter
    shutil.rmtree(folder)


def test_int4_groups_fit_every_quantized_width() -> None:
    # the released models' widths: Gemma 2048 / 16384, the expert 1024 / 4096, SigLIP 1152 / 4304 (= 16 * 269)
    full_size = {"layers.0.vlm.qkv_proj": 2048, "layers.0.vlm.down_proj": 16384, "layers.0.expert.down_proj": 4096,
                 "vision_tower.encoder.layers.0.mlp.fc1": 1152, "vision_tower.encoder.layers.0.mlp.fc2": 4304}
    group_size = lambda config: config.quant_type.granularity.group_size  # noqa: E731
    assert group_size(torchao_config("int4", widths=full_size)) == 16
    assert group_size(torchao_config("int4", widths={"a": 64, "b": 128})) == 64
    assert group_size(torchao_config("int4")) == 16
    with pytest.raises(QuantizationError, match=r"groups of 8 to 128 .* widths \[12\] share none: use int8"):
        torchao_config("int4", widths={"a": 12})
    # CUDA's tile-packed int4 takes groups of 128: SigLIP's fc2 (4304 wide) is kept, by its exact name
    cuda = torchao_config("int4", "cuda", widths=full_size)
    assert cuda.quant_type.group_size == 128
    assert should_convert_module("vision_tower.encoder.layers.0.mlp.fc1", cuda.modules_to_not_convert)
    assert not should_convert_module("vision_tower.encoder.layers.0.mlp.fc2", cuda.modules_to_not_convert)
    assert should_convert_module("vision_tower.encoder.layers.10.mlp.fc2", cuda.modules_to_not_convert)
    demo = quantized_widths(demo_policy_dir(), ("expert",))  # (from the config alone)
    assert demo and all(name.startswith("layers.") and ".expert." in name for name in demo)
    assert sorted(set(demo.values())) == [48, 64, 96]


def test_convert_writes_a_quantized_folder_in_one_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from conftest import FIXTURES

    from pi0_torch.cli import main as cli_main
    from pi0_torch.conversion.convert_openpi import convert_openpi_checkpoint
    from pi0_torch.models.pretrained import is_quantized

    source = FIXTURES / "pi0_small" / "ckpt" / "0"
    output = tmp_path / "pi0_small_int8"
    command = ["convert", "--from", "openpi", "--input", str(source), "--no-progress", "--output-dir", str(output)]
    assert cli_main([*command, "--quantize", "fp8"]) == 1  # refused before converting: nothing written
    assert "fp8 (float8 activations and weights) runs on CUDA GPUs" in capsys.readouterr().err
    assert not output.exists()
    assert cli_main([*command, "--quantize", "int8"]) == 0
    assert f"quantized (int8, for cpu) into {output}" in capsys.readouterr().out
    assert is_quantized(output) and sorted(path.name for path in tmp_path.iterdir()) == ["pi0_small_int8"]  # no scratch
    quantized = PI0ForActionGeneration.from_pretrained(output).eval()
    assert type(quantized.layers[0].vlm.gate_up_proj.weight).__name__ == "Int8Tensor"
    float_model = PI0ForActionGeneration.from_pretrained(
        convert_openpi_checkpoint(source, tmp_path / "float", progress=False).output_dir).eval()
    inputs = float_model.sampling_program(1).example_inputs()
    want = float_model.generate_actions(*inputs[:5], noise=inputs[5])
    got = quantized.generate_actions(*inputs[:5], noise=inputs[5])
    # quantized, and close (the fixture's random weights amplify rounding: measured 2.3e-2 of the largest action)
    assert 0 < float((got - want).abs().max() / want.abs().max()) < 5e-2
