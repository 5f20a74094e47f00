"""`pi0-torch export`: a π0 / π0.5 model folder as one verified graph that runs without the model classes, in ONNX
(onnxruntime, TensorRT) or as an AOTInductor package (`torch._inductor.aoti_load_package`, or C++'s
`AOTIModelPackageLoader`), in a self-contained folder (`pi0_torch.deploy.folder`).

The graph (`DeployGraph`) is the model's exportable core (`PI0ForActionGeneration.sampling_program`: the prefix, its
k/v cache, every Euler step and π0's state token) between the processor's numeric ends: uint8 frames to [-1, 1],
the state normalized and padded, the actions cut to the robot's dims and unnormalized, delta actions made absolute.
It is traced with `torch.export` (non-strict), converted, run once by its runtime and compared with the model's own
`generate_actions` on the same inputs before anything is published; the folder appears whole or not at all.

Refused by name, never as a traceback from an exporter: π0-FAST (its decoding is variable-length), a LoRA run's
checkpoint (adapters not merged: `from_pretrained` refuses it), a device or dtype a format cannot take, an opset below 18.

```python
>>> import tempfile
>>> from pi0_torch.deploy.export import export_model
>>> folder = export_model("demo", tempfile.mkdtemp() + "/demo_onnx", "onnx", num_steps=2, progress=False, optimize=False)
>>> sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
['deploy.json', 'model.onnx', 'norm_stats.json', 'policy_settings.json', 'processor_config.json', 'reference.npz', 'tokenizer.model']

```
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pi0_torch import __version__
from pi0_torch.deploy.folder import (ACTION_TOLERANCE, DEPLOY_FILE, FORMAT_NAME, FORMAT_VERSION, FORMATS, INPUT_NAMES,
                                     MIN_OPSET, ONNX_PROTOBUF_LIMIT, OUTPUT_NAMES, REFERENCE_FILE, action_deviation,
                                     file_sha256)
from pi0_torch.processing.normalization import apply_delta, normalize, unnormalize
from pi0_torch.runtime.policy_settings import SETTINGS_FILE
from pi0_torch.shipped_policy import policy_location
from pi0_torch.utils import files
from pi0_torch.utils.limits import MAX_BATCH_SIZE
from pi0_torch.utils.validation import check_int, first_line

logger = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
DEVICES = ("cpu", "cuda")
REFERENCE_PROMPT = "pick up the object"


class ExportError(ValueError):
    """What cannot be exported, or an export that did not verify: one line naming it."""


class DeployGraph(nn.Module):
    """The exported graph: `generate_actions` between the processor's numeric ends (see the module docstring and
    `pi0_torch.deploy.folder` for the inputs and the output)."""

    def __init__(self, model: nn.Module, processor: Any, batch_size: int, num_steps: int, text_length: int) -> None:
        super().__init__()
        self.program = model.sampling_program(batch_size, num_steps, text_length)
        self.processor = processor
        self.action_dim = model.config.action_dim

    def forward(
        self,
        images: torch.Tensor,  # uint8 [B, C, H, W, 3]
        image_masks: torch.Tensor,  # bool [B, C]
        input_ids: torch.Tensor,  # int64 [B, L]
        attention_mask: torch.Tensor,  # bool [B, L]
        state: torch.Tensor,  # float32 [B, state_dim], the checkpoint's units
        noise: torch.Tensor,  # float32 [B, horizon, action_dim]
    ) -> torch.Tensor:
        processor = self.processor
        pixel_values = images.permute(0, 1, 4, 2, 3).float() / 255.0 * 2.0 - 1.0  # [B, C, 3, H, W], as the processor
        normalized = state if processor.state_stats is None else normalize(
            state, processor.state_stats, processor.norm_mode, processor.min_norm_scale)
        padded = F.pad(normalized.float(), (0, self.action_dim - normalized.shape[-1]))  # [B, action_dim]
        actions = self.program(pixel_values, image_masks, input_ids, attention_mask, padded, noise)
        robot = actions[..., : processor.action_dim_robot]  # [B, horizon, robot action dims]
        if processor.action_stats is not None:
            robot = unnormalize(robot, processor.action_stats, processor.norm_mode, processor.min_norm_scale)
        if processor.delta_action_mask is not None:
            robot = apply_delta(robot, state[:, None].float(), processor.delta_action_mask, inverse=True)
        return robot.float()


def reference_inputs(processor: Any, batch_size: int, text_length: int, action_horizon: int, action_dim: int,
                     seed: int = 0) -> tuple[np.ndarray, ...]:
    """An input set for the graph built as `ExportedPolicy` builds it (seeded): random frames, the first camera always
    shown and the others by sample (the last sample shows only the first), a prompt through the processor's tokenizer
    (π0.5: with the state in it), a state within the statistics' range, standard normal noise."""
    rng = np.random.default_rng(seed)
    cameras, size = len(processor.camera_names), processor.image_size
    images = rng.integers(0, 256, (batch_size, cameras, size, size, 3), dtype=np.uint8)
    masks = np.ones((batch_size, cameras), bool)
    masks[-1, 1:] = batch_size == 1  # (a batch of several: its last sample shows one camera)
    stats = processor.state_stats
    center = np.zeros(processor.state_dim) if stats is None else (stats.mean if processor.norm_mode == "zscore" else (stats.q01 + stats.q99) / 2)
    spread = np.ones(processor.state_dim) if stats is None else (stats.std if processor.norm_mode == "zscore" else (stats.q99 - stats.q01) / 2)
    states = (center + 0.5 * spread * rng.standard_normal((batch_size, processor.state_dim))).astype(np.float32)
    ids, valid = [], []
    for state in states:
        _, _, sample_ids, sample_mask = processor.encode_state_and_prompt({"state": state, "prompt": REFERENCE_PROMPT})
        ids.append(sample_ids[:text_length])
        valid.append(sample_mask[:text_length])
    images[~masks] = 0
    noise = rng.standard_normal((batch_size, action_horizon, action_dim)).astype(np.float32)
    return images, masks, np.stack(ids).astype(np.int64), np.stack(valid), states, noise


def export_model(
    model_dir: str | Path,
    output_dir: str | Path,
    fmt: str = "onnx",
    batch_size: int = 1,
    dtype: str = "float32",
    device: str = "cpu",
    num_steps: int | None = None,
    text_length: int | None = None,
    opset: int = MIN_OPSET,
    overwrite: bool = False,
    progress: bool = True,
    optimize: bool = True,
) -> Path:
    """Export the model and processor of `model_dir` (`"demo"`: the shipped demo policy) into `output_dir` as `fmt`
    ("onnx" or "pt2"), for `batch_size` samples, `num_steps` Euler steps (default: the folder's recommended, else the
    config's) and prompts of `text_length` tokens (default `max_token_len`), weights in `dtype` on `device` (ONNX:
    `optimize` runs onnxscript's optimizer, see `write_onnx`). Returns the folder. Raises [`ExportError`] (a
    `ValueError`) naming what cannot be exported or did not verify."""
    started = time.monotonic()
    say = logger.info if progress else logger.debug
    model_dir = Path(policy_location(model_dir))
    if fmt not in FORMATS:
        raise ExportError(f"--format must be one of {sorted(FORMATS)}, got {fmt!r}")
    if dtype not in DTYPES:
        raise ExportError(f"--dtype must be one of {list(DTYPES)}, got {dtype!r}")
    if device not in DEVICES:
        raise ExportError(f"--device must be one of {list(DEVICES)}, got {device!r}")
    batch_size = check_int("--batch", batch_size, minimum=1, maximum=MAX_BATCH_SIZE)
    check_int("--opset", opset, minimum=MIN_OPSET)
    _check_exportable(model_dir, fmt, dtype, device)
    files.check_output_dir(output_dir, overwrite)
    files.check_separate(model_dir, output_dir)

    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
    from pi0_torch.processing.processing_pi0 import PI0Processor
    from pi0_torch.runtime.policy_settings import PolicySettings

    settings = PolicySettings.load(model_dir)
    say("loading %s (%s on %s)", model_dir, dtype, device)
    model = PI0ForActionGeneration.from_pretrained(model_dir, dtype=DTYPES[dtype]).to(device).eval()
    processor = PI0Processor.from_pretrained(model_dir)
    config = model.config
    num_steps = num_steps if num_steps is not None else settings.num_steps or config.num_inference_steps
    text_length = config.max_token_len if text_length is None else text_length
    graph = DeployGraph(model, processor, batch_size, num_steps, text_length)
    reference = reference_inputs(processor, batch_size, text_length, config.action_horizon, config.action_dim)
    inputs = tuple(torch.from_numpy(array).to(device) for array in reference)

    say("tracing the sampling (torch.export, %d steps, batch %d, %d prompt tokens)", num_steps, batch_size, text_length)
    expected = _model_actions(model, processor, inputs, num_steps)  # generate_actions' own, the oracle
    # (traced with autograd on, as a deployment may call it: the program's own no_grad region is then recorded)
    exported = torch.export.export(graph, inputs, strict=False)
    bound = ACTION_TOLERANCE[dtype]
    traced = exported.module()(*inputs)
    _verify("the traced program", traced, expected, bound)

    with files.atomic_output_dir(output_dir, overwrite) as staging:
        artifact = staging / FORMATS[fmt]
        if fmt == "onnx":
            say("converting to ONNX (opset %d)", opset)
            external = write_onnx(exported, inputs, artifact, opset, optimize=optimize)
        else:
            say("compiling with AOTInductor for %s (minutes at full size)", device)
            _write_pt2(exported, inputs, artifact)
            external = []
        if fmt == "onnx" and dtype != "float32":  # (onnxruntime's CPU provider has no bfloat16 / float16 kernels)
            verified_by = "the traced program (onnxruntime runs a bfloat16 / float16 graph on its CUDA providers only)"
            produced = traced.detach().float().cpu().numpy()
        else:
            verified_by = f"the {fmt} artifact itself ({'onnxruntime' if fmt == 'onnx' else 'AOTInductor'}, {device})"
            produced = _run_artifact(artifact, fmt, device, reference)
            _verify(f"the {fmt} artifact", torch.from_numpy(produced), expected.cpu(), bound)
        np.savez(staging / REFERENCE_FILE, **dict(zip(INPUT_NAMES, reference)), actions=produced)
        processor.save_pretrained(staging)
        if (model_dir / SETTINGS_FILE).is_file():
            settings.save(staging)
        spec = _deploy_spec(model_dir, staging, model, processor, fmt, dtype, device, batch_size, num_steps,
                            text_length, opset, artifact, external, settings)
        spec["artifact"]["verified_by"] = verified_by
        files.write_text_atomically(staging / DEPLOY_FILE, json.dumps(spec, indent=2, ensure_ascii=False) + "\n")
    output_dir = Path(output_dir).expanduser().absolute()
    size = sum(path.stat().st_size for path in output_dir.iterdir() if path.is_file())
    say("wrote %s (%.1f MB) in %.0f s", output_dir, size / 1e6, time.monotonic() - started)
    return output_dir


def _check_exportable(model_dir: Path, fmt: str, dtype: str, device: str) -> None:
    """Refuse, by name and before loading anything, what this export cannot take."""
    config_path = model_dir / "config.json"
    if not config_path.is_file():
        raise ExportError(f"{model_dir} is not a model folder (no config.json); pi0-torch export takes a folder written "
                          "by pi0-torch convert, train or save_pretrained ('demo': the shipped demo policy)")
    try:
        config = json.loads(config_path.read_text())
        model_type = config.get("model_type")
    except (OSError, ValueError, RecursionError, AttributeError) as error:
        raise ExportError(f"{config_path}: not a readable model config ({first_line(error)})") from None
    if model_type == "pi0_fast_torch":
        raise ExportError(f"{model_dir} is a π0-FAST model: its variable-length token decoding is not exported (π0 and "
                          "π0.5, which sample a fixed number of flow steps, are); serve it with pi0-torch serve")
    if model_type != "pi0_torch":
        raise ExportError(f"{config_path}: model_type {model_type!r}; pi0-torch export takes π0 / π0.5 folders ('pi0_torch')")
    if config.get("quantization_config"):
        raise ExportError(f"{model_dir} is quantized (torchao): export the float model it came from; an engine quantizes "
                          "for its hardware (TensorRT: NVIDIA ModelOpt's INT8 / FP8, docs/deploy.md)")
    if device == "cuda" and not torch.cuda.is_available():
        raise ExportError("--device cuda: no CUDA device is visible to torch here")
    if fmt == "pt2" and device == "cpu" and dtype == "float16":
        raise ExportError("--format pt2 --device cpu --dtype float16: AOTInductor's CPU code has no fast float16 path; "
                          "use float32 or bfloat16 on a CPU")
    if dtype == "float16":
        logger.warning("float16 is exported as asked, but fp16 TensorRT engines of π0.5 were reported to lose the "
                       "policy (0%% LIBERO success): prefer bfloat16, or INT8 / FP8 (docs/deploy.md)")


@torch.no_grad()
def _model_actions(model: nn.Module, processor: Any, inputs: tuple[torch.Tensor, ...], num_steps: int) -> torch.Tensor:
    """What the graph must return for `inputs`, by the model's public path: `generate_actions` on the processor's
    float images and normalized state, then the processor's own unnormalization and delta inverse (numpy)."""
    images, masks, ids, valid, state, noise = inputs
    pixel_values = images.permute(0, 1, 4, 2, 3).float() / 255.0 * 2.0 - 1.0
    raw = state.double().cpu().numpy()
    normalized = raw if processor.state_stats is None else normalize(raw, processor.state_stats, processor.norm_mode,
                                                                     processor.min_norm_scale)
    padded = np.zeros((raw.shape[0], model.config.action_dim), np.float32)
    padded[:, : raw.shape[1]] = normalized
    actions = model.generate_actions(pixel_values, masks, ids, valid, torch.from_numpy(padded).to(state.device),
                                     noise=noise, num_steps=num_steps).float().cpu().numpy()
    robot = actions[..., : processor.action_dim_robot]
    if processor.action_stats is not None:
        robot = unnormalize(robot, processor.action_stats, processor.norm_mode, processor.min_norm_scale)
    if processor.delta_action_mask is not None:
        robot = apply_delta(robot, raw[:, None].astype(np.float32), processor.delta_action_mask, inverse=True)
    return torch.from_numpy(np.asarray(robot, np.float32))


def _verify(what: str, got: torch.Tensor, want: torch.Tensor, bound: float) -> None:
    deviation = action_deviation(got.float().cpu().numpy(), want.float().cpu().numpy())
    if not deviation <= bound:
        raise ExportError(f"{what} deviates from generate_actions by {deviation:.3g} of the largest action (bound {bound:g}); "
                          "nothing was written (please report this with the model's config)")
    logger.debug("%s matches generate_actions within %.2e", what, deviation)


def _decompositions() -> dict[Any, Callable[..., Any]]:
    """Rewrites before the exporter's own decompositions: the engine's `_foreach_add` (several norm scales in one op on
    CUDA), which ONNX has no op for, and the cache writes' `index_copy` into core ATen's `index_put` (ONNX ScatterND;
    translated directly, it is ScatterElements, 20x slower in onnxruntime). Everything else is the exporter's: SDPA
    decomposed to core ATen first made onnxruntime 4x slower (its masked softmax)."""
    table = {op: rule for op, rule in torch.export.default_decompositions().items() if op in (torch.ops.aten.index_copy.default,)}
    table[torch.ops.aten._foreach_add.Scalar] = lambda tensors, value: [tensor + value for tensor in tensors]
    return table


def write_onnx(exported: torch.export.ExportedProgram, inputs: tuple[torch.Tensor, ...], path: Path, opset: int = MIN_OPSET,
               input_names: tuple[str, ...] = INPUT_NAMES, output_names: tuple[str, ...] = OUTPUT_NAMES,
               optimize: bool = True) -> list[str]:
    """An exported program as ONNX at `path` (torch's dynamo exporter at `opset`, then onnxscript's optimizer unless
    `optimize=False`: about half the file and a tenth faster in onnxruntime, for a minute more at export; the weights
    in `<name>.data` beside it above protobuf's 2 GB). Returns the external data files."""
    from pi0_torch.utils.extras import require_extra

    require_extra("export", "pi0-torch export --format onnx")
    program = torch.onnx.export(exported.run_decompositions(_decompositions()), inputs, dynamo=True, opset_version=opset,
                                input_names=list(input_names), output_names=list(output_names), optimize=optimize,
                                verbose=False)
    weights = sum(tensor.numel() * tensor.element_size() for tensor in exported.state_dict.values())
    external = weights > ONNX_PROTOBUF_LIMIT * 0.9
    program.save(str(path), external_data=external)
    return sorted(p.name for p in path.parent.iterdir() if p.name.startswith(path.name + ".")) if external else []


def _write_pt2(exported: torch.export.ExportedProgram, inputs: tuple[torch.Tensor, ...], path: Path) -> None:
    """The program compiled by AOTInductor into a package at `path`, its inputs' names, dtypes and shapes in the
    package's metadata (what a C++ runtime reads with `AOTIModelPackageLoader::get_metadata`, examples/cpp)."""
    metadata = {"pi0_torch": __version__, "inputs": ",".join(INPUT_NAMES), "device": inputs[0].device.type}
    for name, tensor in zip(INPUT_NAMES, inputs):
        metadata[f"{name}.dtype"] = str(tensor.dtype).removeprefix("torch.")
        metadata[f"{name}.shape"] = ",".join(str(size) for size in tensor.shape)
    torch._inductor.aoti_compile_and_package(exported, package_path=str(path),
                                             inductor_configs={"aot_inductor.metadata": metadata})


def _run_artifact(path: Path, fmt: str, device: str, reference: tuple[np.ndarray, ...]) -> np.ndarray:
    """The artifact's actions for the reference inputs, run as a deployment runs it (onnxruntime; the AOTInductor
    loader)."""
    from pi0_torch.deploy.runners import load_runner

    return load_runner(path, fmt, "cuda" if device == "cuda" else "cpu")(reference)


def _deploy_spec(model_dir: Path, staging: Path, model: nn.Module, processor: Any, fmt: str, dtype: str, device: str,
                 batch_size: int, num_steps: int, text_length: int, opset: int, artifact: Path, external: list[str],
                 settings: Any) -> dict[str, Any]:
    config = model.config
    size = processor.image_size
    shapes = {
        "images": ("uint8", [batch_size, config.num_cameras, size, size, 3]),
        "image_masks": ("bool", [batch_size, config.num_cameras]),
        "input_ids": ("int64", [batch_size, text_length]),
        "attention_mask": ("bool", [batch_size, text_length]),
        "state": ("float32", [batch_size, processor.state_dim]),
        "noise": ("float32", [batch_size, config.action_horizon, config.action_dim]),
    }
    weights = sorted(model_dir.glob("model*.safetensors"))
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "exported_by": {"pi0_torch": __version__, "torch": torch.__version__, "python": platform.python_version(),
                        **_exporter_versions(fmt)},
        "artifact": {
            "format": fmt, "file": artifact.name, "external_data": external, "dtype": dtype, "device": device,
            **({"opset": opset} if fmt == "onnx" else {}),
            "sha256": {name: file_sha256(staging / name) for name in (artifact.name, *external)},
        },
        "inputs": [{"name": name, "dtype": shapes[name][0], "shape": shapes[name][1]} for name in INPUT_NAMES],
        "outputs": [{"name": "actions", "dtype": "float32",
                     "shape": [batch_size, config.action_horizon, processor.action_dim_robot]}],
        "model": {
            "type": "pi05" if config.pi05 else "pi0", "batch_size": batch_size, "num_steps": num_steps,
            "action_horizon": config.action_horizon, "action_dim": config.action_dim,
            "parameters": sum(p.numel() for p in model.parameters()),
            "source": str(model_dir), "source_sha256": {path.name: file_sha256(path) for path in [model_dir / "config.json", *weights]},
        },
        "images": {"cameras": list(processor.camera_names), "size": [size, size], "layout": "[B, cameras, H, W, 3] uint8 RGB",
                   "resize": "resize with padding: scale by min(H / h, W / w) (int sizes), PIL bilinear, pad with 0, the "
                             "odd pixel at the bottom / right; float frames rounded to uint8 first",
                   "absent_camera": "zeros, mask False"},
        "prompt": {"tokenizer": "tokenizer.model", "length": text_length, "format": "pi05" if processor.state_in_prompt else "pi0",
                   "bos_id": processor.tokenizer.bos_id, "pad_id": processor.tokenizer.pad_id,
                   "cleaning": "strip; '_' and newlines become spaces",
                   "template": ("Task: {text}, State: {bins};\\nAction: " if processor.state_in_prompt else "{text}\\n")},
        "state": {"dim": processor.state_dim, "value_conversion": processor.value_conversion,
                  "normalization": processor.norm_mode, "in_graph": "normalized and padded to action_dim inside the graph"},
        "actions": {"horizon": config.action_horizon, "dim": processor.action_dim_robot,
                    "delta_action_mask": processor.delta_action_mask, "value_conversion": processor.value_conversion,
                    "in_graph": "unnormalized, delta dims made absolute; value_conversion (if any) is the runtime's"},
        "noise": {"distribution": "standard normal", "scale": settings.noise_scale if settings.noise_scale is not None else 1.0},
        "processor": {"config": "processor_config.json", "norm_stats": "norm_stats.json" if processor.norm_stats else None},
        "policy_settings": SETTINGS_FILE if (staging / SETTINGS_FILE).is_file() else None,
        "reference": REFERENCE_FILE,
    }


def _exporter_versions(fmt: str) -> dict[str, str]:
    if fmt != "onnx":
        return {}
    import onnx
    import onnxruntime
    import onnxscript

    return {"onnx": onnx.__version__, "onnxscript": onnxscript.__version__, "onnxruntime": onnxruntime.__version__}


# ----------------------------------------------------------------------------------------------------------------
# pi0-torch export
# ----------------------------------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="MODEL_DIR", help="a π0 / π0.5 model folder (pi0-torch convert, train or "
                        "save_pretrained), or demo: the policy shipped with the package")
    parser.add_argument("--output-dir", required=True, help="folder to create (absent or empty unless --overwrite)")
    parser.add_argument("--format", choices=sorted(FORMATS), default="onnx", help="onnx (onnxruntime, TensorRT) or pt2 "
                        "(an AOTInductor package for torch._inductor.aoti_load_package or C++; compiled for --device)")
    parser.add_argument("--batch", type=int, default=1, help="samples per call (fixed in the graph)")
    parser.add_argument("--dtype", choices=list(DTYPES), default="float32", help="the weights' dtype (bfloat16 rather "
                        "than float16 for TensorRT: docs/deploy.md)")
    parser.add_argument("--device", choices=DEVICES, default="cpu", help="where to trace (pt2: what it is compiled for)")
    parser.add_argument("--num-steps", type=int, help="Euler steps (fixed in the graph; default: the folder's "
                        "recommended, else the config's)")
    parser.add_argument("--text-length", type=int, help="prompt token slots (default: the config's max_token_len)")
    parser.add_argument("--opset", type=int, default=MIN_OPSET, help=f"ONNX opset (at least {MIN_OPSET})")
    parser.add_argument("--no-optimize", dest="optimize", action="store_false", help="ONNX: skip onnxscript's "
                        "optimizer (about half the file and a tenth faster in onnxruntime, for minutes at full size)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir written by pi0-torch")


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        export_model(args.model, args.output_dir, args.format, args.batch, args.dtype, args.device, args.num_steps,
                     args.text_length, args.opset, args.overwrite, optimize=args.optimize)
    except (ValueError, OSError) as error:
        logger.error("pi0-torch export: %s", first_line(error))
        return 1
    return 0

