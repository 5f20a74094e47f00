"""LeRobot and transformers π0 / π0.5 folders (PyTorch, Hugging Face layout) <-> pi0-torch folders:
[`convert_hf_checkpoint`] (`pi0-torch convert --from lerobot|transformers`), [`export_to_transformers`] (`--from
pi0-torch --to transformers`, π0 only) and [`transformers_pi0_inputs`] (our model inputs for transformers'
`PI0ForConditionalGeneration`, for side-by-side comparisons).

Keys of either layout map to ours by rules ([`_hf_key_target`]): q/k/v and gate/up are separate there and fused
here. The folder is written by `pi0_torch.conversion.output_folder`.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open

from pi0_torch.conversion.orbax_reader import first_line
from pi0_torch.conversion.output_folder import (
    DEFAULT_MAX_SHARD_BYTES,
    DTYPES,
    INDEX_FILE,
    SINGLE_FILE,
    ConversionError,
    ConversionResult,
    ShardedSafetensorsWriter,
    build_processor,
    processor_inputs_missing,
    check_disk_space,
    check_output,
    check_tokenizer,
    checked_arguments,
    name_list,
    planned_shapes,
    progress_bar,
    read_norm_stats,
    save_config,
    write_processor_files,
)
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.processing.normalization import NormStats
from pi0_torch.utils.files import atomic_output_dir
from pi0_torch.utils.quiet import transformers_progress

CONFIG_FILE = "config.json"

# One Gemma decoder layer in the Hugging Face layout -> (our name inside `layers.{i}.{vlm|expert}`, part, parts).
# q/k/v and gate/up are separate there and fused (concatenated along the output rows, in this order) here.
_HF_LAYER: dict[str, tuple[str, int, int]] = {
    "self_attn.q_proj.weight": ("qkv_proj.weight", 0, 3),
    "self_attn.k_proj.weight": ("qkv_proj.weight", 1, 3),
    "self_attn.v_proj.weight": ("qkv_proj.weight", 2, 3),
    "self_attn.o_proj.weight": ("o_proj.weight", 0, 1),
    "mlp.gate_proj.weight": ("gate_up_proj.weight", 0, 2),
    "mlp.up_proj.weight": ("gate_up_proj.weight", 1, 2),
    "mlp.down_proj.weight": ("down_proj.weight", 0, 1),
    "input_layernorm.weight": ("attn_norm.weight", 0, 1),
    "post_attention_layernorm.weight": ("mlp_norm.weight", 0, 1),
    # π0.5 adaRMS (openpi's PyTorch Gemma, used by LeRobot): Linear cond -> [scale | shift | gate]
    "input_layernorm.dense.weight": ("attn_norm.modulation.weight", 0, 1),
    "input_layernorm.dense.bias": ("attn_norm.modulation.bias", 0, 1),
    "post_attention_layernorm.dense.weight": ("mlp_norm.modulation.weight", 0, 1),
    "post_attention_layernorm.dense.bias": ("mlp_norm.modulation.bias", 0, 1),
}
_HEADS = ("state_proj", "action_in_proj", "action_time_mlp_in", "action_time_mlp_out", "action_out_proj", "time_mlp_in", "time_mlp_out")

# Key prefixes: LeRobot wraps everything in `model.`; openpi's PyTorch port and transformers' saved files use
# `paligemma_with_expert.{paligemma,gemma_expert}`; transformers' modules are `model.vlm` / `model.dit`.
_VLM = r"(?:model\.)?(?:paligemma_with_expert\.paligemma\.(?:model\.)?|vlm\.)"
_EXPERT = r"(?:model\.)?(?:paligemma_with_expert\.gemma_expert\.(?:model\.)?|dit\.)"
_LM = r"language_model\.(?:model\.)?"


@dataclass(frozen=True)
class _Target:
    name: str  # our parameter
    part: int  # position among the fused parts
    parts: int


_DROP_TIED_EMBEDDING = "tied LM head (copy of the text embedding)"
_HF_RULES: list[tuple[re.Pattern[str], Callable[[re.Match[str]], _Target | str]]] = [
    (re.compile(_VLM + r"vision_tower\.(?:vision_model\.)?(.+)"), lambda m: _Target(f"vision_tower.{m[1]}", 0, 1)),
    (re.compile(_VLM + r"multi_modal_projector\.linear\.(weight|bias)"), lambda m: _Target(f"image_projection.{m[1]}", 0, 1)),
    (re.compile(_VLM + _LM + r"embed_tokens\.weight"), lambda m: _Target("embed_tokens.weight", 0, 1)),
    (re.compile(_VLM + r"(?:language_model\.)?lm_head\.weight"), lambda m: _DROP_TIED_EMBEDDING),
    (re.compile(_VLM + _LM + r"layers\.(\d+)\.(.+)"), lambda m: _layer_target(int(m[1]), "vlm", m[2])),
    (re.compile(_VLM + _LM + r"norm\.weight"), lambda m: _Target("vlm_final_norm.weight", 0, 1)),
    (re.compile(_EXPERT + r"(?:embed_tokens|lm_head)\.weight"), lambda m: "unused action-expert embedding / LM head"),
    (re.compile(_EXPERT + r"layers\.(\d+)\.(.+)"), lambda m: _layer_target(int(m[1]), "expert", m[2])),
    (re.compile(_EXPERT + r"norm\.weight"), lambda m: _Target("expert_final_norm.weight", 0, 1)),
    (re.compile(_EXPERT + r"norm\.dense\.(weight|bias)"), lambda m: _Target(f"expert_final_norm.modulation.{m[1]}", 0, 1)),
    (re.compile(r"(?:model\.)?(?:embed_action_time\.)?(" + "|".join(_HEADS) + r")\.(weight|bias)"), lambda m: _Target(f"{m[1]}.{m[2]}", 0, 1)),
    (re.compile(r"(?:normalize_inputs|normalize_targets|unnormalize_outputs)\..+"), lambda m: "LeRobot normalization buffer"),
]


def _layer_target(layer: int, expert: str, rest: str) -> _Target | str:
    if rest not in _HF_LAYER:
        return ""
    name, part, parts = _HF_LAYER[rest]
    return _Target(f"layers.{layer}.{expert}.{name}", part, parts)


def _hf_key_target(key: str) -> _Target | str:
    """Where a LeRobot / transformers tensor goes: a `_Target`, a reason to drop it, or "" when unknown."""
    for pattern, target in _HF_RULES:
        match = pattern.fullmatch(key)
        if match:
            return target(match)
    return ""


def _safetensors_files(folder: Path) -> list[Path]:
    """The weight files of a Hugging Face-style folder: those of `model.safetensors.index.json`, or `model.safetensors`."""
    index = folder / INDEX_FILE
    if index.is_file():
        try:
            weight_map = json.loads(index.read_text())["weight_map"]
        except (ValueError, KeyError, TypeError) as error:
            raise ConversionError(f"unreadable {index}: {error}") from None
        files = [folder / name for name in sorted(set(weight_map.values()))]
    else:
        files = [folder / SINGLE_FILE]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise ConversionError(f"{folder} has no safetensors weights: missing {', '.join(missing)}")
    return files


@dataclass
class _HFWeights:
    """The tensors of a Hugging Face-layout π0 folder, grouped by the parameter of ours they make up."""

    folder: Path
    files: dict[str, Path]  # source key -> file
    shapes: dict[str, tuple[int, ...]]  # source key -> shape
    sources: dict[str, list[str | None]]  # our name -> source keys in part order
    dropped: list[str]

    @classmethod
    def scan(cls, folder: Path) -> _HFWeights:
        files: dict[str, Path] = {}
        shapes: dict[str, tuple[int, ...]] = {}
        for path in _safetensors_files(folder):
            try:
                with safe_open(path, framework="pt") as handle:
                    for key in handle.keys():
                        files[key] = path
                        shapes[key] = tuple(handle.get_slice(key).get_shape())
            except Exception as error:  # safetensors raises its own SafetensorError on malformed files
                raise ConversionError(f"cannot read {path}: {first_line(error)}") from None
        sources: dict[str, list[str | None]] = {}
        dropped, unknown, tied = [], [], []
        for key in files:
            target = _hf_key_target(key)
            if isinstance(target, _Target):
                parts = sources.setdefault(target.name, [None] * target.parts)
                if parts[target.part] is not None:
                    raise ConversionError(f"{folder}: both {parts[target.part]} and {key} map to {target.name}")
                parts[target.part] = key
            elif target == _DROP_TIED_EMBEDDING:
                tied.append(key)
            elif target:
                dropped.append(key)
            else:
                unknown.append(key)
        if unknown:
            raise ConversionError(f"{folder}: tensors not part of a π0/π0.5 model: {name_list(sorted(unknown))}")
        if "embed_tokens.weight" not in sources and tied:  # hub files keep only the tied LM head
            sources["embed_tokens.weight"] = [tied.pop()]
        dropped += tied
        incomplete = [f"{name} (lacks part {parts.index(None)})" for name, parts in sources.items() if None in parts]
        if incomplete:
            raise ConversionError(f"{folder}: incomplete fused parameters: {name_list(sorted(incomplete))}")
        return cls(folder, files, shapes, sources, sorted(dropped))

    def fused_shape(self, name: str) -> tuple[int, ...]:
        shapes = [self.shapes[key] for key in self.sources[name] if key is not None]
        return (sum(s[0] for s in shapes), *shapes[0][1:])

    def tensor(self, name: str, handles: Mapping[Path, Any]) -> torch.Tensor:
        parts = [handles[self.files[key]].get_tensor(key) for key in self.sources[name] if key is not None]
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=0)


# Released Gemma variants, as LeRobot names them in its config (heads, kv heads, head dim).
_GEMMA_VARIANTS = {"gemma_2b": (8, 1, 256), "gemma_300m": (8, 1, 256)}
_SIGLIP_HEADS = {1152: 16}  # So400m/14


def _hf_config_hints(folder: Path) -> dict[str, Any]:
    """PI0Config fields that the weights do not determine, from a transformers or LeRobot `config.json`."""
    path = folder / CONFIG_FILE
    if not path.is_file():
        return {}
    try:
        raw = json.loads(path.read_text())
    except ValueError as error:
        raise ConversionError(f"unreadable {path}: {error}") from None
    hints: dict[str, Any] = {}
    if isinstance(raw.get("vlm_config"), dict):  # transformers PI0Config
        text, vision, dit = raw["vlm_config"].get("text_config", {}), raw["vlm_config"].get("vision_config", {}), raw.get("dit_config", {})
        for ours, theirs in (("num_attention_heads", "num_attention_heads"), ("num_key_value_heads", "num_key_value_heads"), ("head_dim", "head_dim")):
            if theirs in text:
                hints[ours] = text[theirs]
                if theirs in dit and dit[theirs] != text[theirs]:
                    raise ConversionError(f"{path}: the action expert's {theirs} ({dit[theirs]}) differs from the VLM's ({text[theirs]}); π0 shares them")
        if "num_attention_heads" in vision:
            hints["vision_num_heads"] = vision["num_attention_heads"]
        if "rms_norm_eps" in text:
            hints["rms_norm_eps"] = text["rms_norm_eps"]
        theta = (text.get("rope_parameters") or {}).get("rope_theta", text.get("rope_theta"))
        if theta is not None:
            hints["rope_theta"] = theta
    else:  # LeRobot policy config
        variant = _GEMMA_VARIANTS.get(raw.get("paligemma_variant", ""))
        if variant:
            hints.update(zip(("num_attention_heads", "num_key_value_heads", "head_dim"), variant))
        if "tokenizer_max_length" in raw:
            hints["max_token_len"] = raw["tokenizer_max_length"]
    renames = {
        "chunk_size": "action_horizon",
        "num_inference_steps": "num_inference_steps",
        "num_steps": "num_inference_steps",
        "time_sampling_beta_alpha": "time_beta_alpha",
        "time_sampling_beta_beta": "time_beta_beta",
        "time_sampling_scale": "time_scale",
        "time_sampling_offset": "time_offset",
        "min_period": "time_min_period",
        "max_period": "time_max_period",
    }
    hints.update({ours: raw[theirs] for theirs, ours in renames.items() if raw.get(theirs) is not None})
    return hints


def _config_from_hf(weights: _HFWeights, hints: Mapping[str, Any], overrides: Mapping[str, Any]) -> PI0Config:
    def shape(name: str) -> tuple[int, ...]:
        if name not in weights.sources:
            raise ConversionError(f"{weights.folder}: not a π0/π0.5 checkpoint, no tensor for {name}")
        return weights.fused_shape(name)

    def count(pattern: str) -> int:
        return 1 + max((int(m[1]) for name in weights.sources if (m := re.fullmatch(pattern, name))), default=-1)

    settings = {**hints, **overrides}
    width, _, patch, _ = shape("vision_tower.embeddings.patch_embedding.weight")
    q_rows = weights.shapes[weights.sources["layers.0.vlm.qkv_proj.weight"][0]][0] if "layers.0.vlm.qkv_proj.weight" in weights.sources else 0
    k_rows = weights.shapes[weights.sources["layers.0.vlm.qkv_proj.weight"][1]][0] if q_rows else 0
    kv_heads = settings.get("num_key_value_heads", 1)
    head_dim = settings.get("head_dim", k_rows // kv_heads if k_rows else 0)
    vision_heads = settings.get("vision_num_heads", _SIGLIP_HEADS.get(width))
    if vision_heads is None:
        raise ConversionError(f"{weights.folder}: cannot tell the SigLIP head count of width {width} from the weights; pass vision_num_heads")
    vocab, vlm_width = shape("embed_tokens.weight")
    inferred = dict(
        pi05="time_mlp_in.weight" in weights.sources,
        image_size=math.isqrt(shape("vision_tower.embeddings.position_embedding.weight")[0]) * patch,
        patch_size=patch,
        vision_hidden_size=width,
        vision_intermediate_size=shape("vision_tower.encoder.layers.0.mlp.fc1.weight")[0],
        vision_num_layers=count(r"vision_tower\.encoder\.layers\.(\d+)\.layer_norm1\.weight"),
        vision_num_heads=vision_heads,
        vlm_hidden_size=vlm_width,
        vlm_intermediate_size=shape("layers.0.vlm.gate_up_proj.weight")[0] // 2,
        expert_hidden_size=shape("layers.0.expert.o_proj.weight")[0],
        expert_intermediate_size=shape("layers.0.expert.gate_up_proj.weight")[0] // 2,
        num_hidden_layers=count(r"layers\.(\d+)\.vlm\.o_proj\.weight"),
        num_attention_heads=q_rows // head_dim if head_dim else 0,
        num_key_value_heads=kv_heads,
        head_dim=head_dim,
        vocab_size=vocab,
        action_dim=shape("action_in_proj.weight")[1],
    )
    try:
        return PI0Config(**{**inferred, **settings})
    except (ValueError, TypeError, ZeroDivisionError) as error:
        raise ConversionError(f"{weights.folder}: cannot build a config from these weights: {error}") from None


def convert_hf_checkpoint(
    input_dir: str | os.PathLike[str],
    output_dir: str | os.PathLike[str],
    *,
    dtype: str = "float32",
    tokenizer: str | os.PathLike[str] | None = None,
    norm_stats: str | os.PathLike[str] | None = None,
    processor_options: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    max_shard_bytes: int | str = DEFAULT_MAX_SHARD_BYTES,
    progress: bool = False,
    **config_overrides: Any,
) -> ConversionResult:
    """Import a LeRobot (`lerobot/pi0_base`-style) or transformers `PI0ForConditionalGeneration` folder.

    Keys of either layout (LeRobot's `model.paligemma_with_expert...`, openpi's PyTorch port, transformers' saved
    and in-memory names) are recognised; q/k/v and gate/up are fused into our layout; the unused action-expert
    embedding / LM head, the VLM's tied LM head (when the embedding is also present) and LeRobot normalization
    buffers are dropped (listed in the result). Head counts and the action horizon come from the folder's
    `config.json` where the weights cannot tell them; `config_overrides` win over both. Norm stats for the processor
    files come from `norm_stats` (an openpi `norm_stats.json`, file or folder) or else from a LeRobot folder's
    `policy_preprocessor_step_*_normalizer_processor.safetensors`.
    """
    torch_dtype, max_shard_bytes, output_dir = checked_arguments(dtype, max_shard_bytes, input_dir, output_dir, overwrite)
    folder = Path(input_dir).expanduser()
    if not folder.is_dir():
        raise ConversionError(f"input folder {folder} does not exist")
    weights = _HFWeights.scan(folder)
    config = _config_from_hf(weights, _hf_config_hints(folder), config_overrides)
    plan = planned_shapes(config)
    have = {name: weights.fused_shape(name) for name in weights.sources}
    missing = sorted(set(plan) - set(have))
    unexpected = sorted(set(have) - set(plan))
    misshaped = sorted(f"{n} {have[n]} (expected {plan[n]})" for n in set(plan) & set(have) if have[n] != plan[n])
    problems = [f"{kind}: {name_list(names)}" for kind, names in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", misshaped)) if names]
    if problems:
        raise ConversionError(f"{folder} does not match the inferred {'π0.5' if config.pi05 else 'π0'} config; " + "; ".join(problems))
    if norm_stats is not None:
        stats_path: Path | None = Path(norm_stats).expanduser()
        stats = read_norm_stats(stats_path)
    else:
        stats_path, stats = lerobot_norm_stats(folder) or (None, None)
    tokenizer = check_tokenizer(tokenizer, config)
    processor = build_processor(config, stats, tokenizer, processor_options)
    itemsize = torch.empty((), dtype=torch_dtype).element_size()
    check_disk_space(output_dir, sum(math.prod(s) for s in plan.values()) * itemsize)

    with atomic_output_dir(output_dir, overwrite) as out:
        handles: dict[Path, Any] = {}
        try:
            for path in set(weights.files.values()):
                handles[path] = safe_open(path, framework="pt")
            with ShardedSafetensorsWriter(out, plan, torch_dtype, max_shard_bytes) as writer, progress_bar(
                writer.total_bytes, f"converting {folder.name}", progress
            ) as bar:
                for name in plan:
                    tensor = weights.tensor(name, handles)
                    if not tensor.is_floating_point():
                        raise ConversionError(f"{folder}: tensor for {name} has dtype {tensor.dtype}; expected floating-point weights")
                    bar.update(writer.write(name, tensor))
                    del tensor
        finally:
            handles.clear()
        save_config(config, torch_dtype, out)
        write_processor_files(out, processor, stats, tokenizer)
    return ConversionResult(output_dir, config, torch_dtype, [output_dir / n for n in writer.filenames], writer.total_bytes,
                            stats_path, weights.dropped, processor_missing=processor_inputs_missing(config, stats, tokenizer))


def lerobot_norm_stats(folder: Path) -> tuple[Path, dict[str, NormStats]] | None:
    """Norm stats from a LeRobot policy folder (`policy_preprocessor_step_*_normalizer_processor.safetensors`, keys
    `observation.state.{mean,std,q01,q99}` and `action.{...}`), in openpi's form; None when the folder has none."""
    found = sorted(folder.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    if not found:
        return None
    if len(found) > 1:
        raise ConversionError(f"{folder} has several LeRobot normalizer files ({', '.join(p.name for p in found)}); pass --norm-stats")
    try:
        with safe_open(found[0], framework="np") as handle:
            values = {key: handle.get_tensor(key) for key in handle.keys()}
    except Exception as error:  # safetensors raises its own SafetensorError on malformed files
        raise ConversionError(f"cannot read {found[0]}: {first_line(error)}") from None
    stats = {}
    for ours, theirs in (("state", "observation.state"), ("actions", "action")):
        entry = {name: values.get(f"{theirs}.{name}") for name in ("mean", "std", "q01", "q99")}
        try:
            stats[ours] = NormStats.from_dict({k: None if v is None else v.reshape(-1) for k, v in entry.items()})
        except ValueError as error:
            raise ConversionError(f"{found[0]}: unusable {theirs} statistics: {error}") from None
    return found[0], stats


def _hf_export_names(name: str, config: PI0Config) -> list[tuple[str, int, int]]:
    """transformers `PI0ForConditionalGeneration` parameters (and row ranges) that our parameter `name` becomes."""
    if name.startswith("vision_tower."):
        return [(f"model.vlm.{name}", 0, -1)]
    if name.startswith("image_projection."):
        return [(f"model.vlm.multi_modal_projector.linear.{name.rsplit('.', 1)[1]}", 0, -1)]
    if name == "embed_tokens.weight":
        return [("model.vlm.language_model.embed_tokens.weight", 0, -1)]
    if name == "vlm_final_norm.weight":
        return [("model.vlm.language_model.norm.weight", 0, -1)]
    if name == "expert_final_norm.weight":
        return [("model.dit.norm.weight", 0, -1)]
    if name.split(".", 1)[0] in _HEADS:
        return [(name if name.startswith("action_out_proj") else f"embed_action_time.{name}", 0, -1)]
    match = re.fullmatch(r"layers\.(\d+)\.(vlm|expert)\.(.+)", name)
    if not match:
        raise ConversionError(f"no transformers PI0 counterpart for {name}")
    layer, expert, ours = match.groups()
    prefix = f"model.vlm.language_model.layers.{layer}." if expert == "vlm" else f"model.dit.layers.{layer}."
    width = config.vlm_intermediate_size if expert == "vlm" else config.expert_intermediate_size
    q_rows, kv_rows = config.num_attention_heads * config.head_dim, config.num_key_value_heads * config.head_dim
    rows = {"qkv_proj.weight": [q_rows, kv_rows, kv_rows], "gate_up_proj.weight": [width, width]}.get(ours, [-1])
    theirs = sorted((part, key) for key, (target, part, _) in _HF_LAYER.items() if target == ours)
    if not theirs:
        raise ConversionError(f"no transformers PI0 counterpart for {name}")
    starts = np.cumsum([0, *rows[:-1]]).tolist()
    return [(prefix + key, start, start + count if count > 0 else -1) for (part, key), start, count in zip(theirs, starts, rows)]


def _transformers_config(config: PI0Config) -> Any:
    from transformers import PI0Config as HFPI0Config

    gemma = dict(num_attention_heads=config.num_attention_heads, num_key_value_heads=config.num_key_value_heads,
                 head_dim=config.head_dim, num_hidden_layers=config.num_hidden_layers, rms_norm_eps=config.rms_norm_eps,
                 rope_parameters={"rope_theta": config.rope_theta, "rope_type": "default"})
    return HFPI0Config(
        vlm_config=dict(
            text_config=dict(model_type="gemma", hidden_size=config.vlm_hidden_size, intermediate_size=config.vlm_intermediate_size,
                             vocab_size=config.vocab_size, **gemma),
            vision_config=dict(model_type="siglip_vision_model", hidden_size=config.vision_hidden_size,
                               intermediate_size=config.vision_intermediate_size, num_hidden_layers=config.vision_num_layers,
                               num_attention_heads=config.vision_num_heads, patch_size=config.patch_size,
                               image_size=config.image_size, vision_use_head=False),
            projection_dim=config.vlm_hidden_size,
            image_token_id=config.vocab_size,
        ),
        # (the expert's unused embedding table: transformers >= 5.20 sizes it as the VLM's, earlier ones by this vocab_size)
        dit_config=dict(hidden_size=config.expert_hidden_size, intermediate_size=config.expert_intermediate_size,
                        vocab_size=config.vocab_size, **gemma),
        chunk_size=config.action_horizon,
        max_state_dim=config.action_dim,
        max_action_dim=config.action_dim,
        num_inference_steps=config.num_inference_steps,
        time_sampling_beta_alpha=config.time_beta_alpha,
        time_sampling_beta_beta=config.time_beta_beta,
        time_sampling_scale=config.time_scale,
        time_sampling_offset=config.time_offset,
        min_period=config.time_min_period,
        max_period=config.time_max_period,
    )


def export_to_transformers(
    model_dir: str | os.PathLike[str], output_dir: str | os.PathLike[str], *, dtype: str | None = None,
    overwrite: bool = False, progress: bool = False,
) -> Path:
    """Write a pi0-torch π0 folder as a transformers `PI0ForConditionalGeneration` folder (weights + config.json).

    For side-by-side comparisons with `transformers.PI0ForConditionalGeneration.from_pretrained(output_dir)`. q/k/v
    and gate/up are split; transformers' action expert carries an embedding table the model never reads, written as
    zeros. π0.5 has no transformers counterpart. The whole model passes through memory once (transformers writes
    the files). `dtype` defaults to the stored dtype. `progress`: transformers' "Writing model shards" bar.
    """
    from transformers import PI0ForConditionalGeneration

    source = Path(model_dir).expanduser()
    output = Path(output_dir).expanduser().absolute()
    check_output(source, output, overwrite)
    try:
        config = PI0Config.from_pretrained(source)
    except (OSError, ValueError) as error:
        raise ConversionError(f"{source} is not a pi0-torch model folder: {first_line(error)}") from None
    if config.pi05:
        raise ConversionError("transformers' PI0ForConditionalGeneration has no π0.5 (adaRMS) variant; only π0 exports")
    files = _safetensors_files(source)
    hf_config = _transformers_config(config)
    state: dict[str, torch.Tensor] = {}
    for path in files:
        with safe_open(path, framework="pt") as handle:
            for name in handle.keys():
                tensor = handle.get_tensor(name)
                if dtype is not None:
                    tensor = tensor.to(DTYPES[dtype])
                for target, start, end in _hf_export_names(name, config):
                    state[target] = tensor if (start, end) == (0, -1) else tensor[start:end].clone()
    reference = next(iter(state.values()))
    state["model.dit.embed_tokens.weight"] = torch.zeros(config.vocab_size, config.expert_hidden_size, dtype=reference.dtype)
    with torch.device("meta"):
        model = PI0ForConditionalGeneration(hf_config)
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as error:
        raise ConversionError(f"{source} does not fill transformers' PI0: {first_line(error)}") from None
    with atomic_output_dir(output, overwrite) as folder, transformers_progress(progress):
        model.save_pretrained(folder)
    return output


def transformers_pi0_inputs(inputs: Mapping[str, torch.Tensor], config: PI0Config) -> dict[str, torch.Tensor]:
    """Our model inputs -> the same observation for transformers' `PI0ForConditionalGeneration` (as exported by
    `export_to_transformers`): image placeholder tokens before the text and one combined attention mask.

    transformers' processor would drop a missing camera's tokens; here every camera keeps its tokens, masked when
    missing (as openpi does), and `pixel_attention_mask` is all True so each camera's features land on its own
    tokens. Masked tokens do not advance positions, so both layouts give the same result.
    """
    batch, cameras = inputs["image_masks"].shape
    image_tokens = cameras * config.tokens_per_image
    image_token_id = config.vocab_size  # what `export_to_transformers` configures
    return dict(
        pixel_values=inputs["pixel_values"],
        pixel_attention_mask=torch.ones(batch, cameras, dtype=torch.bool, device=inputs["image_masks"].device),
        input_ids=torch.cat([inputs["input_ids"].new_full((batch, image_tokens), image_token_id), inputs["input_ids"]], dim=1),
        attention_mask=torch.cat(
            [inputs["image_masks"].repeat_interleave(config.tokens_per_image, dim=1), inputs["attention_mask"].bool()], dim=1
        ).long(),
        state=inputs["state"],
    )
