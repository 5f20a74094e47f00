"""π0 / π0.5 in PyTorch, numerically matching openpi (`src/openpi/models/pi0.py`, `gemma.py`, `siglip.py`).

Reading order: the model's pieces (prefix and suffix embeddings, the flow-time conditioning), the training forward,
and `sample_actions_reference`, openpi's `sample_actions` written plainly. The layers are in
`pi0_torch.models.layers`, the vision tower in `pi0_torch.models.vision`, loading and saving in
`pi0_torch.models.pretrained`, the input checks in `pi0_torch.models.input_checks`. `generate_actions`, the fast sampling users
call, comes from `pi0_torch.inference.sampling.ActionSampling` (the inference engine: token layouts, the prefix cache,
fused kernels, CUDA graphs) and is tested against `sample_actions_reference` at every level.

Shapes: B batch, C cameras, P prefix tokens, S suffix tokens, N query heads, K kv heads, H head size, D0 / D1 widths
of the VLM Gemma (expert 0) and the action expert (expert 1).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from transformers.utils import ModelOutput

from pi0_torch.inference.attention import AttentionPlan
from pi0_torch.inference.conditioning import StepConditioning, euler_times
from pi0_torch.inference.layout import PrefixLayout, StreamPass, camera_inputs, compact_prefix, prefix_stream, rope_tables, suffix_stream
from pi0_torch.inference.rtc import per_sample_steps
from pi0_torch.inference.sampling import ActionSampling, allow_recompiles
from pi0_torch.kernels.reference import rope_cos_sin
from pi0_torch.masks import prefix_lm_mask, to_additive_mask
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.flow_matching import interpolate, sample_flow_time, sincos_time_embedding
from pi0_torch.models.input_checks import InputChecks
from pi0_torch.models.layers import AdaRMSNorm, JointDecoderLayer, RMSNorm
from pi0_torch.models.pretrained import PI0PreTrainedModel
from pi0_torch.models.vision import SiglipImageEmbedding, siglip_vision_tower


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


class PI0ForActionGeneration(SiglipImageEmbedding, InputChecks, ActionSampling, PI0PreTrainedModel):
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
        self.post_init()

    # -- prefix: images and text ---------------------------------------------------------------------------------------

    def embed_prefix(
        self, pixel_values: torch.Tensor, image_masks: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Prefix tokens `[B, P, D0]` (each given camera's image tokens, then the scaled text embeddings) and their
        validity `[B, P]`."""
        image_tokens = self.embed_images(pixel_values) if pixel_values.shape[1] else None  # [B, C, 256, D0]
        return self.join_prefix(image_tokens, image_masks, input_ids, attention_mask)

    def join_prefix(
        self, image_tokens: torch.Tensor | None, image_masks: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The prefix of image tokens `[B, C, 256, D0]` (None: no sample shows any camera) and the prompt: image tokens
        are not scaled; text embeddings are multiplied by sqrt(D0) rounded to the weights' dtype (as openpi)."""
        text_tokens = self.embed_tokens(input_ids)
        text_tokens = text_tokens * _rounded_sqrt(text_tokens.shape[-1], text_tokens.dtype)
        valid = attention_mask.bool()
        if image_tokens is None:
            return text_tokens, valid
        image_valid = image_masks[:, :, None].expand(-1, -1, image_tokens.shape[2]).flatten(1)
        return torch.cat([image_tokens.flatten(1, 2), text_tokens], dim=1), torch.cat([image_valid, valid], dim=1)

    # -- suffix: state, noisy actions, flow time -----------------------------------------------------------------------

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

    def conditioning(self, time: torch.Tensor) -> StepConditioning:
        """The suffix's time conditioning for flow times `[T]`, every tensor `[T, ...]` (see `StepConditioning`)."""
        condition = self.time_conditioning(time)
        if not self.config.pi05:
            return StepConditioning(condition, None, None)
        layer_norms = tuple((layer.expert.attn_norm.params(condition), layer.expert.mlp_norm.params(condition)) for layer in self.layers)
        return StepConditioning(None, layer_norms, self.expert_final_norm.params(condition))

    def embed_state(self, state: torch.Tensor) -> torch.Tensor:
        """π0's state token `[B, D1]`."""
        return self.state_proj(state.to(self.state_proj.weight.dtype))

    def embed_actions(self, noisy_actions: torch.Tensor, condition: torch.Tensor | None) -> torch.Tensor:
        """Action tokens `[B * horizon, D1]` of the noisy actions `[B, horizon, action_dim]`. π0 adds the flow time:
        `action_time_mlp_out(silu(action_time_mlp_in(cat(tokens, time))))` with the time half precomputed
        (`condition` `[D1]`, or per token `[B * horizon, D1]`)."""
        tokens = self.action_in_proj(noisy_actions.to(self.action_in_proj.weight.dtype).flatten(0, 1))
        if self.config.pi05:
            return tokens
        action_weight = self.action_time_mlp_in.weight[:, : self.config.expert_hidden_size].t()
        return self.action_time_mlp_out(F.silu(torch.addmm(condition, tokens, action_weight)))

    def embed_suffix(self, state: torch.Tensor | None, noisy_actions: torch.Tensor, condition: torch.Tensor | None) -> torch.Tensor:
        """Suffix tokens `[B * S, D1]`: (π0) the state token, then the action tokens (see `embed_actions`)."""
        actions = self.embed_actions(noisy_actions, condition)
        if self.config.pi05:
            return actions
        batch = noisy_actions.shape[0]
        return torch.cat([self.embed_state(state)[:, None], actions.view(batch, -1, actions.shape[-1])], dim=1).flatten(0, 1)

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
        config = self.config
        horizon = config.action_horizon
        facts = self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state, actions=actions, noise=noise, time=time)
        batch, device = len(facts.text_counts), pixel_values.device
        shape = (batch, horizon, config.action_dim)
        if noise is None:
            noise = torch.randn(shape, device=device, dtype=torch.float32)
        if time is None:
            time = (
                sample_flow_time(batch, config.time_beta_alpha, config.time_beta_beta, config.time_scale, config.time_offset, device)
                if actions is not None
                else torch.ones(batch, device=device)
            )

        committed = None
        if inference_delay is not None:
            delay = per_sample_steps(inference_delay, batch, "inference_delay", device)
            if bool(((delay < 0) | (delay >= horizon)).any()):
                raise ValueError(f"inference_delay must lie in [0, action_horizon - 1 = {horizon - 1}], got {delay.tolist()}")
            committed = torch.arange(horizon, device=device)[None, :] < delay[:, None]  # [B, horizon]

        if actions is not None:
            x_t, target = interpolate(actions.float(), noise.float(), time.float())
            if committed is not None:  # flow time 0 there
                x_t = torch.where(committed[..., None], actions.float(), x_t)
        else:
            x_t, target = noise.float(), None

        if self.sampling_compiled:
            allow_recompiles(self.RECOMPILE_LIMIT)
        layout = facts.layout(config.tokens_per_image)
        prefix, prefix_valid = self.embed_prefix(*camera_inputs(pixel_values, image_masks, layout), input_ids, attention_mask)
        prefix, first = compact_prefix(prefix, prefix_valid, layout)
        clean = self.conditioning(torch.zeros(1, device=device)).steps()[0] if committed is not None else None
        conditioning = self.conditioning(time).per_token(horizon, committed, clean)
        suffix = self.embed_suffix(state, x_t, conditioning.condition)
        _, suffix_out = self.run_layers(prefix, suffix, first, layout, conditioning)
        velocity = self.action_out_proj(suffix_out.view(batch, -1, suffix_out.shape[-1])[:, -horizon:]).float()
        if target is None:
            loss = None
        elif committed is None:
            loss = F.mse_loss(velocity, target)
        else:  # the given steps carry no loss
            loss = F.mse_loss(velocity[~committed], target[~committed])
        return PI0Output(loss=loss, velocity=velocity)

    def run_layers(
        self, prefix: torch.Tensor, suffix: torch.Tensor, first: torch.Tensor, layout: PrefixLayout, conditioning: StepConditioning
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Both experts jointly through every layer and their final norms: (prefix_out `[B * length, D0]`,
        suffix_out `[B * S, D1]`).

        `prefix` holds the compacted prefix (`compact_prefix`, first valid slots `first` `[B]`), `suffix` the suffix
        tokens (`embed_suffix`), `conditioning` its time conditioning per token (`StepConditioning.per_token`). π0's
        state token sees the prefix and itself, its action tokens everything; π0.5's action tokens everything.
        """
        config = self.config
        horizon = config.action_horizon
        slots = layout.length + config.suffix_len
        group_rows = (horizon,) if config.pi05 else (1, horizon)
        rope = rope_tables(config, first, slots)
        streams = (  # (SDPA: gradients flow through attention)
            prefix_stream(config, first, layout, "sdpa", slots, self.dtype, rope),
            suffix_stream(config, first, layout, layout.length, group_rows, "sdpa", slots, self.dtype, rope),
        )
        norms = conditioning.layer_norms or (None,) * len(self.layers)
        for layer, layer_norms in zip(self.layers, norms):
            prefix, suffix = layer(prefix, suffix, streams, expert_norms=layer_norms)
        return self.vlm_final_norm(prefix), self.expert_final_norm(suffix, conditioning.final_norm)

    # -- reference sampling ----------------------------------------------------------------------------------------------

    @torch.no_grad()
    def sample_actions_reference(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        num_steps: int | None = None,
        return_cache: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]:
        """openpi's `sample_actions`, written plainly: the oracle `generate_actions` is tested against.

        The prefix (every camera and prompt token in the inputs' order, padding included) runs alone once, openpi's
        prefix-LM mask over it, its k/v kept; then each Euler step embeds the whole suffix (π0: the state token and the
        noisy actions with the flow time) and runs it against the kept k/v, with the suffix rows of the same mask. No
        token layout, no fused kernels, no graphs, nothing updated in place; slow, and exact.

        Args: as [`generate_actions`] (no real-time chunking); `noise` is required to compare with it.
            `return_cache=True` also returns every layer's k/v `[B, K, P + S, H]` after the last step.

        Returns:
            float32 `[B, horizon, action_dim]` actions in normalized model space.
        """
        config = self.config
        horizon, width = config.action_horizon, config.expert_hidden_size
        self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, state, noise=noise)
        batch, device = pixel_values.shape[0], pixel_values.device
        x_t = noise.float() if noise is not None else torch.randn(batch, horizon, config.action_dim, device=device)
        times = euler_times(config.num_inference_steps if num_steps is None else num_steps)

        prefix, prefix_valid = self.embed_prefix(pixel_values, image_masks, input_ids, attention_mask)  # [B, P, D0]
        length, suffix_len = prefix.shape[1], config.suffix_len
        # block flags: the prefix is one bidirectional block; π0's state token starts a block, the actions another
        suffix_flags = [1] + [0] * (horizon - 1) if config.pi05 else [1, 1] + [0] * (horizon - 1)
        flags = torch.tensor([0] * length + suffix_flags, device=device)
        valid = torch.cat([prefix_valid, prefix_valid.new_ones(batch, suffix_len)], dim=1)
        mask, positions = prefix_lm_mask(valid, flags)  # [B, P + S, P + S], [B, P + S]
        additive = to_additive_mask(mask, self.dtype)[:, None]  # [B, 1, P + S, P + S]
        cos, sin = (table[:, :, None] for table in rope_cos_sin(positions, config.head_dim, config.rope_theta))

        def stream(rows: slice, keys: int) -> StreamPass:
            plan = AttentionPlan("sdpa", keys, fold_heads=False, mask=additive[:, :, rows, :keys].contiguous())
            slots = torch.arange(rows.start, rows.stop, device=device)
            return StreamPass(rows.stop - rows.start, cos[:, rows], sin[:, rows], plan, rows.start, slots)

        cache_shape = (batch, config.num_key_value_heads, length + suffix_len, config.head_dim)
        cache = [(prefix.new_zeros(cache_shape), prefix.new_zeros(cache_shape)) for _ in self.layers]
        prefix_pass = (stream(slice(0, length), length), None)
        x = prefix.flatten(0, 1)
        for layer, layer_cache in zip(self.layers, cache):
            x, _ = layer(x, None, prefix_pass, layer_cache)

        suffix_pass = (None, stream(slice(length, length + suffix_len), length + suffix_len))
        dt = -1.0 / len(times)
        for time in times:
            conditioning = self.conditioning(torch.full((batch,), time, device=device)).per_token(horizon)
            suffix = self.embed_suffix(state, x_t, conditioning.condition)  # [B * S, D1]
            norms = conditioning.layer_norms or (None,) * len(self.layers)
            for layer, layer_cache, layer_norms in zip(self.layers, cache, norms):
                _, suffix = layer(None, suffix, suffix_pass, layer_cache, expert_norms=layer_norms)
            suffix = self.expert_final_norm(suffix, conditioning.final_norm).view(batch, suffix_len, width)
            velocity = self.action_out_proj(suffix[:, -horizon:]).float()
            x_t = x_t + dt * velocity
        return (x_t, cache) if return_cache else x_t


@functools.lru_cache(maxsize=None)
def _rounded_sqrt(width: int, dtype: torch.dtype) -> float:
    """sqrt(width) rounded to `dtype` (openpi scales text embeddings by `sqrt(D).astype(x.dtype)`)."""
    return float(torch.tensor(math.sqrt(width), dtype=dtype))
