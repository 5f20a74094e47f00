"""What trains in a fine-tuning run: [`freeze`] (`vision`: SigLIP + its projection; `vlm`: the whole PaliGemma side)
and [`apply_lora`] (openpi's LoRA fine-tune through `peft`: rank 16 on the VLM Gemma, 32 on the action expert, the
rest of the Gemma frozen; the vision tower and the action/state/time heads keep training); [`merge_lora`] folds the
adapters back into the weights.

Parameters that can never influence the loss (the VLM's final norm and the last layer's VLM o-projection and MLP:
the prefix output of the last layer is never read, only its keys/values) are frozen in every run
([`loss_free_parameter_names`]); they would get no gradient anyway, and freezing them keeps DDP's set of
gradient-carrying parameters static.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("peft",))  # LoRA is peft's (nothing else of [train])
from torch import nn

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.training.settings import LORA_RANK_EXPERT, LORA_RANK_VLM

LORA_TARGETS = ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")

FREEZE_GROUPS = ("vision", "vlm")


def _group_prefixes(model: PI0ForActionGeneration, group: str) -> tuple[str, ...]:
    vision = ("vision_tower.", "image_projection.")
    if group == "vision":
        return vision
    if group == "vlm":
        layers = tuple(f"layers.{i}.{kind}." for i in range(len(model.layers)) for kind in ("vlm", "block"))  # block: π0-FAST
        return vision + ("embed_tokens.", "vlm_final_norm.", "final_norm.") + layers
    raise ValueError(f"unknown freeze group {group!r}; expected one of {FREEZE_GROUPS}")


def loss_free_parameter_names(model: PI0ForActionGeneration) -> list[str]:
    """Parameters that cannot influence the flow-matching loss: the VLM's final norm, and in the last layer the VLM
    o-projection, MLP norm and MLP (the last layer's prefix output is never read; its keys/values are)."""
    if isinstance(model.config, PI0FastConfig):
        return []  # every π0-FAST parameter feeds the next-token loss
    last = f"layers.{len(model.layers) - 1}.vlm."
    unused = ("vlm_final_norm.", last + "o_proj.", last + "mlp_norm.", last + "gate_up_proj.", last + "down_proj.")
    return [name for name, _ in model.named_parameters() if name.startswith(unused)]


def freeze(model: PI0ForActionGeneration, groups: Sequence[str] = ()) -> int:
    """Set `requires_grad=False` on the parameters of `groups` ("vision", "vlm") and on the loss-free parameters.

    Returns the number of trainable parameters left.
    """
    prefixes = tuple(prefix for group in groups for prefix in _group_prefixes(model, group))
    unused = set(loss_free_parameter_names(model))
    for name, param in model.named_parameters():
        if name in unused or (prefixes and name.startswith(prefixes)):
            param.requires_grad_(False)
    return count_trainable(model)


def count_trainable(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def apply_lora(
    model: PI0ForActionGeneration,
    rank_vlm: int = LORA_RANK_VLM,
    rank_expert: int = LORA_RANK_EXPERT,
    freeze_groups: Sequence[str] = (),
) -> nn.Module:
    """openpi-style LoRA through `peft`: adapters of rank `rank_vlm` (alpha = rank) on every VLM Gemma projection and
    of rank `rank_expert` on every action-expert projection; the Gemma base weights, norms and text embedding are
    frozen; the vision tower, its projection and the action/state/time heads keep training in full (peft
    `modules_to_save`), unless `freeze_groups` freezes them too.

    Returns the `peft.PeftModel`; `merge_lora` turns it back into a plain `PI0ForActionGeneration`.
    """
    from peft import LoraConfig, get_peft_model

    frozen_prefixes = tuple(prefix for group in freeze_groups for prefix in _group_prefixes(model, group))
    unused = set(loss_free_parameter_names(model))
    full_modules = [
        name for name, module in model.named_children()
        if name not in ("layers", "embed_tokens", "vlm_final_norm", "expert_final_norm", "final_norm")
        and not f"{name}.".startswith(frozen_prefixes)
        and any(True for _ in module.parameters())
    ]
    targets = "|".join(LORA_TARGETS)
    layer_kinds = "expert" if "vlm" in freeze_groups else "vlm|expert|block"  # a frozen VLM gets no adapters either
    expert_rank = {r"layers\.\d+\.expert\..*": rank_expert} if isinstance(model.config, PI0Config) else {}  # π0-FAST: no expert
    config = LoraConfig(
        r=rank_vlm,
        lora_alpha=rank_vlm,
        target_modules=rf"layers\.\d+\.({layer_kinds})\.({targets})",
        rank_pattern=expert_rank,
        alpha_pattern=expert_rank,
        modules_to_save=full_modules,
        exclude_modules=[name.rsplit(".", 1)[0] for name in unused],
    )
    with warnings.catch_warnings():  # (peft reads transformers' deprecated `is_gradient_checkpointing`: not the user's to fix)
        warnings.filterwarnings("ignore", message=".*is_gradient_checkpointing.*", category=FutureWarning)
        return get_peft_model(model, config)


def merge_lora(model: nn.Module) -> PI0ForActionGeneration:
    """A `peft` LoRA model -> the plain model with the adapters merged into the weights (others returned as is)."""
    from peft import PeftModel

    return model.merge_and_unload() if isinstance(model, PeftModel) else model  # type: ignore[return-value]
