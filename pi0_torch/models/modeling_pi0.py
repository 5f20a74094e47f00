"""π0 / π0.5 in PyTorch, numerically matching openpi (`src/openpi/models/pi0.py`, `gemma.py`, `siglip.py`).

Reading order: normalisation and RoPE, one layer of the joint two-expert Gemma, the model (prefix and suffix
embedding, training forward, cached sampling). Shapes: B batch, C cameras, P prefix tokens, S suffix tokens,
N query heads, K kv heads, H head size, D0 / D1 widths of the VLM Gemma (expert 0) and the action expert (expert 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from transformers import PreTrainedModel, SiglipVisionConfig, SiglipVisionModel
from transformers.modeling_layers import GradientCheckpointingLayer
from transformers.utils import ModelOutput

from pi0_torch.masks import masked_attention, prefix_lm_mask, to_additive_mask
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.flow_matching import euler_times, interpolate, sample_flow_time, sincos_time_embedding
from pi0_torch.models.rtc import DEFAULT_MAX_GUIDANCE, METHODS, ChunkPrefix, chunk_prefix, guidance_weight, per_sample_steps
from pi0_torch.utils.validation import check_pretrained_location, describe, hub_errors
from pi0_torch.utils.validation import check_tensor as _check_tensor  # (the name other model modules import from here)
from pi0_torch.utils import files
from pi0_torch.utils.quiet import transformers_progress

# ----------------------------------------------------------------------------------------------------------------------
# Normalisation and rotary position embedding
# ----------------------------------------------------------------------------------------------------------------------


def _rms_normalize(x: torch.Tensor, eps: float) -> torch.Tensor:
    """`x * rsqrt(mean(x^2) + eps)`, computed and returned in float32."""
    x = x.float()
    return x * torch.rsqrt(x.pow(2).mean(dim=-1, keepdim=True) + eps)


class RMSNorm(nn.Module):
    """Gemma RMSNorm: `normalize(x) * (1 + weight)` in float32, returned in the input dtype."""

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.zeros(dim))

    def forward(self, x: torch.Tensor, modulation: torch.Tensor | None = None) -> tuple[torch.Tensor, None]:
        return (_rms_normalize(x, self.eps) * (1 + self.weight)).to(x.dtype), None


class AdaRMSNorm(nn.Module):
    """π0.5 adaptive RMSNorm: the flow-time condition sets scale, shift and a residual gate.

    `modulation` is `self.modulation(condition)` = [scale | shift | gate], `[B, 3 * dim]` for all tokens of a sample
    or `[B, T, 3 * dim]` per token (real-time chunking gives committed action tokens their own flow time); callers
    compute it (once for all sampling steps, see `PI0ForActionGeneration.expert_modulations`). Returns the normed
    input and the gate.
    """

    def __init__(self, dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.modulation = nn.Linear(dim, 3 * dim)

    def forward(self, x: torch.Tensor, modulation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if modulation.dim() == 2:
            modulation = modulation[:, None, :]
        scale, shift, gate = modulation.chunk(3, dim=-1)  # [B, 1 or T, dim] each
        return (_rms_normalize(x, self.eps) * (1 + scale) + shift).to(x.dtype), gate


def rope_cos_sin(positions: torch.Tensor, head_dim: int, theta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """RoPE rotation for `positions` [B, T]: float32 cos and sin `[B, 1, T, H/2]` (frequencies theta**(-2k/H))."""
    exponents = (2.0 / head_dim) * torch.arange(head_dim // 2, dtype=torch.float32, device=positions.device)
    angles = positions.float()[:, None, :, None] / theta**exponents  # [B, 1, T, H/2]
    return torch.cos(angles), torch.sin(angles)


def apply_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate `x` [B, heads, T, H] in the split-halves layout, in float32; returns x's dtype."""
    first, second = x.float().chunk(2, dim=-1)
    return torch.cat([first * cos - second * sin, second * cos + first * sin], dim=-1).to(x.dtype)


# ----------------------------------------------------------------------------------------------------------------------
# The joint two-expert Gemma
# ----------------------------------------------------------------------------------------------------------------------


class ExpertLayer(nn.Module):
    """One expert's weights in one layer: pre-norms, fused q/k/v, o-projection and the GeGLU MLP (no biases)."""

    def __init__(self, config: PI0Config, width: int, mlp_width: int, adaptive: bool) -> None:
        super().__init__()
        norm = AdaRMSNorm if adaptive else RMSNorm
        heads, kv_heads, head_dim = config.num_attention_heads, config.num_key_value_heads, config.head_dim
        self.q_width, self.kv_width = heads * head_dim, kv_heads * head_dim
        self.attn_norm = norm(width, config.rms_norm_eps)
        self.qkv_proj = nn.Linear(width, self.q_width + 2 * self.kv_width, bias=False)  # rows: q | k | v
        self.o_proj = nn.Linear(self.q_width, width, bias=False)
        self.mlp_norm = norm(width, config.rms_norm_eps)
        self.gate_up_proj = nn.Linear(width, 2 * mlp_width, bias=False)  # rows: gate | up
        self.down_proj = nn.Linear(mlp_width, width, bias=False)
        self.head_dim = head_dim

    def project_qkv(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`h` [B, T, D] -> q [B, N, T, H], k and v [B, K, T, H] (before RoPE)."""
        q, k, v = self.qkv_proj(h).split([self.q_width, self.kv_width, self.kv_width], dim=-1)
        batch, length = h.shape[:2]
        return tuple(y.view(batch, length, -1, self.head_dim).transpose(1, 2) for y in (q, k, v))  # type: ignore[return-value]

    def mlp(self, h: torch.Tensor) -> torch.Tensor:
        gate, up = self.gate_up_proj(h).chunk(2, dim=-1)
        return self.down_proj(F.gelu(gate, approximate="tanh") * up)


def _residual(x: torch.Tensor, y: torch.Tensor, gate: torch.Tensor | None) -> torch.Tensor:
    return x + y if gate is None else x + y * gate


class JointDecoderLayer(GradientCheckpointingLayer):
    """One Gemma layer run by both experts at once: each expert normalises and projects its own tokens, attention
    runs over the concatenated sequence (prefix first), then each expert finishes its own tokens.

    Either stream may be None: the prefix runs alone when its k/v are cached for sampling, the suffix runs alone in
    each sampling step against that cache.
    """

    def __init__(self, config: PI0Config) -> None:
        super().__init__()
        self.vlm = ExpertLayer(config, config.vlm_hidden_size, config.vlm_intermediate_size, adaptive=False)
        self.expert = ExpertLayer(config, config.expert_hidden_size, config.expert_intermediate_size, config.pi05)

    def forward(
        self,
        prefix: torch.Tensor | None,  # [B, P, D0]
        suffix: torch.Tensor | None,  # [B, S, D1]
        cos: torch.Tensor,  # [B, 1, T, H/2] for the tokens passed (T = P + S of the streams present)
        sin: torch.Tensor,
        mask: torch.Tensor,  # additive float [B, 1, T, T_kv] from `to_additive_mask` (built once per pass)
        expert_modulation: tuple[torch.Tensor, torch.Tensor] | None = None,  # adaRMS (attn, mlp) [B, 3*D1] each
        kv_buffer: tuple[torch.Tensor, torch.Tensor] | None = None,  # [B, K, P + S, H] each
        kv_offset: int = 0,
        keys_only: bool = False,
        write_cache: bool = True,
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Returns the updated (prefix, suffix).

        With `kv_buffer`, the new post-RoPE k/v are written into it at `kv_offset` and attention reads the buffer up
        to the end of the new tokens (a static k/v cache). `keys_only` stops once they are written (the last layer
        of the cached prefix: its outputs are never read) and returns (None, None). `write_cache=False` reads the
        buffer's first `kv_offset` entries and appends the new k/v without writing them (a pure function of its
        inputs, for differentiating a sampling step with respect to its input).
        """
        attn_modulation, mlp_modulation = expert_modulation if expert_modulation is not None else (None, None)
        streams = [
            (expert, x, attn_mod, mlp_mod)
            for expert, x, attn_mod, mlp_mod in (
                (self.vlm, prefix, None, None),
                (self.expert, suffix, attn_modulation, mlp_modulation),
            )
            if x is not None
        ]

        queries, keys, values, gates = [], [], [], []
        for expert, x, attn_mod, _ in streams:
            h, gate = expert.attn_norm(x, attn_mod)
            q, k, v = expert.project_qkv(h)
            queries.append(q), keys.append(k), values.append(v), gates.append(gate)
        q = apply_rope(torch.cat(queries, dim=2), cos, sin)
        k = apply_rope(torch.cat(keys, dim=2), cos, sin)
        v = torch.cat(values, dim=2)
        if kv_buffer is not None and not write_cache:
            key_buffer, value_buffer = kv_buffer
            k = torch.cat([key_buffer[:, :, :kv_offset], k], dim=2)
            v = torch.cat([value_buffer[:, :, :kv_offset], v], dim=2)
        elif kv_buffer is not None:
            key_buffer, value_buffer = kv_buffer
            end = kv_offset + k.shape[2]
            key_buffer[:, :, kv_offset:end] = k
            value_buffer[:, :, kv_offset:end] = v
            k, v = key_buffer[:, :, :end], value_buffer[:, :, :end]
        if keys_only:
            return None, None
        attended = masked_attention(q, k, v, mask, scale=q.shape[-1] ** -0.5, additive=True)  # [B, N, T, H]
        attended = attended.transpose(1, 2).flatten(2)  # [B, T, N*H]

        outputs: list[torch.Tensor | None] = [None, None]
        start = 0
        for (expert, x, _, mlp_mod), gate in zip(streams, gates):
            stream_attended = attended[:, start : start + x.shape[1]]
            start += x.shape[1]
            x = _residual(x, expert.o_proj(stream_attended), gate)
            h, gate = expert.mlp_norm(x, mlp_mod)
            outputs[0 if expert is self.vlm else 1] = _residual(x, expert.mlp(h), gate)
        return outputs[0], outputs[1]


# ----------------------------------------------------------------------------------------------------------------------
# The model
# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class PI0Output(ModelOutput):
    """Output of [`PI0ForActionGeneration.forward`].

    Attributes:
        loss: scalar flow-matching loss, mean of `(velocity - (noise - actions))^2` over everything (when `actions`
            were given).
        velocity: predicted flow velocity `v_t` `[B, horizon, action_dim]`.
    """

    loss: torch.Tensor | None = None
    velocity: torch.Tensor | None = None


@dataclass
class StepConditioning:
    """What the flow time contributes to the suffix (see `PI0ForActionGeneration.conditioning`): per sample
    `[B, ...]`, or per action token `[B, horizon, ...]` when committed tokens have their own time (real-time chunking).
    """

    condition: torch.Tensor  # [B, D1] time half of action_time_mlp_in (π0) or adaRMS condition (π0.5)
    modulations: tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor] | None  # π0.5: per layer, final

    def tensors(self) -> list[torch.Tensor]:
        per_layer, final = self.modulations if self.modulations is not None else ([], None)
        return [self.condition, *(m for pair in per_layer for m in pair), *([final] if final is not None else [])]

    def map(self, fn: Callable[..., torch.Tensor], *others: StepConditioning) -> StepConditioning:
        """Apply `fn` to every tensor (with the matching tensors of `others` as further arguments)."""
        values = iter([fn(*group) for group in zip(self.tensors(), *(other.tensors() for other in others))])
        condition = next(values)
        if self.modulations is None:
            return StepConditioning(condition, None)
        per_layer = [(next(values), next(values)) for _ in self.modulations[0]]
        return StepConditioning(condition, (per_layer, next(values)))

    def per_token(self, clean: StepConditioning, committed: torch.Tensor) -> StepConditioning:
        """Per action token: `clean` (flow time 0, one row) where `committed` `[B, horizon]`, this step's elsewhere."""
        return self.map(lambda value, clean_value: torch.where(committed[..., None], clean_value[:, None], value[:, None]), clean)


@dataclass
class PrefixCache:
    """Post-RoPE keys and values of the prefix for every layer, in static buffers with room for the suffix."""

    keys: list[torch.Tensor]  # per layer [B, K, P + S, H]
    values: list[torch.Tensor]
    prefix_valid: torch.Tensor  # bool [B, P]

    @property
    def prefix_len(self) -> int:
        return self.prefix_valid.shape[1]


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
        elif isinstance(module, nn.Linear) and not _is_inside_vision_tower(self, module):
            nn.init.normal_(module.weight, std=std)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding) and not _is_inside_vision_tower(self, module):
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
        """
        config_file = None if kwargs.get("config") else f"{kwargs['subfolder']}/config.json" if kwargs.get("subfolder") else "config.json"
        check_pretrained_location(pretrained_model_name_or_path, config_file, "model")
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
        if problems:
            details = "; ".join(f"{kind}: {', '.join(names[:10])}{' ...' if len(names) > 10 else ''}" for kind, names in problems.items())
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


def _describe_mismatch(item: Any) -> str:
    """transformers reports a mismatch as (name, checkpoint shape, model shape)."""
    if isinstance(item, (tuple, list)) and len(item) == 3:
        name, checkpoint_shape, model_shape = item
        return f"{name} (checkpoint {tuple(checkpoint_shape)}, model {tuple(model_shape)})"
    return str(item)


def _is_inside_vision_tower(model: nn.Module, module: nn.Module) -> bool:
    vision_tower = getattr(model, "vision_tower", None)
    return vision_tower is not None and any(module is m for m in vision_tower.modules())


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


class SiglipImageEmbedding:
    """Image tokens of the PaliGemma models (π0 / π0.5 and π0-FAST): `self.vision_tower` (`siglip_vision_tower`)
    followed by the linear head `self.image_projection` to the Gemma width."""

    def embed_images(self, pixel_values: torch.Tensor, image_masks: torch.Tensor | None = None) -> torch.Tensor:
        """SigLIP + linear head: `[B, C, 3, H, W]` in [-1, 1] -> image tokens `[B, C, tokens_per_image, D0]`.

        With `image_masks` (eager mode only), masked cameras skip the vision tower and get zero tokens: no valid
        token ever attends to them, so the result is unchanged.
        """
        batch, cameras = pixel_values.shape[:2]
        images = pixel_values.flatten(0, 1).to(self.image_projection.weight.dtype)  # [B*C, 3, H, W]
        if image_masks is not None and not torch.compiler.is_compiling():
            keep = image_masks.flatten().bool()
            if not keep.all() and keep.any():
                encoded = self._encode_images(images[keep])  # dtype as the tower runs (autocast may change it)
                tokens = encoded.new_zeros(batch * cameras, *encoded.shape[1:])
                tokens[keep] = encoded
                return tokens.unflatten(0, (batch, cameras))
        return self._encode_images(images).unflatten(0, (batch, cameras))

    def _encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """`[n, 3, H, W]` -> `[n, tokens_per_image, D0]`."""
        return self.image_projection(self.vision_tower(pixel_values=images).last_hidden_state)


class PI0ForActionGeneration(SiglipImageEmbedding, PI0PreTrainedModel):
    """π0 / π0.5: SigLIP vision tower + VLM Gemma (expert 0) + action expert Gemma (expert 1) + action heads.

    ```python
    >>> import torch
    >>> from pi0_torch import PI0Config, PI0ForActionGeneration
    >>> config = PI0Config.from_preset("pi0_small")
    >>> model = PI0ForActionGeneration(config).eval()
    >>> batch = dict(
    ...     pixel_values=torch.zeros(1, config.num_cameras, 3, 224, 224),
    ...     image_masks=torch.ones(1, config.num_cameras, dtype=torch.bool),
    ...     input_ids=torch.ones(1, config.max_token_len, dtype=torch.long),
    ...     attention_mask=torch.ones(1, config.max_token_len, dtype=torch.bool),
    ...     state=torch.zeros(1, config.action_dim),
    ... )
    >>> model.generate_actions(**batch, generator=torch.Generator().manual_seed(0)).shape
    torch.Size([1, 50, 32])
    >>> model(**batch, actions=torch.zeros(1, 50, 32)).loss.shape
    torch.Size([])

    ```
    """

    def __init__(self, config: PI0Config) -> None:
        super().__init__(config)
        self.vision_tower = siglip_vision_tower(config)
        self.image_projection = nn.Linear(config.vision_hidden_size, config.vlm_hidden_size)
        self.embed_tokens = nn.Embedding(config.vocab_size, config.vlm_hidden_size)
        self.layers = nn.ModuleList(JointDecoderLayer(config) for _ in range(config.num_hidden_layers))
        self.vlm_final_norm = RMSNorm(config.vlm_hidden_size, config.rms_norm_eps)
        width = config.expert_hidden_size
        self.expert_final_norm = (AdaRMSNorm if config.pi05 else RMSNorm)(width, config.rms_norm_eps)
        self.action_in_proj = nn.Linear(config.action_dim, width)
        self.action_out_proj = nn.Linear(width, config.action_dim)
        if config.pi05:
            self.time_mlp_in = nn.Linear(width, width)
            self.time_mlp_out = nn.Linear(width, width)
        else:
            self.state_proj = nn.Linear(config.action_dim, width)
            self.action_time_mlp_in = nn.Linear(2 * width, width)
            self.action_time_mlp_out = nn.Linear(width, width)
        self._compiled_sample: Any = None  # set by `compile_sampling`
        self.post_init()

    # -- prefix: images and text ---------------------------------------------------------------------------------------

    def embed_prefix(
        self, pixel_values: torch.Tensor, image_masks: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Prefix tokens `[B, P, D0]` (each camera's image tokens, then the scaled text embeddings) and their
        validity `[B, P]`. Image tokens are not scaled; text embeddings are multiplied by sqrt(D0)."""
        image_tokens = self.embed_images(pixel_values, image_masks)  # [B, C, 256, D0]
        text_tokens = self.embed_tokens(input_ids)
        text_tokens = text_tokens * torch.tensor(math.sqrt(text_tokens.shape[-1]), dtype=text_tokens.dtype)
        tokens = torch.cat([image_tokens.flatten(1, 2), text_tokens], dim=1)
        image_valid = image_masks.bool()[:, :, None].expand(-1, -1, image_tokens.shape[2]).flatten(1)
        return tokens, torch.cat([image_valid, attention_mask.bool()], dim=1)

    # -- suffix: state, noisy actions, flow time -----------------------------------------------------------------------

    def suffix_block_flags(self, device: torch.device) -> torch.Tensor:
        """Block starts of the suffix: π0 [state, a_0, a_1, ...] = [1, 1, 0, ...]; π0.5 [a_0, a_1, ...] = [1, 0, ...]."""
        flags = torch.zeros(self.config.suffix_len, dtype=torch.bool, device=device)
        flags[: 1 if self.config.pi05 else 2] = True
        return flags

    def time_conditioning(self, time: torch.Tensor) -> torch.Tensor:
        """What the flow time contributes, for any number of times `[T]`.

        π0: the time half of `action_time_mlp_in` (its bias included) `[T, D1]`; π0.5: the adaRMS condition
        `silu(time_mlp_out(silu(time_mlp_in(emb))))` `[T, D1]`. Depends on nothing else, so sampling computes it
        for every step at once.
        """
        config = self.config
        dtype = self.action_in_proj.weight.dtype
        embedding = sincos_time_embedding(time, config.expert_hidden_size, config.time_min_period, config.time_max_period)
        embedding = embedding.to(dtype)
        if config.pi05:
            return F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(embedding))))
        width = config.expert_hidden_size
        return F.linear(embedding, self.action_time_mlp_in.weight[:, width:], self.action_time_mlp_in.bias)

    def conditioning(self, time: torch.Tensor, committed: torch.Tensor | None = None) -> StepConditioning:
        """The suffix's time conditioning for flow times `[T]`: `time_conditioning` and (π0.5) the adaRMS
        modulations of every expert norm, `[T, ...]`.

        With `committed` bool `[T, horizon]` (real-time chunking: action tokens whose actions are given), those
        tokens get the conditioning of flow time 0 ("clean") and the result is per token, `[T, horizon, ...]`.
        """
        condition = self.time_conditioning(time)
        step = StepConditioning(condition, self.expert_modulations(condition) if self.config.pi05 else None)
        if committed is None:
            return step
        return step.per_token(self.conditioning(torch.zeros(1, device=time.device)), committed)

    def step_conditioning(self, times: list[float], batch: int, committed: torch.Tensor | None = None) -> list[StepConditioning]:
        """Everything that depends only on the flow time, for all sampling steps at once: per step the
        `conditioning` of that time for a batch of `batch` (per token where `committed` `[B, horizon]` is given)."""
        steps = self.conditioning(torch.tensor(times, dtype=torch.float32, device=self.device))  # [steps, ...]
        clean = self.conditioning(torch.zeros(1, device=self.device)) if committed is not None else None
        per_step = []
        for index in range(len(times)):
            step = steps.map(lambda value, index=index: value[index].expand(batch, -1))
            per_step.append(step if clean is None else step.per_token(clean, committed))
        return per_step

    def expert_modulations(self, condition: torch.Tensor) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
        """π0.5 adaRMS modulations `[..., 3*D1]` of every expert norm for `condition` `[..., D1]`: per layer
        (attention norm, MLP norm), and the final norm."""
        per_layer = [
            (layer.expert.attn_norm.modulation(condition), layer.expert.mlp_norm.modulation(condition)) for layer in self.layers
        ]
        return per_layer, self.expert_final_norm.modulation(condition)

    def embed_suffix(
        self, state: torch.Tensor | None, noisy_actions: torch.Tensor, time_conditioning: torch.Tensor
    ) -> torch.Tensor:
        """Suffix tokens `[B, S, D1]` from the state (π0), the noisy actions `[B, horizon, action_dim]` and
        `time_conditioning(time)`, `[B, D1]` or per action token `[B, horizon, D1]`."""
        dtype = self.action_in_proj.weight.dtype
        action_tokens = self.action_in_proj(noisy_actions.to(dtype))
        if self.config.pi05:
            return action_tokens
        width = self.config.expert_hidden_size
        # action_time_mlp_in(cat(actions, time)) split into its action half and the precomputed time half
        if time_conditioning.dim() == 2:
            time_conditioning = time_conditioning[:, None, :]
        hidden = F.linear(action_tokens, self.action_time_mlp_in.weight[:, :width]) + time_conditioning
        action_tokens = self.action_time_mlp_out(F.silu(hidden))
        state_token = self.state_proj(state.to(dtype))[:, None, :]
        return torch.cat([state_token, action_tokens], dim=1)

    # -- training forward ----------------------------------------------------------------------------------------------

    def forward(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        actions: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        time: torch.Tensor | None = None,
        inference_delay: torch.Tensor | None = None,
        **unused: Any,
    ) -> PI0Output:
        """Predict the flow velocity at time `time` for `x_t = time * noise + (1 - time) * actions`.

        Args:
            pixel_values: float `[B, C, 3, H, W]` in [-1, 1], cameras in `config.camera_names` order.
            image_masks: bool `[B, C]`, False for a missing camera.
            input_ids: long `[B, L]` (L <= `config.max_token_len`); attention_mask: bool/long `[B, L]`.
            state: float `[B, action_dim]` (required by π0, unused by π0.5).
            actions: float `[B, horizon, action_dim]` normalized target actions; gives `loss`. Without them
                `noise` is used as the noisy input `x_t` directly (with `time`, default 1).
            noise: float `[B, horizon, action_dim]`, drawn from N(0, I) when not given.
            time: float `[B]` flow times, drawn from Beta(1.5, 1) * 0.999 + 0.001 when not given.
            inference_delay: long `[B]` (training-time real-time chunking): the first `d` action steps of each
                sample are given clean (flow time 0, `x_t = actions` there) as the actions a robot executes while
                the next chunk is computed; the loss averages over the other steps only. None: every step is noisy.

        Returns:
            [`PI0Output`] with `velocity` `[B, horizon, action_dim]` and `loss` (scalar, when `actions` is given).
        """
        batch = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state)
        config, device = self.config, pixel_values.device
        shape = (batch, config.action_horizon, config.action_dim)
        if actions is not None:
            _check_tensor("actions", actions, shape, floating=True)
        if noise is None:
            noise = torch.randn(shape, device=device, dtype=torch.float32)
        _check_tensor("noise", noise, shape, floating=True)
        if time is None:
            time = (
                sample_flow_time(batch, config.time_beta_alpha, config.time_beta_beta, config.time_scale, config.time_offset, device)
                if actions is not None
                else torch.ones(batch, device=device)
            )
        _check_tensor("time", time, (batch,), floating=True)

        committed = None
        if inference_delay is not None:
            delay = per_sample_steps(inference_delay, batch, "inference_delay", device)
            if bool(((delay < 0) | (delay >= config.action_horizon)).any()):
                raise ValueError(f"inference_delay must lie in [0, action_horizon - 1 = {config.action_horizon - 1}], got {delay.tolist()}")
            committed = torch.arange(config.action_horizon, device=device)[None, :] < delay[:, None]  # [B, horizon]

        if actions is not None:
            x_t, target = interpolate(actions.float(), noise.float(), time.float())
            if committed is not None:  # flow time 0 there
                x_t = torch.where(committed[..., None], actions.float(), x_t)
        else:
            x_t, target = noise.float(), None

        prefix, prefix_valid = self.embed_prefix(pixel_values, image_masks, input_ids, attention_mask)
        conditioning = self.conditioning(time, committed)
        suffix = self.embed_suffix(state, x_t, conditioning.condition)
        suffix_flags = self.suffix_block_flags(device)
        valid = torch.cat([prefix_valid, torch.ones(batch, suffix.shape[1], dtype=torch.bool, device=device)], dim=1)
        flags = torch.cat([torch.zeros(prefix.shape[1], dtype=torch.bool, device=device), suffix_flags])
        mask, positions = prefix_lm_mask(valid, flags)
        _, suffix_out = self.run_layers(prefix, suffix, mask, positions, conditioning)
        velocity = self.action_out_proj(suffix_out[:, -config.action_horizon :]).float()
        if target is None:
            loss = None
        elif committed is None:
            loss = F.mse_loss(velocity, target)
        else:  # the given steps carry no loss
            loss = F.mse_loss(velocity[~committed], target[~committed])
        return PI0Output(loss=loss, velocity=velocity)

    def run_layers(
        self,
        prefix: torch.Tensor,
        suffix: torch.Tensor,
        mask: torch.Tensor,
        positions: torch.Tensor,
        conditioning: StepConditioning,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Both experts jointly through every layer and their final norms: (prefix_out, suffix_out).

        `mask` bool [B, P+S, P+S], `positions` [B, P+S], `conditioning` of the flow time (see `conditioning`).
        """
        cos, sin = rope_cos_sin(positions, self.config.head_dim, self.config.rope_theta)
        mask = to_additive_mask(mask[:, None], prefix.dtype)  # once for all layers
        modulations = conditioning.modulations
        layer_modulations, final_modulation = modulations if modulations is not None else ([None] * len(self.layers), None)
        for layer, modulation in zip(self.layers, layer_modulations):
            prefix, suffix = layer(prefix, suffix, cos, sin, mask, modulation)
        prefix, _ = self.vlm_final_norm(prefix)
        suffix, _ = self.expert_final_norm(suffix, final_modulation)
        return prefix, suffix

    # -- sampling ------------------------------------------------------------------------------------------------------

    def cache_prefix(
        self, pixel_values: torch.Tensor, image_masks: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
    ) -> PrefixCache:
        """Run the prefix once through the VLM expert and keep every layer's post-RoPE k/v.

        Exact for sampling because the prefix never attends to the suffix. The buffers have room for the suffix,
        whose k/v each denoising step writes in place (no per-step copy of the prefix). In eager mode, tokens that
        nothing attends to (masked cameras, text padding) are dropped first, so they cost no compute.
        """
        prefix, prefix_valid = self.embed_prefix(pixel_values, image_masks, input_ids, attention_mask)
        if not torch.compiler.is_compiling():
            prefix, prefix_valid = _drop_invalid_tokens(prefix, prefix_valid)
        batch, prefix_len = prefix_valid.shape
        config = self.config
        buffer_shape = (batch, config.num_key_value_heads, prefix_len + config.suffix_len, config.head_dim)
        cache = PrefixCache(
            keys=[prefix.new_empty(buffer_shape) for _ in self.layers],
            values=[prefix.new_empty(buffer_shape) for _ in self.layers],
            prefix_valid=prefix_valid,
        )
        mask, positions = prefix_lm_mask(prefix_valid, torch.zeros(prefix_len, dtype=torch.bool, device=prefix.device))
        cos, sin = rope_cos_sin(positions, config.head_dim, config.rope_theta)
        mask = to_additive_mask(mask[:, None], prefix.dtype)
        for index, (layer, key_buffer, value_buffer) in enumerate(zip(self.layers, cache.keys, cache.values)):
            last = index == len(self.layers) - 1
            prefix, _ = layer(prefix, None, cos, sin, mask, kv_buffer=(key_buffer, value_buffer), keys_only=last)
        return cache

    def suffix_attention(self, prefix_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mask `[B, 1, S, P+S]` and RoPE cos/sin of the suffix queries: they see every valid prefix token and the
        suffix block mask; their positions continue after the valid prefix tokens."""
        batch = prefix_valid.shape[0]
        device = prefix_valid.device
        suffix_valid = torch.ones(batch, self.config.suffix_len, dtype=torch.bool, device=device)
        suffix_mask, suffix_positions = prefix_lm_mask(suffix_valid, self.suffix_block_flags(device))
        prefix_part = prefix_valid[:, None, :].expand(-1, self.config.suffix_len, -1)
        mask = torch.cat([prefix_part, suffix_mask], dim=2)[:, None]
        positions = prefix_valid.sum(dim=1, keepdim=True) + suffix_positions
        cos, sin = rope_cos_sin(positions, self.config.head_dim, self.config.rope_theta)
        return mask, cos, sin

    def denoise_step(
        self,
        cache: PrefixCache,
        state: torch.Tensor | None,
        x_t: torch.Tensor,
        conditioning: StepConditioning,
        suffix_attention: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        write_cache: bool = True,
    ) -> torch.Tensor:
        """Velocity `[B, horizon, action_dim]` (float32) at `x_t` given the cached prefix, this step's
        `conditioning` (from `step_conditioning`) and `suffix_attention(cache.prefix_valid)`. `write_cache=False`
        leaves the cache untouched (a pure function of `x_t`, to differentiate through)."""
        mask, cos, sin = suffix_attention
        suffix = self.embed_suffix(state, x_t, conditioning.condition)
        mask = to_additive_mask(mask, suffix.dtype)
        modulations = conditioning.modulations
        layer_modulations, final_modulation = modulations if modulations is not None else ([None] * len(self.layers), None)
        for layer, key_buffer, value_buffer, modulation in zip(self.layers, cache.keys, cache.values, layer_modulations):
            _, suffix = layer(
                None, suffix, cos, sin, mask, modulation,
                kv_buffer=(key_buffer, value_buffer), kv_offset=cache.prefix_len, write_cache=write_cache,
            )
        suffix, _ = self.expert_final_norm(suffix, final_modulation)
        return self.action_out_proj(suffix[:, -self.config.action_horizon :]).float()

    def guided_velocity(
        self,
        cache: PrefixCache,
        state: torch.Tensor | None,
        x_t: torch.Tensor,
        time: float,
        conditioning: StepConditioning,
        suffix_attention: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        prefix: ChunkPrefix,
        max_guidance: float,
    ) -> torch.Tensor:
        """Inference-time real-time chunking: the velocity at `x_t`, corrected so that the predicted clean chunk
        `x0 = x_t - t * v` moves toward the previous chunk's target where the soft mask asks for it.

        `v' = v - w * J^T (W * (Y - x0))` with `J = dx0 / dx_t` (one vector-Jacobian product through the suffix;
        the prefix cache is a constant) and `w = min(beta, ((1 - t)^2 + t^2) / (t (1 - t)))`. The minus sign is
        openpi's convention: v points from data to noise and the Euler steps go down in t.
        """

        def clean_estimate(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            velocity = self.denoise_step(cache, state, x, conditioning, suffix_attention, write_cache=False)
            return x - time * velocity, velocity

        predicted, pullback, velocity = torch.func.vjp(clean_estimate, x_t, has_aux=True)
        (correction,) = pullback(prefix.weights[..., None] * (prefix.target - predicted))
        return velocity - guidance_weight(time, max_guidance) * correction

    @torch.no_grad()
    def generate_actions(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        num_steps: int | None = None,
        generator: torch.Generator | None = None,
        previous_actions: torch.Tensor | None = None,
        inference_delay: int | torch.Tensor = 0,
        execution_horizon: int | torch.Tensor | None = None,
        rtc_method: str = "guidance",
        rtc_max_guidance: float = DEFAULT_MAX_GUIDANCE,
        rtc_schedule: str = "exp",
    ) -> torch.Tensor:
        """Sample an action chunk by Euler integration of the flow from noise (t = 1) to actions (t = 0).

        The prefix runs once (`cache_prefix`); each of the `num_steps` steps (default `config.num_inference_steps`)
        runs only the suffix against the cached k/v. Everything that depends only on the flow time is computed for
        all steps up front. The Euler state is kept in float32 whatever the weights' dtype.

        Real-time chunking (see `pi0_torch.models.rtc`): with `previous_actions`, the new chunk continues the one
        the robot is executing. Its index 0 is the step at which this inference starts, `execution_horizon` (`s`)
        steps after the previous one started, and the robot executes `inference_delay` (`d`) more of the previous
        chunk while this one computes. `rtc_method="guidance"` (inference-time RTC) steers every Euler step toward
        the previous chunk's remaining actions with the soft mask `rtc_schedule` and guidance weight clipped at
        `rtc_max_guidance` (beta; 0 gives plain sampling, bit for bit); `"conditioning"` (training-time RTC, for a
        model trained with `config.rtc_max_delay >= d`) gives the first `d` actions as committed (flow time 0) and
        returns them unchanged.

        Args: as [`forward`], plus `noise` `[B, horizon, action_dim]` (drawn with `generator` when not given),
            `previous_actions` float `[B, horizon, action_dim]` (model space, as this method returned it),
            `inference_delay` / `execution_horizon` ints or long `[B]`.

        Returns:
            float32 `[B, horizon, action_dim]` actions in normalized model space (see `PI0Processor` to map them
            back to robot units).
        """
        batch = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state)
        config = self.config
        shape = (batch, config.action_horizon, config.action_dim)
        if noise is None:
            noise = torch.randn(shape, generator=generator, device=pixel_values.device, dtype=torch.float32)
        _check_tensor("noise", noise, shape, floating=True)
        times = euler_times(config.num_inference_steps if num_steps is None else num_steps)
        prefix = None
        if previous_actions is not None:
            prefix = self._chunk_prefix(batch, previous_actions, inference_delay, execution_horizon, rtc_method, rtc_max_guidance, rtc_schedule)
        sample = self._sample if self._compiled_sample is None else self._compiled_sample
        actions = sample(pixel_values, image_masks, input_ids, attention_mask, state, noise.float(), times,
                         prefix, rtc_method, float(rtc_max_guidance))
        # a CUDA graph's output is overwritten by its next replay: compiled sampling hands back a copy
        return actions if self._compiled_sample is None else actions.clone()

    def _sample(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None,
        noise: torch.Tensor,
        times: list[float],
        prefix: ChunkPrefix | None = None,
        rtc_method: str = "guidance",
        rtc_max_guidance: float = DEFAULT_MAX_GUIDANCE,
    ) -> torch.Tensor:
        """The sampling computation of `generate_actions` on checked inputs (what `compile_sampling` compiles)."""
        cache = self.cache_prefix(pixel_values, image_masks, input_ids, attention_mask)
        suffix_attention = self.suffix_attention(cache.prefix_valid)
        guided = prefix is not None and rtc_method == "guidance" and rtc_max_guidance > 0
        committed = prefix.committed if prefix is not None and rtc_method == "conditioning" else None
        dt = -1.0 / len(times)
        x_t = noise if committed is None else torch.where(committed[..., None], prefix.target, noise)
        for time, conditioning in zip(times, self.step_conditioning(times, noise.shape[0], committed)):
            if guided:
                velocity = self.guided_velocity(cache, state, x_t, time, conditioning, suffix_attention, prefix, rtc_max_guidance)
            else:
                velocity = self.denoise_step(cache, state, x_t, conditioning, suffix_attention)
            x_t = x_t + dt * velocity
            if committed is not None:  # the committed actions stay as given
                x_t = torch.where(committed[..., None], prefix.target, x_t)
        return x_t

    def _chunk_prefix(
        self,
        batch: int,
        previous_actions: torch.Tensor,
        inference_delay: int | torch.Tensor,
        execution_horizon: int | torch.Tensor | None,
        rtc_method: str,
        rtc_max_guidance: float,
        rtc_schedule: str,
    ) -> ChunkPrefix:
        """Check the real-time chunking arguments of `generate_actions` (previous chunk and guidance clip within
        `pi0_torch.models.rtc`'s bounds) and build the new chunk's prefix."""
        from pi0_torch.models.rtc import check_rtc_inputs

        config = self.config
        _check_tensor("previous_actions", previous_actions, (batch, config.action_horizon, config.action_dim), floating=True)
        if execution_horizon is None:
            raise ValueError("execution_horizon is required with previous_actions: the steps of the previous chunk executed "
                             "between its inference start and this one's")
        if not isinstance(rtc_method, str) or rtc_method not in METHODS:
            raise ValueError(f"rtc_method must be one of {METHODS}, got {rtc_method!r:.60}")
        check_rtc_inputs("previous_actions", previous_actions, rtc_max_guidance)
        prefix = chunk_prefix(previous_actions.to(self.device), inference_delay, execution_horizon, rtc_schedule)
        longest = int(prefix.committed.sum(dim=1).max())
        if rtc_method == "conditioning" and longest > config.rtc_max_delay:
            raise ValueError(
                f"rtc_method='conditioning' needs a model trained with delays up to the inference delay ({longest}); this "
                f"one was trained with rtc_max_delay={config.rtc_max_delay} (train with --rtc-max-delay, or use 'guidance')"
            )
        return prefix

    @property
    def sampling_compiled(self) -> bool:
        """Whether `generate_actions` runs through `torch.compile` (see `compile_sampling`)."""
        return self._compiled_sample is not None

    def compile_sampling(self, **compile_kwargs: Any) -> None:
        """Opt in to `torch.compile` for `generate_actions`: the prefix pass and the whole Euler loop as one graph.

        `compile_kwargs` go to `torch.compile`, with `fullgraph=True` unless given (a graph break would split the
        sampling, and on CUDA its graph capture, in pieces). On CUDA, `mode="reduce-overhead"` captures the whole
        sampling in one CUDA graph. Inputs of a new shape, or another `num_steps`, compile again.
        `compile_sampling(disable=True)` goes back to eager.
        """
        if compile_kwargs.get("disable"):
            self._compiled_sample = None
            return
        compile_kwargs.setdefault("fullgraph", True)
        self._compiled_sample = torch.compile(self._sample, **compile_kwargs)

    # -- input checks --------------------------------------------------------------------------------------------------

    def _check_inputs(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None,
    ) -> int:
        """Validate the model inputs; returns the batch size. Errors name the argument, expected and actual."""
        config = self.config
        if not isinstance(pixel_values, torch.Tensor) or pixel_values.dim() != 5:
            raise ValueError(
                f"pixel_values must be a float tensor [B, num_cameras={config.num_cameras}, 3, {config.image_size}, "
                f"{config.image_size}], got {describe(pixel_values)}"
            )
        batch = pixel_values.shape[0]
        _check_tensor("pixel_values", pixel_values, (batch, config.num_cameras, 3, config.image_size, config.image_size), floating=True, finite=False)
        low, high = pixel_values.aminmax()
        if low < -1.001 or high > 1.001 or not (torch.isfinite(low) and torch.isfinite(high)):
            raise ValueError(
                f"pixel_values must lie in [-1, 1] (uint8 images map to x / 255 * 2 - 1), got range "
                f"[{low.item():.4g}, {high.item():.4g}]"
            )
        _check_tensor("image_masks", image_masks, (batch, config.num_cameras), dtypes=(torch.bool,))
        if (not isinstance(input_ids, torch.Tensor) or input_ids.dim() != 2 or input_ids.shape[0] != batch
                or not 1 <= input_ids.shape[1] <= config.max_token_len):
            raise ValueError(
                f"input_ids must be a torch.Tensor [B={batch}, L] with 1 <= L <= max_token_len={config.max_token_len}, "
                f"got {describe(input_ids)}"
            )
        _check_tensor("input_ids", input_ids, tuple(input_ids.shape), dtypes=(torch.long, torch.int32))
        lowest, highest = input_ids.aminmax()
        if (lowest < 0) | (highest >= config.vocab_size):
            raise ValueError(
                f"input_ids must be token ids in [0, vocab_size={config.vocab_size}), got values in "
                f"[{lowest.item()}, {highest.item()}] (a tokenizer larger than the model's vocabulary?)"
            )
        _check_tensor("attention_mask", attention_mask, tuple(input_ids.shape), dtypes=(torch.bool, torch.long, torch.int32))
        if not config.pi05 or state is not None:
            if state is None:
                raise ValueError(f"state is required by pi0: a float tensor [B={batch}, action_dim={config.action_dim}]")
            _check_tensor("state", state, (batch, config.action_dim), floating=True)
        return batch


def _drop_invalid_tokens(tokens: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Move each row's valid tokens to the front, in order, and cut the columns no row needs.

    Exact for the valid tokens: the prefix-LM mask and the positions (`cumsum(valid) - 1`) only depend on which
    tokens are valid and their order, and invalid tokens are never attended to.
    """
    kept = int(valid.sum(dim=1).max())
    if kept == valid.shape[1]:
        return tokens, valid
    order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices[:, :kept]  # valid first, in order
    tokens = tokens.gather(1, order[..., None].expand(-1, -1, tokens.shape[-1]))
    return tokens, valid.gather(1, order)
