"""How π0-family checkpoints load and save: `PI0PreTrainedModel`, transformers' `PreTrainedModel` refusing any checkpoint
whose tensors do not match the model (never a silent random init), with openpi's weight initialisation."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn
from transformers import PreTrainedModel

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.layers import AdaRMSNorm, RMSNorm
from pi0_torch.models.vision import is_inside_vision_tower
from pi0_torch.utils import files
from pi0_torch.utils.quiet import transformers_progress
from pi0_torch.utils.validation import check_pretrained_location, hub_errors


class PI0PreTrainedModel(PreTrainedModel):
    config_class = PI0Config
    config: PI0Config
    base_model_prefix = "pi0"
    main_input_name = "pixel_values"
    supports_gradient_checkpointing = True
    _no_split_modules = ["JointDecoderLayer", "SiglipEncoderLayer"]
    _supports_sdpa = True

    @torch.no_grad()
    def _init_weights(self, module: nn.Module) -> None:
        std = 0.02
        if isinstance(module, AdaRMSNorm):
            # openpi initialises the adaRMS Dense to zero: unit scale, no shift, closed residual gates.
            nn.init.zeros_(module.modulation.weight)
            nn.init.zeros_(module.modulation.bias)
        elif isinstance(module, RMSNorm):
            nn.init.zeros_(module.weight)
        elif isinstance(module, nn.Linear) and not is_inside_vision_tower(self, module):
            nn.init.normal_(module.weight, std=std)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding) and not is_inside_vision_tower(self, module):
            nn.init.normal_(module.weight, std=std)
        else:
            super()._init_weights(module)

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: Any, *args: Any, **kwargs: Any) -> Any:
        """`PreTrainedModel.from_pretrained` that refuses a checkpoint whose tensors do not match the model.

        transformers only warns about missing or unexpected weights and initialises the missing ones randomly; a
        policy with silently random weights is worse than no policy, so any missing, unexpected or mis-shaped
        tensor raises `ValueError` naming them. `ignore_mismatched_sizes=True` is the explicit opt-in to
        re-initialise mis-shaped tensors (e.g. fine-tuning with another `action_dim`). Quiet unless `verbose=True`
        (transformers' "Loading weights" bar).

        A local folder must hold `config.json` (unless a `config` is given); a path that is neither a folder nor a hub
        id `namespace/name` is refused at once, without trying the hub (see `pi0_torch.utils.validation.is_hub_id`).
        A weight stored as integers, booleans or 8-bit floats for a floating-point parameter is refused too, by name
        (transformers would cast it silently).
        """
        config_file = None if kwargs.get("config") else f"{kwargs['subfolder']}/config.json" if kwargs.get("subfolder") else "config.json"
        check_pretrained_location(pretrained_model_name_or_path, config_file, "model")
        folder = Path(str(pretrained_model_name_or_path)) / (kwargs.get("subfolder") or "")
        local = folder.is_dir()  # (else a hub id: transformers' own checks)
        if local:
            _refuse_pickled_weights(folder)
            _check_shard_index(folder)
            _check_quantization(folder, kwargs.get("quantization_config"))
        want_info = kwargs.pop("output_loading_info", False)
        allow_mismatched = kwargs.pop("ignore_mismatched_sizes", False)  # an explicit opt-in to re-initialise them
        with hub_errors(pretrained_model_name_or_path, "model"), transformers_progress(kwargs.pop("verbose", False)):
            model, info = super().from_pretrained(
                pretrained_model_name_or_path, *args, output_loading_info=True, ignore_mismatched_sizes=True, **kwargs
            )
        problems = {
            "missing": sorted(info.get("missing_keys", ())),
            "unexpected": sorted(info.get("unexpected_keys", ())),
            "mis-shaped": [] if allow_mismatched else sorted(_describe_mismatch(item) for item in info.get("mismatched_keys", ())),
        }
        problems = {kind: names for kind, names in problems.items() if names}
        wrong_kind = _non_floating_weights(folder, model) if local else []
        if wrong_kind:
            problems["not floating-point"] = wrong_kind
        if problems:
            details = "; ".join(f"{kind}: {', '.join(names[:10])}{' ...' if len(names) > 10 else ''}" for kind, names in problems.items())
            if any(name.endswith(".lora_a") for name in problems.get("unexpected", ())):
                details += (" (a checkpoint of a LoRA run, adapters not merged: `pi0-torch consolidate CHECKPOINT "
                            "--output-dir DIR` writes the model folder)")
            raise ValueError(f"checkpoint {pretrained_model_name_or_path} does not match {cls.__name__}({model.config.model_type}): {details}")
        return (model, info) if want_info else model

    def save_pretrained(self, save_directory: Any, *args: Any, verbose: bool = False, **kwargs: Any) -> Any:
        """`PreTrainedModel.save_pretrained`, quiet unless `verbose=True` (transformers' "Writing model shards" bar).
        The weight files get the permissions of the folder's other files (safetensors would write them 0600)."""
        with transformers_progress(verbose):
            result = super().save_pretrained(save_directory, *args, **kwargs)
        for weights in Path(save_directory).glob("model*.safetensors"):
            files.give_default_mode(weights)
        return result


def _non_floating_weights(folder: Path, model: nn.Module) -> list[str]:
    """The tensors of a local checkpoint's safetensors files that are stored as integers, booleans or 8-bit floats
    where the model has a floating-point parameter or buffer (`name (I32)`): transformers casts them silently (the demo
    policy saved as int32 loaded with 560 of 272,947 parameters non-zero and returned normal-looking actions)."""
    from safetensors import safe_open

    floating = {name for name, tensor in model.state_dict().items() if tensor.is_floating_point()}
    found = []
    for path in sorted(folder.glob("*.safetensors")):
        with safe_open(str(path), "pt") as checkpoint:
            for name in checkpoint.keys():
                dtype = checkpoint.get_slice(name).get_dtype()
                if name in floating and (dtype == "BOOL" or dtype[0] in "IU" or dtype.startswith("F8")):  # (not BF16)
                    found.append(f"{name} ({dtype})")
    return sorted(found)


def _refuse_pickled_weights(folder: Path) -> None:
    """A local folder whose weights are only pickled (`pytorch_model.bin`, `*.pt`): unpickling runs arbitrary code, and
    torch's refusal recommends exactly that (`weights_only=False`), so it is refused first, in one line."""
    if any(folder.glob("*.safetensors")):
        return
    pickled = sorted(path.name for pattern in ("*.bin", "*.pt", "*.pth", "*.ckpt") for path in folder.glob(pattern))
    if pickled:
        raise ValueError(f"{folder} holds only pickled weights ({', '.join(pickled[:3])}); pickled weights are not loaded "
                         "(unpickling can run any code): convert them to safetensors where you trust the file, e.g. "
                         "safetensors.torch.save_file(torch.load(path, weights_only=True), 'model.safetensors')")


def _check_shard_index(folder: Path) -> None:
    """A local folder's `model.safetensors.index.json` names shards inside the folder: a shard path that is absolute,
    climbs out (`..`) or leads out through a link would load another folder's weights (or any file) as this model's."""
    index = folder / "model.safetensors.index.json"
    if not index.is_file():
        return
    try:
        weight_map = json.loads(index.read_text()).get("weight_map")
    except (OSError, ValueError, AttributeError, RecursionError) as error:
        raise ValueError(f"{index} is not a shard index (a JSON object with a weight_map): {error}") from None
    if not isinstance(weight_map, dict) or not all(isinstance(shard, str) for shard in weight_map.values()):
        raise ValueError(f"{index}: weight_map must map each tensor name to a shard file name")
    inside = folder.resolve()
    for shard in sorted(set(weight_map.values())):
        path = Path(shard)
        if path.is_absolute() or ".." in path.parts or not (folder / path).resolve().is_relative_to(inside):
            raise ValueError(f"{index} names the shard {shard!r} outside the model folder; shards are loaded only "
                             "from the folder itself")


def is_quantized(directory: str | Path) -> bool:
    """Whether a model folder's `config.json` records a quantization (written by `save_pretrained` of a quantized
    model)."""
    path = Path(directory) / "config.json"
    try:
        return bool(json.loads(path.read_text()).get("quantization_config"))
    except (OSError, ValueError, AttributeError, RecursionError):
        return False


def _check_quantization(folder: Path, asked: Any) -> None:
    """A quantized folder (its `config.json` records a `quantization_config`) loads with torchao installed; quantizing
    it again is refused. Both in one line, before transformers tries."""
    from pi0_torch.utils.extras import require_extra

    if not is_quantized(folder):
        return
    if asked is not None:
        raise ValueError(f"{folder} is quantized already (its config.json records a quantization_config); load it as it "
                         "is, or quantize the float model it came from")
    require_extra("quant", f"{folder} (a quantized model)", modules=("torchao",))


def _describe_mismatch(item: Any) -> str:
    """transformers reports a mismatch as (name, checkpoint shape, model shape)."""
    if isinstance(item, (tuple, list)) and len(item) == 3:
        name, checkpoint_shape, model_shape = item
        return f"{name} (checkpoint {tuple(checkpoint_shape)}, model {tuple(model_shape)})"
    return str(item)
