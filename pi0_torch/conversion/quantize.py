"""Quantized π0 / π0.5 / π0-FAST models with torchao, the transformers way: `from_pretrained(folder,
quantization_config=torchao_config("int8"))` quantizes while loading, `save_pretrained` writes the quantized weights
(safetensors) with the quantization in `config.json`, and loading that folder gives the quantized model back.
`pi0-torch quantize MODEL_DIR --output-dir DIR --scheme int8` does both and copies the processor files;
`pi0-torch convert ... --quantize int8` converts and quantizes in one command.

Which layers: the decoder projections of both Gemma experts (q/k/v, o, gate/up, down) and SigLIP's attention and MLP
projections (`GROUPS`; `--modules` chooses among them). Kept in their dtype, always: the embeddings, the norms (π0.5's
adaRMS modulations too), the patch embedding, the image projection, and the action, state and time projections
(`KEPT_MODULES`): small, read every step, and where quantization studies of VLAs found the error.

Schemes (`SCHEMES`), by where they run:

| scheme | torchao config | runs on |
|---|---|---|
| `int8` | `Int8WeightOnlyConfig` | CPU, CUDA |
| `int8-dynamic` | `Int8DynamicActivationInt8WeightConfig` (activations quantized per call) | CPU, CUDA |
| `int4` | CUDA: `Int4WeightOnlyConfig` (tile-packed, groups of 128, bf16; layers of other widths kept); CPU: `IntxWeightOnlyConfig` (int4 in groups, stored one value per byte) | CPU, CUDA |
| `fp8` | `Float8DynamicActivationFloat8WeightConfig` (per row) | CUDA, compute capability >= 8.9 |
| `fp8-weight` | `Float8WeightOnlyConfig` | CPU, CUDA |

A scheme the device cannot run is refused by name, saying what runs there instead.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pi0_torch.models.pretrained import is_quantized  # noqa: F401 (re-exported: a quantized folder)
from pi0_torch.utils.extras import require_extra

logger = logging.getLogger(__name__)

SCHEMES = ("int8", "int8-dynamic", "int4", "fp8", "fp8-weight")
DYNAMIC_SCHEMES = ("int8-dynamic", "fp8")  # activations quantized in each call
# module groups that may be quantized: name -> the modules' name pattern (transformers' `modules_to_not_convert` syntax)
GROUPS = {"vlm": "layers.*.vlm", "expert": "layers.*.expert", "vision": "vision_tower"}
DEFAULT_GROUPS = ("vlm", "expert", "vision")
KEPT_MODULES = (
    "embed_tokens", "image_projection", "action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in",
    "action_time_mlp_out", "time_mlp_in", "time_mlp_out", "modulation", "lm_head",
)
INT4_GROUPS = (128, 64, 32, 16, 8)  # the CPU int4 scheme's group size: the largest that divides every quantized input width
CUDA_INT4_GROUP = 128  # CUDA's tile-packed int4 (tinygemm): groups of 128 input features
PROCESSOR_FILES = ("processor_config.json", "norm_stats.json", "tokenizer.model", "policy_settings.json",
                   "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json")


class QuantizationError(ValueError):
    """A scheme, device or folder that cannot be quantized: one line naming it and what runs instead."""


def check_scheme(scheme: str, device: Any = "cpu") -> None:
    """Refuse, by name, a scheme this package does not know or `device` cannot run."""
    import torch

    if scheme not in SCHEMES:
        raise QuantizationError(f"--scheme must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    device = torch.device(device)
    if device.type not in ("cpu", "cuda"):
        raise QuantizationError(f"quantized models run on cpu or cuda, not {device.type}")
    if scheme == "fp8":
        capability = torch.cuda.get_device_capability(device) if device.type == "cuda" else None
        if capability is None or capability < (8, 9):
            where = f"compute capability {capability[0]}.{capability[1]}" if capability else "a CPU"
            raise QuantizationError(f"--scheme fp8 (float8 activations and weights) runs on CUDA GPUs of compute "
                                    f"capability 8.9 or more (Ada, Hopper); this is {where}: use fp8-weight or int8 there")


def torchao_config(scheme: str, device: Any = "cpu", modules: Sequence[str] = DEFAULT_GROUPS,
                   widths: Mapping[str, int] | None = None) -> Any:
    """transformers' `TorchAoConfig` of `scheme` for `device`, quantizing the module `groups` `modules` (of `GROUPS`)
    and keeping everything else. `widths`: the input width of each layer it would quantize, by name
    (`quantized_widths`); int4 needs them: on a CPU its group size is the largest of `INT4_GROUPS` that divides them all
    (without them, 16: it divides every width of the released π0 / π0.5 models, SigLIP's MLP being 4304 wide); on
    CUDA, whose tile-packed int4 takes groups of 128, a layer whose width is no multiple of 128 is kept."""
    require_extra("quant", "a quantized model", modules=("torchao",))
    import torch
    from torchao.quantization import (Float8DynamicActivationFloat8WeightConfig, Float8WeightOnlyConfig,
                                      Int4WeightOnlyConfig, Int8DynamicActivationInt8WeightConfig, Int8WeightOnlyConfig,
                                      IntxWeightOnlyConfig)
    from torchao.quantization.granularity import PerGroup, PerRow
    from transformers import TorchAoConfig

    check_scheme(scheme, device)
    unknown = sorted(set(modules) - set(GROUPS))
    if unknown or not modules:
        raise QuantizationError(f"--modules must name some of {', '.join(GROUPS)}, got {list(modules)}")
    device = torch.device(device)
    kept = [*KEPT_MODULES, *(GROUPS[group] for group in GROUPS if group not in modules)]
    if scheme == "int8":
        config: Any = Int8WeightOnlyConfig()
    elif scheme == "int8-dynamic":
        config = Int8DynamicActivationInt8WeightConfig()
    elif scheme == "int4" and device.type == "cuda":
        config = Int4WeightOnlyConfig(group_size=CUDA_INT4_GROUP, int4_packing_format="tile_packed_to_4d")
        unpackable = sorted(name for name, width in (widths or {}).items() if width % CUDA_INT4_GROUP)
        if unpackable:
            logger.info("int4 on CUDA packs groups of %d input features: %d layers of other widths stay in their dtype "
                        "(%s, ...)", CUDA_INT4_GROUP, len(unpackable), unpackable[0])
        kept += [re.escape(name) for name in unpackable]
    elif scheme == "int4":
        values = sorted(set((widths or {}).values()))
        group = next((size for size in INT4_GROUPS if all(width % size == 0 for width in values)), None) if values else 16
        if group is None:
            raise QuantizationError(f"--scheme int4 on a CPU quantizes in groups of 8 to 128 input features; these layers' "
                                    f"widths {values} share none: use int8")
        config = IntxWeightOnlyConfig(weight_dtype=torch.int4, granularity=PerGroup(group))
    elif scheme == "fp8":
        config = Float8DynamicActivationFloat8WeightConfig(granularity=PerRow())
    else:
        config = Float8WeightOnlyConfig()
    return TorchAoConfig(config, modules_to_not_convert=kept)


def quantize_folder(model_dir: str | Path, output_dir: str | Path, scheme: str = "int8", device: str = "cpu",
                    modules: Sequence[str] = DEFAULT_GROUPS, overwrite: bool = False) -> Path:
    """Load the model of `model_dir` quantized with `scheme` for `device` and write it (with the processor files and
    `policy_settings.json`) into `output_dir`, whole or not at all. Refuses a folder that is quantized already."""
    import torch

    from pi0_torch.shipped_policy import policy_location
    from pi0_torch.utils import files

    model_dir = Path(policy_location(model_dir))
    if not (model_dir / "config.json").is_file():
        raise QuantizationError(f"{model_dir} is not a model folder (no config.json)")
    if is_quantized(model_dir):
        raise QuantizationError(f"{model_dir} is quantized already (its config.json records a quantization_config); "
                                "quantize the float model it came from")
    check_scheme(scheme, device)
    files.check_output_dir(output_dir, overwrite)
    files.check_separate(model_dir, output_dir)
    model_class = _model_class(model_dir)
    # (the dtype the kernels take: CUDA's int4 and float8 linears compute in bf16; otherwise the folder's own)
    dtype = torch.bfloat16 if scheme == "fp8" or (scheme == "int4" and torch.device(device).type == "cuda") else None
    widths = quantized_widths(model_dir, modules) if scheme == "int4" else None  # (int4's groups)
    config = torchao_config(scheme, device, modules, widths)
    model = model_class.from_pretrained(model_dir, quantization_config=config, dtype=dtype, device_map=device)
    with files.atomic_output_dir(output_dir, overwrite) as staging:
        model.save_pretrained(staging)
        for name in PROCESSOR_FILES:
            if (model_dir / name).is_file():
                shutil.copy2(model_dir / name, staging / name)
        for folder in ("fast_tokenizer",):  # (π0-FAST's action tokenizer)
            if (model_dir / folder).is_dir():
                shutil.copytree(model_dir / folder, staging / folder)
    return Path(output_dir).expanduser().absolute()


def quantized_widths(model_dir: str | Path, modules: Sequence[str] = DEFAULT_GROUPS) -> dict[str, int]:
    """The input width of each linear layer `torchao_config(..., modules)` would quantize in the model of `model_dir`,
    by name (the model built from its config on the meta device; no weights are read)."""
    import torch
    from torch import nn
    from transformers.quantizers.quantizers_utils import should_convert_module

    model_class = _model_class(model_dir)
    with torch.device("meta"):
        model = model_class(model_class.config_class.from_pretrained(model_dir))
    kept = [*KEPT_MODULES, *(GROUPS[group] for group in GROUPS if group not in modules)]
    return {name: module.in_features for name, module in model.named_modules()
            if isinstance(module, nn.Linear) and should_convert_module(name, kept)}


def _model_class(model_dir: str | Path) -> Any:
    """The model class of the folder `model_dir`: π0-FAST's or π0 / π0.5's."""
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
    from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration

    model_type = json.loads((Path(model_dir) / "config.json").read_text()).get("model_type")
    return PI0FastForActionGeneration if model_type == "pi0_fast_torch" else PI0ForActionGeneration


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="MODEL_DIR", help="a model folder (π0, π0.5 or π0-FAST), or demo")
    parser.add_argument("--output-dir", required=True, help="folder to create (absent or empty unless --overwrite)")
    parser.add_argument("--scheme", choices=SCHEMES, default="int8", help="int8 (weight-only; CPU and CUDA), "
                        "int8-dynamic, int4, fp8 (CUDA, compute capability 8.9+), fp8-weight")
    parser.add_argument("--device", default="cpu", help="where the quantized model will run (cpu or cuda: int4 packs "
                        "its weights for one of them)")
    parser.add_argument("--modules", default=",".join(DEFAULT_GROUPS), help=f"comma list of the layer groups to "
                        f"quantize: {', '.join(GROUPS)} (embeddings, norms and the action / state / time projections "
                        "are always kept)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --output-dir written by pi0-torch")


def run(args: argparse.Namespace) -> int:
    from pi0_torch.utils.extras import MissingExtraError
    from pi0_torch.utils.validation import first_line

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        folder = quantize_folder(args.model, args.output_dir, args.scheme, args.device,
                                 [name for name in args.modules.split(",") if name], args.overwrite)
    except MissingExtraError as error:
        logger.error("%s", error.message("pi0-torch quantize"))
        return 1
    except (ValueError, OSError) as error:
        logger.error("pi0-torch quantize: %s", first_line(error))
        return 1
    size = sum(path.stat().st_size for path in folder.iterdir() if path.is_file())
    logger.info("wrote %s (%s, %.1f MB)", folder, args.scheme, size / 1e6)
    return 0
