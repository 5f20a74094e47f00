"""Inputs that used to crash deep or go silently wrong (issue 17 items 8-10, issue 16 item 1): each now gets a
`ValueError` (or a one-line CLI error) naming the argument, what was expected and what came."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import safetensors
import torch
import transformers

from pi0_torch import PI0Config, PI0ForActionGeneration, PI0Processor
from pi0_torch.cli import main as cli_main
from pi0_torch.data.lerobot_dataset import LeRobotDatasetError, LeRobotEpisodeDataset
from pi0_torch.data.synthetic_data import write_synthetic_dataset
from pi0_torch.processing.images import resize_with_pad, to_model_image
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.utils.validation import is_hub_id

# a tiny π0 (one camera, short horizon): every check runs before or around a fraction of a millisecond of math
TINY = dict(
    image_size=28, vision_hidden_size=16, vision_intermediate_size=32, vision_num_layers=1, vision_num_heads=2,
    vlm_hidden_size=32, vlm_intermediate_size=64, expert_hidden_size=16, expert_intermediate_size=32,
    num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1, head_dim=8, vocab_size=512,
    action_dim=8, action_horizon=4, max_token_len=12, camera_names=["base_0_rgb"], num_inference_steps=2,
)
STATS = {key: NormStats(mean=np.zeros(dim), std=np.ones(dim), q01=-np.ones(dim), q99=np.ones(dim))
         for key, dim in (("state", 6), ("actions", 5))}


@pytest.fixture(scope="module")
def tokenizer():
    return build_test_tokenizer()


@pytest.fixture(scope="module")
def model() -> PI0ForActionGeneration:
    torch.manual_seed(0)
    return PI0ForActionGeneration(PI0Config.from_preset("pi0_small", **TINY)).eval()


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory, model: PI0ForActionGeneration, tokenizer) -> Path:
    """A model folder as the converter writes it (weights, config and processor)."""
    folder = tmp_path_factory.mktemp("saved") / "tiny"
    model.save_pretrained(folder)
    PI0Processor.from_config(model.config, tokenizer, norm_stats=STATS).save_pretrained(folder)
    return folder


def inputs(config: PI0Config, **changes: Any) -> dict[str, Any]:
    values = dict(
        pixel_values=torch.zeros(1, 1, 3, 28, 28), image_masks=torch.ones(1, 1, dtype=torch.bool),
        input_ids=torch.ones(1, 12, dtype=torch.long), attention_mask=torch.ones(1, 12, dtype=torch.bool),
        state=torch.zeros(1, 8),
    )
    return {**values, **changes}


def with_value(shape: tuple[int, ...], index: tuple[int, ...], value: float) -> torch.Tensor:
    tensor = torch.zeros(shape)
    tensor[index] = value
    return tensor


# --------------------------------------------------------------------------------------------- model inputs


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (dict(state=with_value((1, 8), (0, 3), float("nan"))), r"state must be finite, got 1 NaN/inf value \(the first at index \(0, 3\)\)"),
        (dict(state=with_value((1, 8), (0, 0), float("inf"))), "state must be finite"),
        (dict(noise=torch.full((1, 4, 8), float("nan"))), "noise must be finite, got 32 NaN/inf values"),
        (dict(input_ids=torch.full((1, 12), 512)), r"input_ids must be token ids in \[0, vocab_size=512\), got values in \[512, 512\]"),
        (dict(input_ids=torch.full((1, 12), -1)), r"input_ids must be token ids .* got values in \[-1, -1\]"),
        (dict(input_ids=[[1] * 12]), r"input_ids must be a torch.Tensor \[B=1, L\] .* got list"),
        (dict(input_ids=np.ones((1, 12), np.int64)), r"input_ids must be a torch.Tensor .* got shape \(1, 12\) dtype int64"),
        (dict(input_ids=None), "input_ids must be a torch.Tensor .* got NoneType"),
    ],
)
def test_generate_actions_refuses_bad_inputs(model: PI0ForActionGeneration, changes: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        model.generate_actions(**inputs(model.config, **changes))


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (dict(state=with_value((1, 8), (0, 1), float("nan"))), "state must be finite"),
        (dict(actions=with_value((1, 4, 8), (0, 2, 5), float("inf"))), r"actions must be finite, .*\(0, 2, 5\)"),
        (dict(time=torch.tensor([float("nan")])), "time must be finite"),
        (dict(input_ids=torch.full((1, 12), 600)), "input_ids must be token ids"),
    ],
)
def test_forward_refuses_bad_inputs(model: PI0ForActionGeneration, changes: dict, message: str) -> None:
    batch = {**inputs(model.config), "actions": torch.zeros(1, 4, 8), **changes}
    with pytest.raises(ValueError, match=message):
        model(**batch)


@pytest.mark.parametrize("name", ["pixel_values", "image_masks", "input_ids", "attention_mask", "state", "noise"])
def test_inputs_on_another_device_than_the_model_are_named(model: PI0ForActionGeneration, name: str) -> None:
    """Before: a CUDA model given a processor's CPU tensors failed deep inside with torch's "Expected all tensors to be
    on the same device" (here the `meta` device plays the other one)."""
    batch = {**inputs(model.config), "noise": torch.zeros(1, 4, 8)}
    batch[name] = batch[name].to("meta")
    with pytest.raises(ValueError, match=rf"{name} is on meta but the model is on cpu: move the inputs .*inputs.to\(model.device\)"):
        model.generate_actions(**batch)
    batch.pop("noise")
    if name != "noise":
        with pytest.raises(ValueError, match=rf"{name} is on meta but the model is on cpu"):
            model(**batch)


def test_a_model_split_or_offloaded_by_a_device_map_is_refused(saved: Path, tmp_path: Path, model: PI0ForActionGeneration) -> None:
    """`from_pretrained(..., device_map=...)` that offloads layers leaves their weights on `meta` until each module runs;
    sampling read some outside their modules and failed with "Tensor on device meta is not on the expected device
    cpu!". Now a one-line refusal says what to do. A device map with one place works as before."""
    pytest.importorskip("accelerate")
    device_map = {name: "cpu" for name, _ in model.named_children()} | {"layers": "disk"}
    offloaded = PI0ForActionGeneration.from_pretrained(saved, device_map=device_map, offload_folder=str(tmp_path / "offload"))
    batch = inputs(model.config)
    for run in (lambda: offloaded.generate_actions(**batch), lambda: offloaded(**batch)):
        with pytest.raises(ValueError, match=r"device_map placing its weights on \['cpu', 'disk'\]; it runs with every weight on one device"):
            run()
    for one_place in ({"": "cpu"}, {"vision_tower": "cuda", "layers": "cuda:0"}):  # (a map as transformers records it)
        offloaded.hf_device_map = one_place
        offloaded._check_placement()
    offloaded.hf_device_map = {"vision_tower": "cuda:0", "layers": "cuda:1"}
    with pytest.raises(ValueError, match=r"placing its weights on \['cuda:0', 'cuda:1'\]"):
        offloaded._check_placement()
    placed = PI0ForActionGeneration.from_pretrained(saved, device_map={"": "cpu"}).eval()
    noise = torch.randn(1, 4, 8, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(placed.generate_actions(**batch, noise=noise), model.generate_actions(**batch, noise=noise), rtol=0, atol=0)


def test_policy_refuses_a_state_that_overflows_float32(model: PI0ForActionGeneration, tokenizer) -> None:
    """Before: 1e308 passed the float64 check and became inf -> NaN actions."""
    policy = PI0Policy(model, PI0Processor.from_config(model.config, tokenizer, norm_stats=STATS), seed=0)
    frame = np.zeros((48, 64, 3), np.uint8)
    observation = {"images": {"base_0_rgb": frame}, "state": np.zeros(6), "prompt": "pick up the fork"}
    assert np.isfinite(policy.infer(observation)["actions"]).all()
    state = np.zeros(6)
    state[4] = 1e308
    with pytest.raises(ValueError, match=r"observation.state: has values beyond float32's range \(±3.4e38\) at dims \[4\]"):
        policy.infer({**observation, "state": state})
    tiny_std = {**STATS, "state": NormStats(mean=np.zeros(6), std=np.full(6, 1e-30))}
    strict = PI0Processor.from_config(model.config, tokenizer, norm_stats=tiny_std, min_norm_scale=0.0)
    state[4] = 1e33  # fine as float32, not once divided by std + 1e-6
    with pytest.raises(ValueError, match=r"state \(normalized\): has values beyond float32's range .* dims \[4\]"):
        strict(images={"base_0_rgb": frame}, state=state, prompt="go")
    actions = np.zeros((4, 5))
    actions[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"actions: contains NaN or inf at indices \[\(1, 2\)\]"):
        strict(images={"base_0_rgb": frame}, state=np.zeros(6), prompt="go", actions=actions)


def test_empty_frames_are_refused_and_thin_strips_are_resized() -> None:
    """Before: 0x0 raised ZeroDivisionError; 1x20000 was refused with 'height and width must be > 0'."""
    for frame in (np.zeros((0, 0, 3), np.uint8), np.zeros((3, 5, 0), np.float32), torch.zeros(0, 7, 3)):
        with pytest.raises(ValueError, match=r"images\['cam'\]: a frame of \d+x\d+ pixels; expected at least 1x1"):
            to_model_image(frame, 224, name="images['cam']")
    with pytest.raises(ValueError, match="a frame of 0x4 pixels"):
        resize_with_pad(np.zeros((0, 4, 3), np.uint8), 224, 224)
    strip = np.full((1, 20_000, 3), 255, np.uint8)
    image = to_model_image(strip, 224)  # scaled to 224x1, padded to 224x224
    assert image.shape == (3, 224, 224) and (image[:, 111:113] > -1).any() and (image[:, :100] == -1).all()
    float_strip = to_model_image(np.ones((20_000, 1, 3), np.float32), 224)
    assert float_strip.shape == (3, 224, 224) and (float_strip > -1).any()


# --------------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(num_key_value_heads=0), r"num_key_value_heads must be an integer in \[1, 256\], got 0"),  # was ZeroDivisionError
        (dict(patch_size=0), r"patch_size must be an integer in \[1, 2048\], got 0"),  # was ZeroDivisionError
        (dict(expert_hidden_size="48"), r"expert_hidden_size must be an integer in \[1, 16384\], got '48' \(str\)"),  # TypeError
        (dict(action_horizon=8.0), r"action_horizon must be an integer in \[1, 1024\], got 8.0 \(float\)"),
        (dict(rope_theta=-1.0), "rope_theta must be a finite number > 0, got -1.0"),  # was NaN actions
        (dict(rms_norm_eps=-1e-6), "rms_norm_eps must be a finite number > 0"),  # was NaN actions
        (dict(time_max_period=0.0), "time_max_period must be a finite number > 0, got 0.0"),  # was NaN actions
        (dict(time_min_period=float("inf")), "time_min_period must be a finite number > 0, got inf"),
        (dict(time_offset=0.5), r"time_scale \+ time_offset must be <= 1"),
        (dict(vision_num_heads=3), r"vision_hidden_size \(40\) must be a multiple of vision_num_heads \(3\)"),
        (dict(camera_names="base_0_rgb"), "camera_names must be a list of camera names"),
        (dict(camera_names=["a", ""]), "camera_names must be non-empty, unique strings"),
        (dict(action_horizn=8), r"unknown config settings \['action_horizn'\] \(did you mean 'action_horizon'"),
        (dict(pi05=True), "pi05 is set by the preset name"),
    ],
)
def test_config_settings_are_checked(overrides: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PI0Config.from_preset("pi0_small", **overrides)


def test_config_json_is_checked_on_load(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "config"
    PI0Config.from_preset("pi0_small").save_pretrained(folder)
    saved = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps([saved]))  # was TypeError: argument after ** must be a mapping
    with pytest.raises(ValueError, match=r"config.json must hold a JSON object of settings, got a JSON list"):
        PI0Config.from_pretrained(folder)
    (folder / "config.json").write_text(json.dumps({**saved, "num_key_value_heads": 0}))
    with pytest.raises(ValueError, match="num_key_value_heads must be an integer in \\[1, 256\\]"):
        PI0Config.from_pretrained(folder)
    with pytest.raises(ValueError, match="pi05 must be true or false, got 'false'"):
        PI0Config.from_dict({**saved, "pi05": "false"})
    # keys transformers writes are expected; a stray one (a typo, or a newer version's) is loaded with a warning
    (folder / "config.json").write_text(json.dumps({**saved, "action_horizn": 8}))
    with caplog.at_level(logging.WARNING, logger="pi0_torch.models.configuration_pi0"):
        config = PI0Config.from_pretrained(folder)
    assert config.action_horizon == 50
    assert caplog.messages == [
        "PI0Config: ignoring unknown settings ['action_horizn'] (did you mean 'action_horizon' for 'action_horizn'?)"
    ]


def test_processor_config_unknown_key_is_named(saved: Path, tmp_path: Path) -> None:
    folder = Path(shutil.copytree(saved, tmp_path / "copy"))
    settings = json.loads((folder / "processor_config.json").read_text())
    (folder / "processor_config.json").write_text(json.dumps({**settings, "colour": 1}))  # was TypeError
    with pytest.raises(ValueError, match=r"processor_config.json has unknown settings \['colour'\]"):
        PI0Processor.from_pretrained(folder)
    (folder / "processor_config.json").write_text("[]")
    with pytest.raises(ValueError, match="processor_config.json must hold a JSON object"):
        PI0Processor.from_pretrained(folder)


# --------------------------------------------------------------------------------------------- model locations


@pytest.fixture()
def no_hub(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any attempt to reach the hub (or its cache) fails the test."""
    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError(f"tried the hub with {args[:1]}")

    monkeypatch.setattr(transformers.PreTrainedModel, "from_pretrained", classmethod(refuse))
    monkeypatch.setattr(transformers.PretrainedConfig, "from_pretrained", classmethod(refuse))
    monkeypatch.setattr("huggingface_hub.snapshot_download", refuse)


def test_what_counts_as_a_hub_id(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "converted").mkdir()
    assert is_hub_id("someone/pi05_droid") and is_hub_id("lerobot/pi0.5-droid_v2")
    for local in ("converted/pi05_droid", "pi05_droid", "./pi05/droid", "../pi05/droid", "/data/pi05_droid",
                  "~/pi05_droid", "a/b/c", "some--one/x", "someone/x.git", Path("someone/pi05_droid")):
        assert not is_hub_id(local), local


def test_missing_model_folders_fail_fast_and_point_to_convert(
    saved: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_hub: None
) -> None:
    """Before: a missing folder was a hub repo-id format error (or a hub connection error after ~50 s), a folder
    without config.json a list of missing tensors of a default-size model."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "converted").mkdir()
    for loader in (PI0ForActionGeneration.from_pretrained, PI0Config.from_pretrained, PI0Processor.from_pretrained):
        for path in ("converted/pi05_droid", str(tmp_path / "nowhere"), "pi05_droid"):
            with pytest.raises(FileNotFoundError, match=r"no (model|processor) folder at .*pi0-torch convert"):
                loader(path)
    no_config = Path(shutil.copytree(saved, tmp_path / "no_config"))
    (no_config / "config.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"no_config/config.json is missing, so .* is not a model folder \(it holds "):
        PI0ForActionGeneration.from_pretrained(no_config)
    with pytest.raises(FileNotFoundError, match="is a file; expected a model folder"):
        PI0ForActionGeneration.from_pretrained(no_config / "model.safetensors")
    with pytest.raises(FileNotFoundError, match="model folder not found"):
        PI0Policy.from_pretrained(tmp_path / "nowhere")


def test_a_hub_id_still_loads_from_the_hub(saved: Path, tmp_path: Path) -> None:
    """A converted model published on the hub, here in an offline hub cache: model and processor load from it."""
    commit = "0123456789abcdef0123456789abcdef01234567"
    repo = tmp_path / "hub" / "models--someone--tiny-pi0"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    shutil.copytree(saved, repo / "snapshots" / commit)
    options = dict(cache_dir=tmp_path / "hub", local_files_only=True)
    model = PI0ForActionGeneration.from_pretrained("someone/tiny-pi0", **options)
    processor = PI0Processor.from_pretrained("someone/tiny-pi0", **options)
    assert model.config.action_horizon == 4 and processor.state_dim == 6
    with pytest.raises(OSError, match="'someone/elsewhere' is no local folder, and as a hub id it could not be loaded"):
        PI0ForActionGeneration.from_pretrained("someone/elsewhere", **options)
    with pytest.raises(OSError, match="'someone/elsewhere' is no local folder"):
        PI0Processor.from_pretrained("someone/elsewhere", **options)


# --------------------------------------------------------------------------------------------- training and data


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("data") / "reach", num_episodes=2, num_heldout=0,
                                   episode_length=6, image_size=16, storage="image", seed=0)


def train(dataset: Path, output: Path, *extra: str) -> list[str]:
    return ["train", "--dataset", str(dataset), "--model", "pi0_small", "--output-dir", str(output),
            "--tokenizer", "test", "--cpu", *extra]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--max-steps", "0"), "error: --max-steps must be an integer in [1, 1000000000], got 0 (int)"),  # trained one step
        (("--batch-size", "0"), "error: --batch-size must be an integer in [1, 65536], got 0 (int)"),
        (("--batch-size", "1000000000"), "error: --batch-size must be an integer in [1, 65536], got 1000000000 (int)"),
        (("--config-overrides", '{"action_horizon": 100000000}'),  # the kernel killed the trainer at 23 GB
         "error: action_horizon must be an integer in [1, 1024], got 100000000 (int)"),
        (("--config-overrides", '{"action_horizn": 8}'),  # trained with horizon 50
         "error: unknown config settings ['action_horizn'] (did you mean 'action_horizon' for 'action_horizn'?)"),
        (("--config-overrides", '{"rope_theta": -1}'), "error: rope_theta must be a finite number > 0, got -1 (int)"),
    ],
)
def test_train_refuses_bad_settings_in_one_line(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: tuple[str, ...], message: str
) -> None:
    assert cli_main(train(dataset, tmp_path / "out", *extra)) == 1
    assert capsys.readouterr().err == message + "\n"
    assert not (tmp_path / "out").exists()


def test_config_overrides_must_be_a_json_object(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        cli_main(train(dataset, tmp_path / "out", "--config-overrides", "[8]"))
    assert exited.value.code == 2 and "expected a JSON object, got a JSON list" in capsys.readouterr().err


def test_broken_dataset_files_are_named(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = Path(shutil.copytree(dataset, tmp_path / "broken"))
    info = root / "meta" / "info.json"
    saved_info = info.read_text()
    for text, message in (("{not json", "is not valid JSON"), ("[]", "must hold a JSON object, got a JSON list"),
                          (json.dumps({**json.loads(saved_info), "features": []}), "'features' must map")):
        info.write_text(text)
        with pytest.raises(LeRobotDatasetError, match=rf"{info} {message}|{info}: {message}"):
            LeRobotEpisodeDataset(root, 4, progress=False)
    info.write_text(saved_info)
    data_file = min((root / "data").glob("chunk-*/*.parquet"))
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])  # a copy cut short
    with pytest.raises(LeRobotDatasetError, match=rf"{data_file} is not a readable parquet file"):
        LeRobotEpisodeDataset(root, 4, progress=False)
    # through the command: one line naming the file, no traceback
    assert cli_main(train(root, tmp_path / "out", "--max-steps", "1")) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {data_file} is not a readable parquet file (") and err.count("\n") == 1
    assert "Traceback" not in err


def test_a_folder_of_pickled_weights_is_refused_in_one_line(saved: Path, tmp_path: Path) -> None:
    """Never torch's traceback recommending `weights_only=False`: pickled weights are refused before anything loads."""
    pickled = tmp_path / "pickled"
    pickled.mkdir()
    shutil.copy(saved / "config.json", pickled / "config.json")
    (pickled / "pytorch_model.bin").write_bytes(b"not even a pickle")
    with pytest.raises(ValueError, match=r"holds only pickled weights \(pytorch_model.bin\); pickled weights are not "
                                         r"loaded") as error:
        PI0ForActionGeneration.from_pretrained(pickled)
    assert "weights_only=False" not in str(error.value)


def test_a_shard_index_pointing_outside_its_folder_is_refused(saved: Path, tmp_path: Path) -> None:
    """A `model.safetensors.index.json` naming `../other/model.safetensors` or an absolute path would load another
    folder's weights as this model's; as the dataset reader, the loader refuses shard paths leaving the folder."""
    sharded = tmp_path / "sharded"
    sharded.mkdir()
    shutil.copy(saved / "config.json", sharded / "config.json")
    names = list(safetensors.safe_open(saved / "model.safetensors", "pt").keys())
    for shard in ("../elsewhere/model.safetensors", str(saved / "model.safetensors")):
        index = {"metadata": {}, "weight_map": {name: shard for name in names}}
        (sharded / "model.safetensors.index.json").write_text(json.dumps(index))
        with pytest.raises(ValueError, match="names the shard .* outside the model folder"):
            PI0ForActionGeneration.from_pretrained(sharded)
    (sharded / "inside.safetensors").symlink_to(saved / "model.safetensors")  # a link leading out
    index = {"metadata": {}, "weight_map": {name: "inside.safetensors" for name in names}}
    (sharded / "model.safetensors.index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="names the shard 'inside.safetensors' outside the model folder"):
        PI0ForActionGeneration.from_pretrained(sharded)
    (sharded / "inside.safetensors").unlink()
    shutil.copy(saved / "model.safetensors", sharded / "inside.safetensors")  # the same shard, in the folder: loads
    PI0ForActionGeneration.from_pretrained(sharded)


def test_train_takes_demo_as_eval_and_serve_do() -> None:
    import argparse

    from pi0_torch.shipped_policy import demo_policy_dir
    from pi0_torch.training.trainer import add_arguments, settings_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--model", "demo", "--dataset", "data", "--output-dir", "out"])
    assert settings_from_args(args).model == str(demo_policy_dir())


@pytest.mark.parametrize("command", [["doctor"], ["eval", "--policy", "demo", "--env", "pi0_torch/Reach-v0"],
                                     ["bench", "--presets", "pi0_small"]])
def test_the_meta_device_is_refused_in_one_line(command: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 63, round 5 item 9: `--device meta` in doctor and eval, and `PI0Policy.from_pretrained(device="meta")`,
    gave tracebacks (meta tensors hold no data: nothing computes there)."""
    from pi0_torch.cli import main
    from pi0_torch.runtime import PI0Policy

    assert main([*command, "--device", "meta"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("--device: meta holds tensors without data, so nothing runs there; pi0-torch runs on cpu, "
                        "cuda or mps") and "\n" not in err, err
    with pytest.raises(ValueError, match=r"^device: meta holds tensors without data"):
        PI0Policy.from_pretrained("demo", device="meta")
