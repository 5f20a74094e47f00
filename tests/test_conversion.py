"""Checkpoint conversion: openpi fixtures (JAX outputs), transformers' PI0, LeRobot layout, bad inputs."""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import re
import shutil
from pathlib import Path

import ml_dtypes
import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.conversion import convert as conversion, convert_hf, convert_openpi, orbax_reader
from pi0_torch.conversion.convert import (
    ConversionError,
    convert_hf_checkpoint,
    convert_openpi_checkpoint,
    export_to_transformers,
)
from pi0_torch.conversion.convert_hf import transformers_pi0_inputs
from pi0_torch.conversion.output_folder import planned_shapes
from pi0_torch.processing.normalization import load_openpi_norm_stats
from pi0_torch.conversion.orbax_reader import write_orbax_checkpoint
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.utils import files

from conftest import FIXTURES, HANG_S, VARIANTS, OpenpiReference, relative_error
from test_orbax_reader import writable_copy

FLOAT32_TOLERANCE = 1e-4
BF16_TOLERANCE = 3e-2
ROOT = Path(__file__).resolve().parents[1]


def step_dir(variant: str) -> Path:
    return FIXTURES / variant / "ckpt" / "0"


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Path]:
    """Both fixtures converted to float32 and bfloat16."""
    root = tmp_path_factory.mktemp("converted")
    return {
        (variant, dtype): convert_openpi_checkpoint(step_dir(variant), root / f"{variant}-{dtype}", dtype=dtype, progress=False).output_dir
        for variant in VARIANTS
        for dtype in ("float32", "bfloat16")
    }


def state_dict_of(folder: Path) -> dict[str, torch.Tensor]:
    tensors = {}
    for path in sorted(folder.glob("*.safetensors")):
        with safe_open(path, framework="pt") as handle:
            tensors.update({key: handle.get_tensor(key) for key in handle.keys()})
    return tensors


@torch.no_grad()
def openpi_loss_and_actions(model: PI0ForActionGeneration, ref: OpenpiReference) -> tuple[torch.Tensor, torch.Tensor]:
    """openpi's compute_loss ([B, horizon], mean over the action dim) and sample_actions on the fixture inputs."""
    inputs = ref.model_inputs()
    noise, time, actions = ref.tensor("inputs/loss_noise"), ref.tensor("inputs/loss_time"), ref.tensor("inputs/actions")
    velocity = model(**inputs, actions=actions, noise=noise, time=time).velocity
    loss = ((velocity.float() - (noise - actions)) ** 2).mean(dim=-1)
    sampled = model.generate_actions(**inputs, noise=ref.tensor("inputs/sample_noise"), num_steps=int(ref["inputs/num_steps"]))
    return loss, sampled


# -- openpi ----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", VARIANTS)
def test_float32_conversion_reproduces_openpi(variant: str, converted: dict, references: dict) -> None:
    ref = references[variant]
    model = PI0ForActionGeneration.from_pretrained(converted[variant, "float32"]).eval()
    assert model.dtype == torch.float32 and model.config.pi05 == (variant == "pi05_small")
    direct = ref.model().state_dict()  # the same leaves loaded in memory by load_openpi_params
    assert all(torch.equal(tensor, direct[name]) for name, tensor in model.state_dict().items())
    loss, actions = openpi_loss_and_actions(model, ref)
    assert relative_error(loss, ref["fp32/loss"]) <= FLOAT32_TOLERANCE
    assert relative_error(actions, ref["fp32/actions"]) <= FLOAT32_TOLERANCE


@pytest.mark.parametrize("variant", VARIANTS)
def test_bfloat16_conversion_reproduces_openpi_bf16_inference(variant: str, converted: dict, references: dict) -> None:
    ref = references[variant]
    model = PI0ForActionGeneration.from_pretrained(converted[variant, "bfloat16"]).eval()
    assert model.dtype == torch.bfloat16
    float32 = state_dict_of(converted[variant, "float32"])
    assert all(torch.equal(tensor, float32[name].to(torch.bfloat16)) for name, tensor in model.state_dict().items())
    inputs = ref.model_inputs()
    with torch.no_grad():
        actions = model.generate_actions(**inputs, noise=ref.tensor("inputs/sample_noise"))
    assert relative_error(actions, ref["bf16_infer/actions"]) <= BF16_TOLERANCE


def test_output_folder(converted: dict) -> None:
    folder = converted["pi0_small", "bfloat16"]
    assert sorted(p.name for p in folder.iterdir()) == [files.MANIFEST_FILE, "config.json", "model.safetensors",
                                                         "norm_stats.json"]
    config = json.loads((folder / "config.json").read_text())
    assert (config["model_type"], config["architectures"], config["dtype"]) == ("pi0_torch", ["PI0ForActionGeneration"], "bfloat16")
    with safe_open(folder / "model.safetensors", framework="pt") as handle:
        assert handle.metadata() == {"format": "pt"}
        assert list(handle.keys()) == sorted(planned_shapes(PI0ForActionGeneration.config_class(**config)))
    ours, source = load_openpi_norm_stats(folder), load_openpi_norm_stats(step_dir("pi0_small"))
    assert sorted(ours) == sorted(source)
    assert all(np.array_equal(ours[k].mean, source[k].mean) and np.array_equal(ours[k].q99, source[k].q99) for k in ours)
    assert sorted(p.name for p in folder.parent.iterdir()) == sorted(f"{v}-{d}" for v in VARIANTS for d in ("float32", "bfloat16"))


def test_processor_loads_from_converted_folder(tmp_path: Path) -> None:
    tokenizer = build_test_tokenizer(save_to=tmp_path / "paligemma_tokenizer.model")
    out = convert_openpi_checkpoint(step_dir("pi05_small"), tmp_path / "out", tokenizer=tmp_path / "paligemma_tokenizer.model", progress=False).output_dir
    processor = PI0Processor.from_pretrained(out)
    assert processor.pi05 and processor.max_token_len == 200 and processor.norm_mode == "quantile"
    source = load_openpi_norm_stats(step_dir("pi05_small"))
    assert np.array_equal(processor.norm_stats["actions"].q01, source["actions"].q01)
    assert processor.tokenizer.vocab_size == tokenizer.vocab_size


def test_processor_settings_from_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`--delta-action-mask` / `--value-conversion` go into the saved processor; a setting that cannot apply to the
    checkpoint's norm stats fails before any weight is written."""
    build_test_tokenizer(save_to=tmp_path / "tok.model")
    common = ["--from", "openpi", "--input", str(step_dir("pi0_small")), "--tokenizer", str(tmp_path / "tok.model")]
    assert run_cli(*common, "--output-dir", str(tmp_path / "delta"), "--delta-action-mask", "1,1,1,0", "--no-progress") == 0
    mask = PI0Processor.from_pretrained(tmp_path / "delta").delta_action_mask  # (padded to the robot's 8 action dims)
    assert mask == [True, True, True, False] + [False] * (len(mask) - 4) and len(mask) == 8
    assert run_cli(*common, "--output-dir", str(tmp_path / "aloha"), "--value-conversion", "aloha") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: cannot build the processor") and "applies to a state and actions of 14 values" in err[-1]
    assert not (tmp_path / "aloha").exists()
    assert run_cli("--from", "openpi", "--input", str(step_dir("pi0_small")), "--output-dir", str(tmp_path / "x"),
                   "--value-conversion", "aloha") == 1
    assert "processor settings ['value_conversion'] need --tokenizer\n" in capsys.readouterr().err  # (the norm stats are there)


def test_sharded_output(converted: dict, tmp_path: Path) -> None:
    out = convert_openpi_checkpoint(step_dir("pi0_small"), tmp_path / "sharded", max_shard_bytes="300kB", progress=False).output_dir
    shards = sorted(p.name for p in out.glob("*.safetensors"))
    assert len(shards) > 2 and shards == [f"model-{i:05d}-of-{len(shards):05d}.safetensors" for i in range(1, len(shards) + 1)]
    assert all(p.stat().st_size < 300_000 + 100_000 for p in out.glob("*.safetensors"))  # one tensor may exceed
    index = json.loads((out / "model.safetensors.index.json").read_text())
    single = state_dict_of(converted["pi0_small", "float32"])
    assert set(index["weight_map"]) == set(single) and set(index["weight_map"].values()) == set(shards)
    assert index["metadata"]["total_size"] == sum(t.numel() * 4 for t in single.values())
    model = PI0ForActionGeneration.from_pretrained(out)
    assert all(torch.equal(tensor, single[name]) for name, tensor in model.state_dict().items())


def test_released_layout_bfloat16_without_value_suffix(tmp_path: Path) -> None:
    """bfloat16 leaves, no "/value", one chunk per layer (a sharded save) -> the bf16-rounded weights, exactly."""
    arrays = {k: v.astype(ml_dtypes.bfloat16) for k, v in dict(np.load(FIXTURES / "pi05_small" / "params_flat.npz")).items()}
    write_orbax_checkpoint(tmp_path / "ckpt" / "params", arrays, value_suffix=False, chunk_bytes=20_000)
    out = convert_openpi_checkpoint(tmp_path / "ckpt", tmp_path / "out", progress=False).output_dir
    assert not (out / "norm_stats.json").exists()  # this checkpoint has no assets
    rounded = OpenpiReference("pi05_small")
    rounded.params = {k: v.astype(np.float32) for k, v in arrays.items()}
    expected = rounded.model().state_dict()
    assert all(torch.equal(tensor, expected[name]) for name, tensor in state_dict_of(out).items())


@pytest.mark.parametrize("streaming", [True, False], ids=["zstd-stream", "tensorstore"])
@pytest.mark.parametrize("chunk_bytes", [None, 70_000], ids=["one-chunk", "two-layer-chunks"])
def test_multi_layer_chunks_are_decoded_once_and_spilled(
    chunk_bytes: int | None, streaming: bool, converted: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    monkeypatch.setattr(convert_openpi, "_SMALL_LEAF_BYTES", 0)  # every multi-layer chunk counts as big: spill to scratch
    if streaming and orbax_reader.streaming_reason() is not None:
        pytest.skip(f"{orbax_reader.streaming_reason()}: chunks are decoded by tensorstore")
    if not streaming:
        monkeypatch.setattr(orbax_reader, "zstandard", None)
    write_orbax_checkpoint(tmp_path / "ckpt" / "params", dict(np.load(FIXTURES / "pi0_small" / "params_flat.npz")), chunk_bytes=chunk_bytes)
    decoded: list[tuple[str, int, int]] = []
    original = orbax_reader.OrbaxCheckpoint.iter_rows
    monkeypatch.setattr(orbax_reader.OrbaxCheckpoint, "iter_rows", lambda self, path, start=0, stop=None: decoded.append((path, start, stop)) or original(self, path, start, stop))
    with caplog.at_level(logging.WARNING, logger="pi0_torch.conversion.convert_openpi"):
        out = convert_openpi_checkpoint(tmp_path / "ckpt", tmp_path / "out", progress=False).output_dir
    # (decoding chunks whole costs memory: the conversion says so, and why)
    assert ("zstandard is not installed: each stored chunk is decoded whole" in caplog.text) != streaming, caplog.text
    checkpoint = orbax_reader.OrbaxCheckpoint(tmp_path / "ckpt")
    stacked = {path for path, _, _ in decoded}
    multi_layer_chunks = {p for p, info in checkpoint.leaves.items() if ("encoderblock" in p or "llm/layers" in p) and info.chunks[0] > 1}
    assert stacked == multi_layer_chunks  # (a leaf chunked per layer is sliced directly)
    for path in stacked:  # every chunk decoded once, not once per layer
        layers, rows = checkpoint.info(path).shape[0], checkpoint.info(path).chunks[0]
        assert sorted((start, stop) for p, start, stop in decoded if p == path) == [
            (start, min(start + rows, layers)) for start in range(0, layers, rows)
        ], path
    expected = state_dict_of(converted["pi0_small", "float32"])
    assert all(torch.equal(tensor, expected[name]) for name, tensor in state_dict_of(out).items())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt", "out"] and not (out / ".scratch").exists()


def test_asset_selection(tmp_path: Path) -> None:
    step = writable_copy(step_dir("pi0_small"), tmp_path / "0")
    shutil.copytree(step / "assets" / "reference", step / "assets" / "other_robot")
    with pytest.raises(ConversionError, match="several asset ids; pick one with --asset-id: other_robot, reference"):
        convert_openpi_checkpoint(step, tmp_path / "out", progress=False)
    with pytest.raises(ConversionError, match="no norm stats for asset id 'nope'.*choices: other_robot, reference"):
        convert_openpi_checkpoint(step, tmp_path / "out", asset_id="nope", progress=False)
    result = convert_openpi_checkpoint(step, tmp_path / "out", asset_id="other_robot", progress=False)
    assert result.norm_stats == step / "assets" / "other_robot" / "norm_stats.json"


# -- command line and bad inputs -------------------------------------------------------------------------------------


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    conversion.add_arguments(parser)
    return conversion.run(parser.parse_args(["--no-progress", *argv]))


def damaged_checkpoint(tmp_path: Path, damage: str) -> Path:
    arrays = dict(np.load(FIXTURES / "pi0_small" / "params_flat.npz"))
    if damage == "missing leaf":
        del arrays["PaliGemma/llm/layers/mlp_1/linear"]
    elif damage == "wrong shape":
        arrays["action_out_proj/kernel"] = arrays["action_out_proj/kernel"][:, :30]
    elif damage == "unexpected leaf":
        arrays["PaliGemma/llm/extra_head/kernel"] = np.zeros((4, 4), np.float32)
    elif damage == "foreign tree":
        arrays = {"encoder/dense/kernel": np.zeros((4, 4), np.float32)}
    if damage == "truncated data":
        step = writable_copy(step_dir("pi0_small"), tmp_path / "ckpt")
        data = max((step / "params").rglob("d/*"), key=lambda p: p.stat().st_size)
        with open(data, "r+b") as handle:
            handle.truncate(data.stat().st_size // 2)
        return step
    if damage == "not a checkpoint":
        (tmp_path / "ckpt").mkdir()
        (tmp_path / "ckpt" / "notes.txt").write_text("hello")
        return tmp_path / "ckpt"
    write_orbax_checkpoint(tmp_path / "ckpt" / "params", arrays)
    return tmp_path / "ckpt"


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("missing leaf", r"missing: PaliGemma/llm/layers/mlp_1/linear"),
        ("wrong shape", r"mis-shaped: action_out_proj/kernel \(48, 30\) \(expected \(48, 32\)\)"),
        ("unexpected leaf", r"unexpected: PaliGemma/llm/extra_head/kernel"),
        ("foreign tree", r"not a pi0/pi0.5 parameter tree"),
        ("truncated data", r"cannot read leaf .* OUT_OF_RANGE"),
        ("not a checkpoint", r"is not an orbax checkpoint: no _METADATA"),
    ],
)
def test_bad_input_gives_one_error_line_and_no_output(damage: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    source = damaged_checkpoint(tmp_path, damage)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert run_cli("--from", "openpi", "--input", str(source), "--output-dir", str(tmp_path / "out" / "model")) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert re.search(message, err[0]), err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no partial folder, no created parent


def test_existing_output_and_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A non-empty output folder is replaced only with --overwrite, and only when pi0-torch wrote all of it (issue
    28.1: an `--overwrite` once deleted whatever the folder held)."""
    out = tmp_path / "out"
    convert = ("--from", "openpi", "--input", str(step_dir("pi0_small")), "--output-dir", str(out))
    assert run_cli(*convert) == 0
    capsys.readouterr()
    assert run_cli(*convert) == 1
    assert "exists and is not empty (pass --overwrite" in capsys.readouterr().err
    assert run_cli(*convert, "--overwrite", "--dtype", "bfloat16") == 0  # an earlier conversion: replaced
    assert "π0, " in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == [files.MANIFEST_FILE, "config.json", "model.safetensors", "norm_stats.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    (out / "keep.txt").write_text("mine")  # a file of the user's: never replaced, even with --overwrite
    assert run_cli(*convert, "--overwrite") == 1
    err = capsys.readouterr().err
    assert "holds files that pi0-torch did not write (keep.txt)" in err and err.count("\n") == 1, err
    assert (out / "keep.txt").read_text() == "mine" and (out / "model.safetensors").is_file()


def tree_digest(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_size for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("where", ["same", "same via symlink", "inside the input", "containing the input", "params of the input"])
def test_output_overlapping_the_input_is_refused_even_with_overwrite(where: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Issue 17.1: `--output-dir` equal to, inside or around the input once deleted the checkpoint being converted."""
    source = tmp_path / "run" / "0"
    shutil.copytree(step_dir("pi0_small"), source)
    before = tree_digest(tmp_path / "run")
    (tmp_path / "link").symlink_to(source)
    given_input, output = {
        "same": (source, source),
        "same via symlink": (source, tmp_path / "link"),
        "inside the input": (source, source / "converted"),
        "containing the input": (source, tmp_path / "run"),
        "params of the input": (source / "params", source / "assets"),  # the assets beside params/ are input too
    }[where]
    assert run_cli("--from", "openpi", "--input", str(given_input), "--output-dir", str(output), "--overwrite") == 1
    err = capsys.readouterr().err.strip()
    # (the assets folder holds the input's files: refused for that before its overlap is even looked at)
    assert err.startswith("error: output folder") and ("the input" in err or "did not write" in err) and "\n" not in err, err
    assert tree_digest(tmp_path / "run") == before  # nothing deleted, nothing added


def test_partial_folder_of_a_killed_conversion_is_removed_by_the_next_run(tmp_path: Path) -> None:
    """Issue 17.3: a SIGKILLed conversion leaves `.NAME.partial-*`; the next conversion beside it removes it, while a
    live run's partial folder and foreign folders stay."""
    import signal
    import subprocess
    import sys
    import textwrap

    # a conversion killed while it writes its weights
    script = textwrap.dedent(f"""
        import os, signal
        from pi0_torch.conversion import convert, output_folder
        original = output_folder.ShardedSafetensorsWriter.write
        def write_then_die(self, name, tensor):
            original(self, name, tensor)
            os.kill(os.getpid(), signal.SIGKILL)
        output_folder.ShardedSafetensorsWriter.write = write_then_die
        convert.convert_openpi_checkpoint({str(step_dir("pi0_small"))!r}, {str(tmp_path / "killed")!r}, progress=False)
    """)
    finished = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, timeout=HANG_S)
    assert finished.returncode == -signal.SIGKILL, finished.stderr
    [stale] = [p for p in tmp_path.iterdir()]
    assert stale.name.startswith(".killed.partial-") and (stale / "model.safetensors").is_file()

    live = tmp_path / ".other.partial-live"  # a run that is still writing: this process owns it
    live.mkdir()
    files.claim(live)
    foreign = tmp_path / ".mine.partial-notes"  # no owner file: not ours to delete
    foreign.mkdir()
    assert run_cli("--from", "openpi", "--input", str(step_dir("pi0_small")), "--output-dir", str(tmp_path / "next")) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, foreign.name, "next"])


def test_plain_script(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    spec = importlib.util.spec_from_file_location("convert_openpi_checkpoint", ROOT / "conversion" / "convert_openpi_checkpoint.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    argv = ["--checkpoint-dir", str(step_dir("pi05_small") / "params"), "--output-dir", str(tmp_path / "out"), "--dtype", "bfloat16", "--no-progress"]
    assert script.main(argv) == 0
    assert PI0ForActionGeneration.from_pretrained(tmp_path / "out").dtype == torch.bfloat16
    capsys.readouterr()
    assert script.main(argv) == 1 and capsys.readouterr().err.startswith("error: output folder")


# -- transformers PI0ForConditionalGeneration and LeRobot ------------------------------------------------------------


def tiny_transformers_pi0():
    """A transformers PI0ForConditionalGeneration at the pi0_small fixture's size, with random weights everywhere."""
    from transformers import PI0Config, PI0ForConditionalGeneration

    gemma = dict(num_hidden_layers=3, num_attention_heads=4, num_key_value_heads=1, head_dim=32)
    config = PI0Config(
        vlm_config=dict(
            text_config=dict(model_type="gemma", hidden_size=64, intermediate_size=128, vocab_size=1024, **gemma),
            vision_config=dict(model_type="siglip_vision_model", hidden_size=40, intermediate_size=80, num_hidden_layers=2,
                               num_attention_heads=4, patch_size=14, image_size=224, vision_use_head=False),
            projection_dim=64,
            image_token_id=1024,
        ),
        dit_config=dict(hidden_size=48, intermediate_size=96, **gemma),
    )
    torch.manual_seed(0)
    model = PI0ForConditionalGeneration(config).eval()
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            parameter.normal_(0.0, 0.1 if "norm" in name else 0.05)
    return model


def paired_inputs(batch: int = 2, cameras: int = 3, text: int = 48, vocab_size: int = 1024) -> tuple[dict, dict]:
    """The same observation for our model and for transformers' PI0; the middle camera of sample 1 is missing."""
    generator = torch.Generator().manual_seed(1)
    pixel_values = torch.rand(batch, cameras, 3, 224, 224, generator=generator) * 2 - 1
    image_masks = torch.ones(batch, cameras, dtype=torch.bool)
    image_masks[1, 1] = False
    input_ids = torch.randint(3, vocab_size, (batch, text), generator=generator)
    input_ids[:, 0] = 2
    attention_mask = torch.arange(text)[None, :] < torch.tensor([[20], [31]])
    ours = dict(pixel_values=pixel_values, image_masks=image_masks, input_ids=input_ids, attention_mask=attention_mask,
                state=torch.randn(batch, 32, generator=generator))
    return ours, transformers_pi0_inputs(ours, PI0Config.from_preset("pi0_small", vocab_size=vocab_size))


@pytest.fixture(scope="module")
def transformers_pi0(tmp_path_factory: pytest.TempPathFactory):
    model = tiny_transformers_pi0()
    folder = tmp_path_factory.mktemp("hf") / "pi0"
    model.save_pretrained(folder)
    return model, folder


@torch.no_grad()
def test_transformers_import_matches_transformers_sample_actions(transformers_pi0, tmp_path: Path) -> None:
    hf_model, folder = transformers_pi0
    result = convert_hf_checkpoint(folder, tmp_path / "ours", progress=False)
    assert any("gemma_expert" in name for name in result.dropped)  # the action expert's unused embedding table
    ours = PI0ForActionGeneration.from_pretrained(result.output_dir).eval()
    ours_inputs, hf_inputs = paired_inputs()
    noise = torch.randn(2, 50, 32, generator=torch.Generator().manual_seed(2))
    expected = hf_model.sample_actions(noise=noise, **hf_inputs)
    assert relative_error(ours.generate_actions(**ours_inputs, noise=noise), expected.numpy()) <= 1e-5
    time, actions = torch.tensor([0.3, 0.8]), torch.randn(2, 50, 32, generator=torch.Generator().manual_seed(3))
    velocity = hf_model(noise=noise, timestep=time, actions=actions, **hf_inputs).logits
    assert relative_error(ours(**ours_inputs, actions=actions, noise=noise, time=time).velocity, velocity.numpy()) <= 1e-5


def lerobot_key(transformers_name: str) -> str:
    """transformers' module names -> the key names of LeRobot's hub checkpoints (`lerobot/pi0_base`)."""
    for theirs, lerobot in (
        ("model.vlm.vision_tower.", "model.paligemma_with_expert.paligemma.model.vision_tower.vision_model."),
        ("model.vlm.language_model.embed_tokens.weight", "model.paligemma_with_expert.paligemma.lm_head.weight"),  # tied copy only
        ("model.vlm.", "model.paligemma_with_expert.paligemma.model."),
        ("model.dit.", "model.paligemma_with_expert.gemma_expert.model."),
        ("embed_action_time.", "model."),
        ("action_out_proj.", "model.action_out_proj."),
    ):
        if transformers_name.startswith(theirs):
            return lerobot + transformers_name[len(theirs):]
    raise AssertionError(transformers_name)


def test_lerobot_layout_import(transformers_pi0, tmp_path: Path) -> None:
    hf_model, folder = transformers_pi0
    state = {lerobot_key(k): v.contiguous() for k, v in hf_model.state_dict().items() if "dit.embed_tokens" not in k}
    state["model.paligemma_with_expert.gemma_expert.lm_head.weight"] = torch.zeros(1024, 48)
    (tmp_path / "lerobot").mkdir()
    save_file(state, tmp_path / "lerobot" / "model.safetensors", metadata={"format": "pt"})
    (tmp_path / "lerobot" / "config.json").write_text(json.dumps({"type": "pi0", "chunk_size": 50, "tokenizer_max_length": 48, "num_inference_steps": 10}))
    base = {"mean": torch.linspace(-1, 1, 7), "std": torch.linspace(0.5, 2, 7), "q01": torch.linspace(-3, -1, 7), "q99": torch.linspace(1, 3, 7)}
    stats = {f"{key}.{name}": value * (2 if key == "action" else 1) for key in ("observation.state", "action") for name, value in base.items()}
    save_file(stats, tmp_path / "lerobot" / "policy_preprocessor_step_3_normalizer_processor.safetensors")
    overrides = dict(num_attention_heads=4, num_key_value_heads=1, head_dim=32, vision_num_heads=4)  # not in LeRobot's config
    result = convert_hf_checkpoint(tmp_path / "lerobot", tmp_path / "ours", progress=False, **overrides)
    assert result.dropped == ["model.paligemma_with_expert.gemma_expert.lm_head.weight"]
    written = load_openpi_norm_stats(result.output_dir)
    assert np.allclose(written["state"].std, stats["observation.state.std"].numpy()) and np.allclose(written["actions"].q99, stats["action.q99"].numpy())
    from_transformers = convert_hf_checkpoint(folder, tmp_path / "reference", progress=False)
    expected = state_dict_of(from_transformers.output_dir)
    assert {k: torch.equal(v, expected[k]) for k, v in state_dict_of(result.output_dir).items()} == {k: True for k in expected}


def test_pi05_lerobot_layout_roundtrip(converted: dict, tmp_path: Path) -> None:
    """π0.5 in LeRobot's layout (adaRMS `*.dense`, `time_mlp_*`) imports back to the very same weights."""
    ours = state_dict_of(converted["pi05_small", "float32"])
    config = PI0ForActionGeneration.config_class.from_pretrained(converted["pi05_small", "float32"])
    lerobot = {}
    for name, tensor in ours.items():
        if name.startswith("expert_final_norm.modulation."):
            lerobot["model.paligemma_with_expert.gemma_expert.model.norm.dense." + name.rsplit(".", 1)[1]] = tensor
            continue
        for target, start, end in convert_hf._hf_export_names(name, config):
            lerobot[lerobot_key(target)] = tensor[start:end if end > 0 else None].clone()
    (tmp_path / "lerobot").mkdir()
    save_file(lerobot, tmp_path / "lerobot" / "model.safetensors", metadata={"format": "pt"})
    result = convert_hf_checkpoint(tmp_path / "lerobot", tmp_path / "ours", progress=False,
                                   num_attention_heads=4, head_dim=32, vision_num_heads=4, max_token_len=200)
    assert result.config.pi05 and result.dropped == []
    assert {k: torch.equal(v, ours[k]) for k, v in state_dict_of(result.output_dir).items()} == {k: True for k in ours}


@torch.no_grad()
def test_export_to_transformers_reproduces_openpi(converted: dict, references: dict, tmp_path: Path) -> None:
    from transformers import PI0ForConditionalGeneration

    ref = references["pi0_small"]
    out = export_to_transformers(converted["pi0_small", "float32"], tmp_path / "hf")
    hf_model, info = PI0ForConditionalGeneration.from_pretrained(out, output_loading_info=True)
    assert not any(info[k] for k in ("missing_keys", "unexpected_keys", "mismatched_keys")), info
    assert hf_model.config.dit_config.vocab_size == ref.config.vocab_size  # (set by us: transformers < 5.20 does not)
    inputs = ref.model_inputs()
    actions = hf_model.eval().sample_actions(**transformers_pi0_inputs(inputs, ref.config), noise=ref.tensor("inputs/sample_noise"))
    assert relative_error(actions, ref["fp32/actions"]) <= FLOAT32_TOLERANCE
    with pytest.raises(ConversionError, match="no π0.5"):
        export_to_transformers(converted["pi05_small", "float32"], tmp_path / "hf05")


def test_hf_import_errors(transformers_pi0, tmp_path: Path) -> None:
    _, folder = transformers_pi0
    state = state_dict_of(folder)
    broken = tmp_path / "broken"
    broken.mkdir()
    save_file({**state, "model.some_new_head.weight": torch.zeros(2, 2)}, broken / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(ConversionError, match="tensors not part of a π0/π0.5 model: model.some_new_head.weight"):
        convert_hf_checkpoint(broken, tmp_path / "out", progress=False)
    missing = {k: v for k, v in state.items() if not k.endswith("layers.1.self_attn.k_proj.weight")}
    save_file(missing, broken / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(ConversionError, match=r"incomplete fused parameters: layers\.1\.(vlm|expert)\.qkv_proj\.weight \(lacks part 1\)"):
        convert_hf_checkpoint(broken, tmp_path / "out", progress=False)
    (broken / "model.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}")
    with pytest.raises(ConversionError, match="cannot read"):
        convert_hf_checkpoint(broken, tmp_path / "out", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken"]


def test_a_truncated_weights_file_is_one_line_naming_the_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Issue 38.15: `convert --from pi0-torch --to transformers` on a truncated model.safetensors gave a traceback;
    nothing is written either."""
    from pi0_torch import demo_policy_dir
    from pi0_torch.cli import main

    shutil.copytree(demo_policy_dir(), tmp_path / "in")
    weights = tmp_path / "in" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    assert main(["convert", "--from", "pi0-torch", "--to", "transformers", "--input", str(tmp_path / "in"),
                 "--output-dir", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err
    assert error.startswith(f"error: {tmp_path / 'in'}: the weights are not a readable safetensors file") and error.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_no_progress_silences_the_export_to_transformers(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    """Issue 63, first hour 7: `convert --to transformers --no-progress` still showed "Writing model shards"."""
    from transformers.utils import logging as hf_logging

    from pi0_torch import demo_policy_dir
    from pi0_torch.cli import main

    hf_logging.enable_progress_bar()  # (as in a fresh process)
    assert main(["convert", "--from", "pi0-torch", "--to", "transformers", "--input", str(demo_policy_dir()),
                 "--output-dir", str(tmp_path / "out"), "--no-progress"]) == 0
    captured = capfd.readouterr()
    assert "Writing model shards" not in captured.err + captured.out and (tmp_path / "out" / "config.json").is_file()
