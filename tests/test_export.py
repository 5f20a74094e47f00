"""`pi0-torch export` and `ExportedPolicy` (`pi0_torch.deploy`): the exported graphs return what the model returns,
in onnxruntime (without torch) and as an AOTInductor package (without pi0_torch); openpi's own actions are met
through an exported graph; a deployment folder refuses what it cannot run, by name.

The exports here run 2 Euler steps of the demo policy (seconds each); `make test-slow` adds π0.5's fixture in ONNX."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pi0_torch.deploy.export import ExportError, export_model, write_onnx
from pi0_torch.deploy.folder import DEPLOY_FILE, INPUT_NAMES, ExportFolderError, read_deploy
from pi0_torch.deploy.policy import ExportedPolicy, is_export_folder
from pi0_torch.runtime.observation_formats import ObservationError
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.shipped_policy import demo_policy_dir

from conftest import OpenpiReference, relative_error

REPO = Path(__file__).resolve().parents[1]
STEPS = 2
PROGRAM_INPUTS = ("pixel_values", "image_masks", "input_ids", "attention_mask", "state", "noise")


def observations() -> list[dict]:
    rng = np.random.default_rng(0)
    frame = lambda h, w: rng.integers(0, 256, (h, w, 3), dtype=np.uint8)  # noqa: E731
    return [
        {"images": {"base_0_rgb": frame(60, 80), "left_wrist_0_rgb": frame(48, 48)}, "state": rng.standard_normal(3),
         "prompt": "pick up the red block"},
        {"images": {"base_0_rgb": frame(120, 90)}, "state": rng.standard_normal(3), "prompt": "reach the green zone"},
    ]


def relative(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.abs(got - want).max() / np.abs(want).max())


@pytest.fixture(scope="module")
def onnx_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_model("demo", tmp_path_factory.mktemp("export") / "demo_onnx", "onnx", num_steps=STEPS, progress=False)


@pytest.fixture(scope="module")
def pt2_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_model("demo", tmp_path_factory.mktemp("export") / "demo_pt2", "pt2", num_steps=STEPS, progress=False)


def test_the_folder_holds_what_a_runtime_needs(onnx_folder: Path) -> None:
    names = sorted(path.name for path in onnx_folder.iterdir() if not path.name.startswith("."))
    assert names == ["deploy.json", "model.onnx", "norm_stats.json", "policy_settings.json", "processor_config.json",
                     "reference.npz", "tokenizer.model"]
    spec = read_deploy(onnx_folder)
    assert [entry["name"] for entry in spec["inputs"]] == list(INPUT_NAMES)
    shapes = {entry["name"]: (entry["dtype"], entry["shape"]) for entry in spec["inputs"]}
    assert shapes["images"] == ("uint8", [1, 2, 48, 48, 3]) and shapes["noise"] == ("float32", [1, 16, 3])
    assert spec["outputs"] == [{"name": "actions", "dtype": "float32", "shape": [1, 16, 3]}]
    assert spec["artifact"]["opset"] >= 18 and len(spec["artifact"]["sha256"]["model.onnx"]) == 64
    assert spec["model"]["num_steps"] == STEPS and "model.safetensors" in spec["model"]["source_sha256"]
    assert spec["noise"]["scale"] == 0.1  # (the demo policy's recommended noise)
    reference = np.load(onnx_folder / "reference.npz")
    assert sorted(reference.files) == sorted([*INPUT_NAMES, "actions"])


@pytest.mark.parametrize("fmt", ["onnx", "pt2"])
def test_exported_policy_returns_the_model_policys_actions(fmt: str, request: pytest.FixtureRequest) -> None:
    folder = request.getfixturevalue(f"{fmt}_folder")
    exported = ExportedPolicy.from_folder(folder, noise_scale=0.0)  # (verifies its hash and reference.npz)
    model = PI0Policy.from_pretrained("demo", num_steps=STEPS, noise_scale=0.0)
    for observation in observations():
        got, want = exported.infer(observation)["actions"], model.infer(observation)["actions"]
        assert got.shape == want.shape == (16, 3) and got.dtype == np.float32
        assert relative(got, want) <= 1e-5
    with_noise = ExportedPolicy.from_folder(folder, seed=3)
    first, again = (ExportedPolicy.from_folder(folder, seed=3).infer(observations()[0])["actions"] for _ in range(2))
    assert np.array_equal(first, again) and np.array_equal(first, with_noise.infer(observations()[0])["actions"])
    assert with_noise.metadata["model_type"] == "pi0" and with_noise.metadata["replan_steps"] == 4


def test_observations_are_checked_as_pi0_policy_checks_them(onnx_folder: Path) -> None:
    exported = ExportedPolicy.from_folder(onnx_folder)
    model = PI0Policy.from_pretrained("demo", num_steps=STEPS)
    bad = [
        {**observations()[0], "state": np.zeros(5)},
        {**observations()[0], "images": {"top": np.zeros((8, 8, 3), np.uint8)}},
        {**observations()[0], "state": np.array([np.nan, 0, 0])},
        {**observations()[0], "images": {"base_0_rgb": np.full((8, 8, 3), 2.0, np.float32)}},
    ]
    for observation in bad:
        with pytest.raises(ObservationError) as theirs:
            model.prepare(observation)
        with pytest.raises(ObservationError) as ours:
            exported.prepare(observation)
        assert str(ours.value) == str(theirs.value)
    with pytest.raises(ObservationError, match="takes no real-time chunking"):
        exported.prepare({**observations()[0], "previous_actions": np.zeros((16, 3)), "execution_horizon": 4})


def test_an_onnx_export_runs_without_torch(onnx_folder: Path) -> None:
    """numpy, onnxruntime, sentencepiece and Pillow only: importing torch (or transformers) fails in this process."""
    script = f"""
import builtins, sys
real = builtins.__import__
def guard(name, *args, **kwargs):
    if name.split(".")[0] in ("torch", "transformers", "huggingface_hub", "safetensors", "tokenizers"):
        raise ImportError("blocked " + name)
    return real(name, *args, **kwargs)
builtins.__import__ = guard
import numpy as np
from pi0_torch.deploy import ExportedPolicy
policy = ExportedPolicy.from_folder({str(onnx_folder)!r}, seed=0)
actions = policy.infer({{"images": {{"base_0_rgb": np.zeros((60, 80, 3), np.uint8)}}, "state": np.zeros(3), "prompt": "reach"}})["actions"]
print(actions.shape, "torch" in sys.modules, np.isfinite(actions).all())
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("\n")[-2] == "(16, 3) False True"


def test_a_pt2_package_runs_without_pi0_torch(pt2_folder: Path) -> None:
    script = f"""
import sys, numpy as np, torch
compiled = torch._inductor.aoti_load_package({str(pt2_folder / 'model.pt2')!r})
reference = np.load({str(pt2_folder / 'reference.npz')!r})
names = {list(INPUT_NAMES)!r}
outputs = compiled(*(torch.from_numpy(reference[name]) for name in names))
actions = (outputs[0] if isinstance(outputs, (list, tuple)) else outputs).numpy()
print(float(np.abs(actions - reference["actions"]).max()), any(name.startswith("pi0_torch") for name in sys.modules))
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd="/", timeout=300)
    assert result.returncode == 0, result.stderr
    deviation, imported = result.stdout.split()
    assert float(deviation) <= 1e-6 and imported == "False"


@pytest.mark.parametrize("variant", ["pi0_small", pytest.param("pi05_small", marks=pytest.mark.slow)])
def test_openpi_actions_through_an_onnx_graph(variant: str, tmp_path: Path) -> None:
    """The exportable core of the openpi fixture model, as ONNX in onnxruntime: openpi's own actions (π0.5: slow)."""
    import onnxruntime

    reference = OpenpiReference(variant)
    model, inputs = reference.model(), reference.model_inputs()
    arguments = (inputs["pixel_values"], inputs["image_masks"], inputs["input_ids"], inputs["attention_mask"].bool(),
                 inputs["state"], reference.tensor("inputs/sample_noise"))
    program = model.sampling_program(batch_size=2, num_steps=int(reference["inputs/num_steps"]))
    exported = torch.export.export(program, arguments, strict=False)
    assert relative_error(exported.module()(*arguments), reference["fp32/actions"]) <= 1e-5
    write_onnx(exported, arguments, tmp_path / "core.onnx", input_names=PROGRAM_INPUTS, optimize=False)
    session = onnxruntime.InferenceSession(str(tmp_path / "core.onnx"), providers=["CPUExecutionProvider"])
    feed = {name: value.numpy() for name, value in zip(PROGRAM_INPUTS, arguments)}
    assert relative_error(session.run(None, feed)[0], reference["fp32/actions"]) <= 1e-5


def test_eval_and_serve_take_an_exported_folder(onnx_folder: Path) -> None:
    from pi0_torch.runtime.rollout import LocalPolicy, load_policy

    local = load_policy(str(onnx_folder), connections=1)
    assert isinstance(local, LocalPolicy) and isinstance(local.policy, ExportedPolicy) and is_export_folder(onnx_folder)
    with pytest.raises(ValueError, match="exported with 2 steps"):
        load_policy(str(onnx_folder), connections=1, num_steps=10)
    result = subprocess.run([sys.executable, "-m", "pi0_torch.cli", "eval", "--policy", str(onnx_folder), "--env",
                             "pi0_torch/Reach-v0", "--episodes", "2", "--num-envs", "2"], capture_output=True, text=True,
                            cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "success" in result.stdout


# -- what is refused -------------------------------------------------------------------------------------------------


def test_a_folder_that_is_not_a_usable_export_is_refused_in_one_line(onnx_folder: Path, tmp_path: Path) -> None:
    with pytest.raises(ExportFolderError, match="holds no deploy.json, so it is not an exported policy"):
        ExportedPolicy.from_folder(demo_policy_dir())
    damaged = shutil.copytree(onnx_folder, tmp_path / "damaged")
    with (damaged / "model.onnx").open("ab") as stream:
        stream.write(b"\0")
    with pytest.raises(ExportFolderError, match="SHA-256 .* differs"):
        ExportedPolicy.from_folder(damaged)
    (damaged / "tokenizer.model").unlink()
    with pytest.raises(ExportFolderError, match="'tokenizer.model' is missing"):
        ExportedPolicy.from_folder(damaged)
    newer = shutil.copytree(onnx_folder, tmp_path / "newer")
    spec = json.loads((newer / DEPLOY_FILE).read_text())
    (newer / DEPLOY_FILE).write_text(json.dumps({**spec, "format_version": 99}))
    with pytest.raises(ExportFolderError, match="export format version 99"):
        ExportedPolicy.from_folder(newer)
    with pytest.raises(ExportFolderError, match="no CUDAExecutionProvider .* onnxruntime-gpu"):
        ExportedPolicy.from_folder(onnx_folder, provider="cuda")


def test_what_cannot_be_exported_is_refused_before_loading(tmp_path: Path) -> None:
    fast = tmp_path / "fast"
    fast.mkdir()
    (fast / "config.json").write_text(json.dumps({"model_type": "pi0_fast_torch"}))
    with pytest.raises(ExportError, match="π0-FAST model: its variable-length token decoding is not exported"):
        export_model(fast, tmp_path / "out", "onnx")
    from pi0_torch import PI0ForActionGeneration
    from pi0_torch.training.lora import apply_lora

    adapter = shutil.copytree(demo_policy_dir(), tmp_path / "lora")  # a LoRA run's checkpoint: adapters not merged
    apply_lora(PI0ForActionGeneration.from_pretrained(adapter), 2, 2).save_pretrained(adapter)
    with pytest.raises(ValueError, match=r"unexpected: layers\.0\.expert.* LoRA run, adapters not merged: `pi0-torch "
                                         "consolidate"):
        export_model(adapter, tmp_path / "out", "onnx")
    with pytest.raises(ExportError, match="AOTInductor's CPU code has no fast float16 path"):
        export_model("demo", tmp_path / "out", "pt2", dtype="float16")
    with pytest.raises(ExportError, match="--format must be one of"):
        export_model("demo", tmp_path / "out", "tflite")
    with pytest.raises(ValueError, match="--opset must be an integer >= 18"):
        export_model("demo", tmp_path / "out", "onnx", opset=13)
    assert not (tmp_path / "out").exists()


def test_an_export_that_fails_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pi0_torch.deploy.export as export

    def full_disk(*args: object, **kwargs: object) -> list[str]:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "write_onnx", full_disk)
    with pytest.raises(OSError, match="No space left"):
        export_model("demo", tmp_path / "out", "onnx", num_steps=1, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_the_cpp_example_runs_a_pt2_package(pt2_folder: Path, tmp_path: Path) -> None:
    """examples/cpp builds against the torch wheel's C++ library and prints the package's actions for its stand-in
    inputs (black frames, every camera shown, the prompt `bos "\\n"`, zero state and noise): those of the package run
    from Python on the same inputs."""
    tools = [tool for tool in ("cmake", "c++") if shutil.which(tool) is None]
    headers = Path(torch.__file__).parent / "include" / "torch" / "csrc" / "inductor" / "aoti_package" / "model_package_loader.h"
    if tools or not headers.is_file():
        pytest.skip(f"needs {' and '.join(tools) or 'the torch wheel’s C++ headers'} to build examples/cpp")
    prefix = f"-DCMAKE_PREFIX_PATH={torch.utils.cmake_prefix_path}"
    for command in (["cmake", "-S", str(REPO / "examples" / "cpp"), "-B", str(tmp_path), prefix],
                    ["cmake", "--build", str(tmp_path), "-j", "2"]):
        built = subprocess.run(command, capture_output=True, text=True, timeout=600)
        assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    result = subprocess.run([str(tmp_path / "run_policy"), str(pt2_folder / "model.pt2")], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    printed = np.array([[float(v) for v in line.split()] for line in result.stdout.splitlines()[1:17]])

    reference = np.load(pt2_folder / "reference.npz")
    inputs = [np.zeros_like(reference[name]) for name in INPUT_NAMES]
    inputs[1][:] = True
    inputs[2][:, :2], inputs[3][:, :2] = (2, 108), True
    compiled = torch._inductor.aoti_load_package(str(pt2_folder / "model.pt2"))
    outputs = compiled(*(torch.from_numpy(value) for value in inputs))
    expected = (outputs[0] if isinstance(outputs, (list, tuple)) else outputs)[0].numpy()  # [horizon, dims]
    assert printed.shape == expected.shape == (16, 3)
    assert np.abs(printed - expected).max() <= 1e-3  # (printed with 4 decimals)


def test_a_bfloat16_onnx_export_is_verified_by_its_program_and_refused_on_the_cpu_provider(tmp_path: Path) -> None:
    folder = export_model("demo", tmp_path / "bf16", "onnx", dtype="bfloat16", num_steps=1, progress=False,
                          optimize=False)
    spec = read_deploy(folder)
    assert spec["artifact"]["dtype"] == "bfloat16" and spec["artifact"]["verified_by"].startswith("the traced program")
    with pytest.raises(ExportFolderError, match="bfloat16 ONNX graph, which onnxruntime runs on its 'cuda' and 'tensorrt'"):
        ExportedPolicy.from_folder(folder)
