"""What trains in a fine-tuning run: [`freeze`] (`vision`: SigLIP + its projection; `vlm`: the whole PaliGemma side);
openpi's LoRA is `pi0_torch.training.lora`.

Parameters that can never influence the loss (the VLM's final norm and the last layer's VLM o-projection and MLP:
the prefix output of the last layer is never read, only its keys/values) are frozen in every run
([`loss_free_parameter_names`]); they would get no gradient anyway, and freezing them keeps DDP's set of
gradient-carrying parameters static.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration

FREEZE_GROUPS = ("vision", "vlm")


def group_prefixes(model: PI0ForActionGeneration, group: str) -> tuple[str, ...]:
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
    prefixes = tuple(prefix for group in groups for prefix in group_prefixes(model, group))
    unused = set(loss_free_parameter_names(model))
    for name, param in model.named_parameters():
        if name in unused or (prefixes and name.startswith(prefixes)):
            param.requires_grad_(False)
    return count_trainable(model)


def count_trainable(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
