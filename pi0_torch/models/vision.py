"""The image side of the PaliGemma models (π0 / π0.5 and π0-FAST): SigLIP So400m/14 without a pooling head, and the
linear head that turns its patch tokens into Gemma-width image tokens (not scaled by sqrt(D))."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn
from transformers import SiglipVisionConfig, SiglipVisionModel


def sincos_2d_positions(grid: int, width: int, temperature: float = 10_000.0) -> torch.Tensor:
    """big_vision's `posemb_sincos_2d`: `[grid * grid, width]` rows in raster order, `[sin x | cos x | sin y | cos y]`
    over `width // 4` frequencies from 1 down to `1 / temperature` (x the patch column, y its row)."""
    quarter = width // 4
    omega = 1.0 / temperature ** (torch.arange(quarter, dtype=torch.float64) / max(quarter - 1, 1))  # [width / 4]
    rows, columns = torch.meshgrid(torch.arange(grid, dtype=torch.float64), torch.arange(grid, dtype=torch.float64), indexing="ij")
    x = columns.flatten()[:, None] * omega  # [grid^2, width / 4]
    y = rows.flatten()[:, None] * omega
    return torch.cat([x.sin(), x.cos(), y.sin(), y.cos()], dim=1).float()


def siglip_vision_tower(config: Any) -> SiglipVisionModel:
    """The SigLIP tower of π0, π0.5 and π0-FAST from a config's `vision_*` dims, `image_size` and `patch_size`:
    pre-LN blocks with tanh GELU, LayerNorm eps 1e-6, no pooling head (openpi's `pool_type="none"`), patch
    positions initialised by `sincos_2d_positions` (square patch grids and widths divisible by 4, as every preset
    has; otherwise SigLIP's random init)."""
    vision_config = SiglipVisionConfig(
        hidden_size=config.vision_hidden_size,
        intermediate_size=config.vision_intermediate_size,
        num_hidden_layers=config.vision_num_layers,
        num_attention_heads=config.vision_num_heads,
        image_size=config.image_size,
        patch_size=config.patch_size,
        hidden_act="gelu_pytorch_tanh",
        layer_norm_eps=1e-6,
        vision_use_head=False,
        attn_implementation="sdpa",
    )
    tower = SiglipVisionModel(vision_config)
    # A tower trained from scratch starts with big_vision's 2-D sine-cosine patch positions (still a learned table)
    # instead of a random one: where a patch lies is readable from the first step. With the random table the tiny
    # demo policy spent thousands of steps finding where objects are (docs/training.md). Loaded weights replace it.
    table = tower.embeddings.position_embedding.weight  # [patches, width]
    grid = math.isqrt(table.shape[0])
    if grid * grid == table.shape[0] and table.shape[1] % 4 == 0 and table.device.type != "meta":
        with torch.no_grad():
            table.copy_(sincos_2d_positions(grid, table.shape[1]))
    return tower


def is_inside_vision_tower(model: nn.Module, module: nn.Module) -> bool:
    vision_tower = getattr(model, "vision_tower", None)
    return vision_tower is not None and any(module is m for m in vision_tower.modules())


class SiglipImageEmbedding:
    """Image tokens of the PaliGemma models (π0 / π0.5 and π0-FAST): `self.vision_tower` (`siglip_vision_tower`)
    followed by the linear head `self.image_projection` to the Gemma width."""

    def embed_images(self, pixel_values: torch.Tensor) -> torch.Tensor:
        """SigLIP + linear head: `[B, C, 3, H, W]` in [-1, 1] -> image tokens `[B, C, tokens_per_image, D0]`."""
        images = pixel_values.flatten(0, 1).to(self.image_projection.weight.dtype)  # [B*C, 3, H, W]
        patches = self.vision_tower(pixel_values=images).last_hidden_state  # [B*C, tokens_per_image, D]
        return self.image_projection(patches).unflatten(0, pixel_values.shape[:2])
