"""Issue 28, class 7 (and the model-folder and step-count items of classes 8 and 9): every size and count has an
upper bound that names it, memory is estimated before a model is built from a config, and a broken model folder or
step count is one line wherever it comes in (`PI0Policy.from_pretrained`, `pi0-torch serve`, `pi0-torch eval`)."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pi0_torch.cli import main
from pi0_torch.models.configuration_base import SIZE_LIMITS
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.inference.conditioning import euler_times
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import train_policy

REPO = Path(__file__).resolve().parents[1]
DEMO_POLICY = REPO / "pi0_torch" / "demo_policy"
PI0_SIZES = [name for name in SIZE_LIMITS if name in PI0Config().to_dict()]
FAST_SIZES = [name for name in SIZE_LIMITS if name in PI0FastConfig().to_dict()]


@pytest.mark.parametrize(("config_class", "name"), [(PI0Config, n) for n in PI0_SIZES] + [(PI0FastConfig, n) for n in FAST_SIZES])
def test_every_size_and_count_has_a_named_upper_bound(config_class: type, name: str) -> None:
    """`action_horizon: 1e8` ran the trainer out of memory, `num_inference_steps: 1e9` never returned,
    `num_hidden_layers: 1e6` failed after 348 s: each size is refused by name, at once, one past its bound."""
    preset = "pi0_small" if config_class is PI0Config else "pi0_fast_small"
    limit = SIZE_LIMITS[name]
    start = time.monotonic()
    with pytest.raises(ValueError, match=rf"^{name} must be an integer in \[\d+, {limit}\], got {limit + 1} \(int\)$"):
        config_class.from_preset(preset, **{name: limit + 1})
    with pytest.raises(ValueError, match=rf"^{name} must be an integer"):
        config_class.from_preset(preset, **{name: float(limit)})  # 1e9 in a JSON file is a float
    assert time.monotonic() - start < 1.0


def test_all_sizes_are_bounded() -> None:
    """No integer setting of either config's own escapes the table (a new size must get a bound); the others are
    bounded by a size (rtc_max_delay < action_horizon, fast_skip_tokens < vocab_size) or are 0/1 switches."""
    import inspect

    for config_class in (PI0Config, PI0FastConfig):
        own = inspect.signature(config_class.__init__).parameters
        defaults = {name: parameter.default for name, parameter in own.items() if type(parameter.default) is int}
        unbounded = sorted(set(defaults) - set(SIZE_LIMITS) - {"rtc_max_delay", "fast_skip_tokens",
                                                               "decoding_position_offset", "eos_token_id"})
        assert not unbounded, unbounded


@pytest.mark.parametrize("steps", [2.5, True, 0, 10**9, "10"])
def test_step_counts_are_integers_in_range(steps: object) -> None:
    """Issue 28.9: `num_steps=2.5` and `num_steps=True` were accepted; 1e9 never returned."""
    with pytest.raises(ValueError, match=r"num_steps must be an integer in \[1, 1000\]"):
        euler_times(steps)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"num_steps must be an integer in \[1, \d+\]"):
        PI0Policy.from_pretrained(DEMO_POLICY, device="cpu", num_steps=steps)  # type: ignore[arg-type]


def test_serve_with_absurd_steps_fails_before_listening(tmp_path: Path) -> None:
    """`serve --num-steps 1000000000` never listened (its warm-up never returned)."""
    start = time.monotonic()
    finished = subprocess.run([sys.executable, "-m", "pi0_torch.cli", "serve", "--model", str(DEMO_POLICY), "--port", "0",
                               "--device", "cpu", "--num-steps", "1000000000"], capture_output=True, text=True, timeout=120)
    assert finished.returncode == 1 and time.monotonic() - start < 60
    assert "num_steps must be an integer in [1, 8192], got 1000000000" in finished.stderr and "Traceback" not in finished.stderr


def test_a_model_too_large_for_this_machine_is_refused_before_allocating(tmp_path: Path) -> None:
    huge = {"vlm_hidden_size": 16_384, "vlm_intermediate_size": 65_536, "num_hidden_layers": 256}
    config = PI0Config.from_preset("pi0", **huge)
    assert config.estimated_parameters() > 800e9
    with pytest.raises(ValueError, match=r"this config has about \d+\.\d B parameters, \d+\.\d GiB of float32 weights "
                                         r"alone; this machine has"):
        train_policy(TrainSettings(dataset=str(REPO / "missing-dataset"), model="pi0", output_dir=str(tmp_path / "run"),
                                   config_overrides=huge))


BROKEN_FOLDERS = {
    "config.json is a JSON list": (lambda folder: (folder / "config.json").write_text("[1, 2]"),
                                   "config.json must hold a JSON object of settings, got a JSON list"),
    "dtype float7": (lambda folder: (folder / "config.json").write_text(json.dumps(
        {**json.loads((folder / "config.json").read_text()), "dtype": "float7"})),
        "dtype must name a torch floating-point dtype (float32, bfloat16, float16) or 'auto', got 'float7'"),
    "truncated weights": (lambda folder: (folder / "model.safetensors").write_bytes(
        (folder / "model.safetensors").read_bytes()[:1000]), "the weights are not a readable safetensors file"),
}


@pytest.fixture(params=sorted(BROKEN_FOLDERS))
def broken_folder(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    folder = tmp_path / "policy"
    shutil.copytree(DEMO_POLICY, folder)
    damage, message = BROKEN_FOLDERS[request.param]
    damage(folder)
    return folder, message


def test_a_broken_model_folder_is_one_line_in_python(broken_folder: tuple[Path, str]) -> None:
    folder, message = broken_folder
    with pytest.raises(ValueError) as refused:
        PI0Policy.from_pretrained(folder, device="cpu")
    assert message in str(refused.value) and "\n" not in str(refused.value), refused.value


def test_a_broken_model_folder_is_one_line_on_the_command_line(broken_folder: tuple[Path, str], capsys: pytest.CaptureFixture[str],
                                                               caplog: pytest.LogCaptureFixture) -> None:
    folder, message = broken_folder
    assert main(["eval", "--policy", str(folder), "--env", "pi0_torch/Reach-v0", "--episodes", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pi0-torch eval: error: ") and message in err and "\n" not in err, err
    with caplog.at_level(logging.ERROR):
        assert main(["serve", "--model", str(folder), "--port", "0", "--device", "cpu"]) == 1
    errors = [record for record in caplog.records if record.levelno >= logging.ERROR]
    assert len(errors) == 1 and message in errors[0].getMessage() and not errors[0].exc_info


def test_a_fast_chunk_outside_the_fitted_range_warns_when_encoded(caplog: pytest.LogCaptureFixture) -> None:
    """Issue 28.9: such a chunk encoded to tokens that decode to zeros, silently."""
    from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer

    rng = np.random.default_rng(0)
    chunks = [np.cumsum(rng.normal(0, 0.1, (10, 3)), axis=0) for _ in range(200)]
    tokenizer = FASTActionTokenizer.fit(chunks, scale=10, vocab_size=256)
    with caplog.at_level(logging.WARNING):
        tokenizer(np.stack(chunks[:5]))
    assert not caplog.records and tokenizer.unencodable_chunks == 0
    with caplog.at_level(logging.WARNING):
        ids = tokenizer(np.stack([chunks[0], chunks[1] * 50, chunks[2] * 50]))
    assert tokenizer.unencodable_chunks == 2 and len(caplog.records) == 1
    assert "FAST: chunk 1 has scaled DCT coefficients in" in caplog.text and "outside what this tokenizer encodes" in caplog.text
    assert not np.allclose(tokenizer.decode(ids[1:2], 10, 3)[0], chunks[1] * 50, atol=0.5)  # what the warning is about


@pytest.mark.parametrize(("setting", "message"), [
    ({"max_batch_size": 10**9}, r"max_batch_size must be an integer in \[1, 1024\], got 1000000000"),  # a compiled
    ({"port": 70_000}, r"port must be an integer in \[0, 65535\], got 70000"),  # warm-up ran every batch size
])
def test_server_counts_are_bounded(setting: dict, message: str) -> None:
    from pi0_torch.runtime.serving import PolicyServer

    class Policy:  # what PolicyServer reads before serving
        metadata: dict = {}
        camera_names = ["base_0_rgb"]

    with pytest.raises(ValueError, match=message):
        PolicyServer(Policy(), **setting)  # type: ignore[arg-type]
