"""What a fine-tuning run trains, from its settings: the model config ([`load_config`]: a model folder's or a
preset), the processor ([`build_processor`]: tokenizer, norm stats, robot dims, and the settings the model folder's
processor was trained with, [`run_processor_settings`]), and the model with its frozen parts or LoRA adapters
([`build_model`]); [`check_memory`] refuses a config too large for this machine before anything is built.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.normalization import compute_norm_stats, load_openpi_norm_stats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.processing.robot_spaces import get_conversion
from pi0_torch.processing.tokenization import TEST_TOKENIZER, TEST_TOKENIZER_VOCAB, build_test_tokenizer
from pi0_torch.training.fast import build_fast_processor
from pi0_torch.training.lora import apply_lora
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainable import FREEZE_GROUPS, freeze

logger = logging.getLogger(__name__)


def is_model_folder(model: str) -> bool:
    """Whether `--model` names a model folder (one with `config.json`) rather than a preset."""
    return (Path(model) / "config.json").is_file()


def load_config(settings: TrainSettings) -> PI0Config | PI0FastConfig:
    """The model config: a checkpoint folder's `config.json`, or a preset with `config_overrides`."""
    if is_model_folder(settings.model):
        if settings.config_overrides:
            raise ValueError("config_overrides apply to presets only; a checkpoint folder keeps its own config")
        model_type = json.loads((Path(settings.model) / "config.json").read_text()).get("model_type")
        config = (PI0FastConfig if model_type == PI0FastConfig.model_type else PI0Config).from_pretrained(settings.model)
    elif settings.model in fast_preset_names():
        config = PI0FastConfig.from_preset(settings.model, **settings.config_overrides)
    elif settings.model not in preset_names():
        raise ValueError(f"--model {settings.model!r} is neither a checkpoint folder (with config.json) nor a preset "
                         f"{preset_names() + fast_preset_names()}")
    else:
        config = PI0Config.from_preset(settings.model, **settings.config_overrides)
    if settings.rtc_max_delay is not None:  # a training choice the saved config records
        if not isinstance(config, PI0Config):
            raise ValueError("--rtc-max-delay applies to π0 / π0.5 (flow matching); π0-FAST decodes tokens")
        config = PI0Config.from_dict({**config.to_dict(), "rtc_max_delay": settings.rtc_max_delay})
    return config


def _processor_class(config: PI0Config | PI0FastConfig) -> type[PI0Processor]:
    return PI0FastProcessor if isinstance(config, PI0FastConfig) else PI0Processor


# Processor settings a fine-tuning run takes over from the model folder's processor (unless a flag overrides them):
# what the model was trained to read and to predict. Sizes come from the config, robot dims from the dataset.
INHERITED_PROCESSOR_SETTINGS = (
    "norm_mode", "delta_action_mask", "value_conversion", "min_norm_scale", "float_image_range", "required_cameras",
    "default_prompt", "truncation", "state_in_prompt",
)


def run_processor_settings(settings: TrainSettings, model_processor: PI0Processor | None) -> dict[str, Any]:
    """The processor settings of a run: the model folder's (`INHERITED_PROCESSOR_SETTINGS`), with
    `--delta-action-mask` / `--value-conversion` on top when given (`"none"` turns a value conversion off). A flag
    that changes an inherited setting logs a warning naming both values."""
    saved = model_processor.to_dict() if model_processor is not None else {}
    chosen = {name: saved[name] for name in INHERITED_PROCESSOR_SETTINGS if name in saved}
    flags = {"delta_action_mask": settings.delta_action_mask, "value_conversion": settings.value_conversion,
             "default_prompt": settings.default_prompt, "state_in_prompt": settings.state_in_prompt}
    for name, value in flags.items():
        if value is None:
            continue
        value = None if value == "none" else value
        if name in chosen and chosen[name] != value:
            logger.warning("--%s %s replaces the %s %s that %s was trained with", name.replace("_", "-"),
                           "none" if value is None else value, name, chosen[name], settings.model)
        chosen[name] = value
    kept = [f"{name}={value}" for name, value in chosen.items() if name in saved and flags.get(name) is None]
    if kept:
        logger.info("processor settings of %s kept: %s (--delta-action-mask, --value-conversion, --default-prompt "
                    "override those)",
                    settings.model, ", ".join(kept))
    return chosen


def build_processor(settings: TrainSettings, config: PI0Config | PI0FastConfig, dataset: LeRobotEpisodeDataset) -> PI0Processor:
    """The processor of a run: tokenizer from `--tokenizer` (or the model folder), norm stats from the dataset (or
    the model folder's processor, or an openpi `norm_stats.json`), robot dims from the dataset, and every other
    setting from the model folder's processor unless a flag overrides it ([`run_processor_settings`]); for π0-FAST
    the FAST tokenizer from `--fast-tokenizer` (a folder, or `fit`), else the model folder's. A resumed run takes
    the checkpoint's processor, which must fit the dataset."""
    processor_class = _processor_class(config)
    if settings.resume_from_checkpoint and (Path(settings.resume_from_checkpoint) / "processor_config.json").is_file():
        processor = processor_class.from_pretrained(settings.resume_from_checkpoint)
        for name, ours, theirs in (("state_dim", processor.state_dim, dataset.state_dim),
                                   ("action_dim_robot", processor.action_dim_robot, dataset.action_dim)):
            if ours != theirs:
                raise ValueError(f"--resume-from-checkpoint {settings.resume_from_checkpoint}: its processor has "
                                 f"{name} {ours}, the dataset {theirs}; resume with the run's dataset")
        return processor
    model_processor = None
    if is_model_folder(settings.model) and (Path(settings.model) / "processor_config.json").is_file():
        model_processor = processor_class.from_pretrained(settings.model)
    if settings.tokenizer == TEST_TOKENIZER:
        prompts = sorted(set(dataset.tasks.values()))
        tokenizer: Any = build_test_tokenizer(vocab_size=min(TEST_TOKENIZER_VOCAB, config.vocab_size), extra_sentences=prompts)
    elif settings.tokenizer:
        tokenizer = settings.tokenizer
    elif model_processor is not None:
        tokenizer = model_processor.tokenizer
    else:
        raise ValueError("no tokenizer: pass --tokenizer PATH (PaliGemma's SentencePiece model), or --tokenizer test for a tiny demo model")

    chosen = run_processor_settings(settings, model_processor)
    same_space = model_processor is not None and model_processor.norm_stats is not None and (
        model_processor.state_dim, model_processor.action_dim_robot) == (dataset.state_dim, dataset.action_dim)
    source = settings.norm_stats
    if source == "auto":  # a trained policy keeps the statistics it acts with; a base model of another robot does not
        source = "model" if same_space else "dataset"
    computed = None
    if source == "dataset" or same_space:  # (also to say how far the data lies from the model's statistics)
        dataset.check_value_spread()  # one corrupt value would make every other one normalize to about 0
        chunks: Iterable[dict[str, np.ndarray]] = dataset.iter_state_action_chunks()
        if chosen.get("value_conversion") is not None:  # the statistics of what the model sees
            conversion = get_conversion(chosen["value_conversion"])
            chunks = ({"state": conversion.state_to_model(c["state"]), "actions": conversion.actions_to_model(c["actions"])}
                      for c in chunks)
        computed = compute_norm_stats(
            chunks, delta_action_mask=chosen.get("delta_action_mask"), total=len(dataset.episodes), progress=settings.progress,
        )
    if settings.norm_stats == "auto" and source == "model" and computed is not None:
        far = _far_from_model(model_processor, computed)
        if far is not None:  # the model's statistics do not describe this data: it would normalize to hundreds
            logger.warning("norm stats: the dataset's %s; the model's statistics do not describe these episodes, so the "
                           "run trains with the dataset's (--norm-stats auto; --norm-stats model keeps the model's)", far)
            source = "dataset"
    if source == "dataset":
        norm_stats = computed
    elif source == "model":
        if model_processor is None or model_processor.norm_stats is None:
            raise ValueError(f"--norm-stats model: {settings.model} has no processor with norm stats")
        norm_stats = model_processor.norm_stats
    else:
        norm_stats = load_openpi_norm_stats(settings.norm_stats)
    if source != "dataset":  # (statistics of another robot space would be cut to the dataset's dims without a word)
        given = {"model": f"{settings.model}'s norm stats"}.get(source, str(settings.norm_stats))
        for key, dim in (("state", dataset.state_dim), ("actions", dataset.action_dim)):
            if key in norm_stats and norm_stats[key].dim != dim:
                raise ValueError(f"--norm-stats {source if source == 'model' else settings.norm_stats}: {given} have "
                                 f"{norm_stats[key].dim} {key} dims, the dataset {dim}: they describe another robot "
                                 "(--norm-stats dataset computes the dataset's)")
    _log_norm_stats_choice(settings, source, model_processor if same_space else None, computed)
    robot = dict(state_dim=dataset.state_dim, action_dim_robot=dataset.action_dim, **chosen)
    if isinstance(config, PI0FastConfig):
        action_tokenizer: Any = settings.fast_tokenizer
        if action_tokenizer is None and model_processor is not None:
            action_tokenizer = model_processor.action_tokenizer
        return build_fast_processor(config, tokenizer, norm_stats, dataset, action_tokenizer, **robot)
    return PI0Processor.from_config(config, tokenizer, norm_stats, **robot)


# How far a dataset's statistics may lie from a model's, in the model's normalized units (centre shift, or spread as a
# multiple of the model's), for `--norm-stats auto` to keep the model's: a fine-tune continues the policy on data like
# its own; beyond, the data normalizes to tens or hundreds (a dim constant in the model's data, its scale floored at
# min_norm_scale, that moves in the dataset: the demo policy's gripper, Reach to PickPlace, trained at a loss of 5.7e5)
AUTO_KEEPS_MODEL_WITHIN = 10.0


def _distances(model_processor: PI0Processor, computed: dict[str, Any]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per key ("state", "actions"): how far the dataset's centre lies from the model's, and its spread as a multiple of
    the model's, per dim, in the model's normalized units (its norm mode's scale, floored at `min_norm_scale`)."""
    distances = {}
    for key in ("state", "actions"):
        ours, theirs = model_processor.norm_stats[key], computed[key]
        dims = min(ours.dim, theirs.dim)
        if model_processor.norm_mode == "quantile" and ours.has_quantiles and theirs.has_quantiles:
            span = np.maximum(ours.q99[:dims] - ours.q01[:dims], model_processor.min_norm_scale) / 2  # (units of [-1, 1])
            shift = np.abs((theirs.q01[:dims] + theirs.q99[:dims]) / 2 - (ours.q01[:dims] + ours.q99[:dims]) / 2) / span
            spread = (theirs.q99[:dims] - theirs.q01[:dims]) / (2 * span)
        else:
            scale = np.maximum(ours.std[:dims], model_processor.min_norm_scale)
            shift = np.abs(theirs.mean[:dims] - ours.mean[:dims]) / scale
            spread = theirs.std[:dims] / scale
        distances[key] = (shift, spread)
    return distances


def _far_from_model(model_processor: PI0Processor, computed: dict[str, Any]) -> str | None:
    """Where the dataset's statistics lie beyond `AUTO_KEEPS_MODEL_WITHIN` of the model's (one phrase), or None."""
    for key, (shift, spread) in _distances(model_processor, computed).items():
        worst = int(np.argmax(np.maximum(shift, spread)))
        if max(float(shift[worst]), float(spread[worst])) > AUTO_KEEPS_MODEL_WITHIN:
            return (f"{key} dim {worst} lies {float(shift[worst]):.3g} of the model's scale from its centre with a "
                    f"spread of {float(spread[worst]):.3g} times its own (beyond {AUTO_KEEPS_MODEL_WITHIN:g})")
    return None


def _log_norm_stats_choice(settings: TrainSettings, source: str, model_processor: PI0Processor | None,
                           computed: dict[str, Any] | None) -> None:
    """Say which statistics the run trains with, and, where the model folder has statistics of the same robot space,
    how far the dataset's lie from them, in the model's normalized units (a fine-tune that silently replaced a trained
    policy's statistics once took it from 79% to 7% success)."""
    where = {"model": f"{settings.model}'s (the model folder's processor)", "dataset": "the training episodes'"}
    what = where.get(source, source)
    reason = " (--norm-stats auto: the model folder has none for this robot's dims)" if (
        settings.norm_stats == "auto" and source == "dataset") else ""
    logger.info("norm stats: %s%s", what, reason)
    if model_processor is None or computed is None:
        return
    for key, (shift, spread) in _distances(model_processor, computed).items():
        worst = int(np.argmax(shift))
        logger.info("norm stats, %s: the dataset's centre lies up to %.2f of the model's scale from the model's (dim %d); "
                    "its spread is %.2f-%.2f times the model's%s", key, float(shift[worst]), worst, float(spread.min()),
                    float(spread.max()), "" if source == "model" else " (training with the dataset's: --norm-stats model "
                    "keeps the policy's own)")


def build_model(settings: TrainSettings, config: PI0Config | PI0FastConfig) -> nn.Module:
    """The model with its frozen parts set, and openpi's LoRA adapters when asked (drawn from `--seed`, the same in
    every process)."""
    fast = isinstance(config, PI0FastConfig)
    model_class = PI0FastForActionGeneration if fast else PI0ForActionGeneration
    if is_model_folder(settings.model):  # with the run's config: it may add training choices (rtc_max_delay)
        model = model_class.from_pretrained(settings.model, config=config, dtype=torch.float32)
    else:
        torch.manual_seed(settings.seed)
        model = model_class(config)
    for group in settings.freeze:
        if group not in FREEZE_GROUPS:
            raise ValueError(f"--freeze {group!r}: expected one of {FREEZE_GROUPS}")
    if "vlm" in settings.freeze and fast:
        raise ValueError("--freeze vlm: π0-FAST is all VLM, nothing would train; freeze 'vision' or use --lora")
    freeze(model, settings.freeze)
    if settings.lora:
        model = apply_lora(model, settings.lora_rank_vlm, settings.lora_rank_expert, settings.freeze,
                           torch.Generator().manual_seed(settings.seed))
        adapters = sum(p.numel() for name, p in model.named_parameters() if ".lora_" in name and p.requires_grad)
        frozen = sum(p.numel() * p.element_size() for p in model.parameters() if not p.requires_grad)
        vlm = [] if "vlm" in settings.freeze else [f"rank {settings.lora_rank_vlm} on the {'' if fast else 'VLM '}Gemma"]
        expert = [] if fast else [f"rank {settings.lora_rank_expert} on the action expert"]
        logger.info("LoRA in openpi's layout: %s, %d adapter parameters; the rest of the Gemma frozen and rounded to "
                    "bf16 (frozen weights: %.3g GiB)", ", ".join(vlm + expert), adapters, frozen / 2**30)
    return model


def check_memory(config: PI0Config | PI0FastConfig) -> None:
    """Before a model is built from a config: refuse one whose float32 weights alone exceed this machine's memory,
    and warn when weights, gradients and AdamW's two moments (16 bytes a parameter) would."""
    import psutil

    parameters = config.estimated_parameters()
    available = psutil.virtual_memory().total
    if 4 * parameters > available:
        raise ValueError(f"this config has about {parameters / 1e9:.1f} B parameters, {4 * parameters / 2**30:.1f} GiB "
                         f"of float32 weights alone; this machine has {available / 2**30:.1f} GiB of memory "
                         "(--config-overrides)")
    if 16 * parameters > available:
        logger.warning("this config has about %.2f B parameters: training needs about %.1f GiB for weights, gradients "
                       "and AdamW state, more than this machine's %.1f GiB", parameters / 1e9,
                       16 * parameters / 2**30, available / 2**30)
