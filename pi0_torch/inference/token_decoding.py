"""π0-FAST's decoding as it runs fast: `TokenDecoding`, the mixin that gives `PI0FastForActionGeneration` its
`generate_tokens` (as `pi0_torch.inference.sampling.ActionSampling` gives π0 its `generate_actions`).

The model computes the prefill (`prepare_decoding`) and one decoded token (`decode_step`) against a static k/v cache
(`DecodingCache`); this mixin loops over the tokens and chooses what runs them: the modules, the fused kernels
(`pi0_torch.inference.fast_decoding`), `torch.compile` (`compile_decoding`) or hand-captured CUDA graphs
(`capture_decoding`, `pi0_torch.inference.decoding_graphs`), each checked against eager decoding.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from pi0_torch.inference.checks import (VERIFY_TOLERANCE, bound, decoding_ops_reason, layers_reason,
                                        relative_deviation, setting_reason)
from pi0_torch.inference.fast_decoding import DecodingLayers
from pi0_torch.inference.layer_pass import SamplingWeights, decoder_sampling_weights

logger = logging.getLogger(__name__)


@dataclass
class DecodingCache:
    """Everything `decode_step` needs, built once per call of `generate_tokens` (nothing is allocated per token)."""

    keys: list[torch.Tensor]  # per layer [B, K, S, H], prefix k/v in slots [0, P), decoded tokens' after
    values: list[torch.Tensor]
    masks: torch.Tensor | None  # additive [B, 1, T, S]: row t = the slots the token decoded at step t sees (None: fused)
    cos: torch.Tensor  # [B, 1, T, H] RoPE of the decoded tokens' positions
    sin: torch.Tensor
    slots: torch.Tensor  # long [T]: slot of the token decoded at step t (P + t)
    first: torch.Tensor  # long [B]: the first slot decoded tokens see; the token of step t sees [first, P + t]
    fused: DecodingLayers | None  # what the fused kernels read of each layer (its k/v views of `keys` and `values`); None: modules


class TokenDecoding:
    """`generate_tokens` and its engine settings, for a model with `config`, `layers`, `dtype`, `_check_inputs`,
    `decoding_slots`, `prepare_decoding` and `decode_step` (`PI0FastForActionGeneration`). Engine state is set on
    first use, not in the model's `__init__`."""

    VERIFY_CALLS = 3  # `generate_tokens` calls checked against eager decoding after `compile_decoding`
    DECODING_KERNELS = ("auto", "torch", "triton")
    # engine state (class defaults until set on the instance)
    _compiled_decode_step: Any = None  # set by `compile_decoding`
    _compiled_prefill: Any = None
    _calls_to_verify = 0  # `generate_tokens` calls still to check against eager decoding
    _decoding_graphs: Any = None  # `DecodingGraphs` once `capture_decoding` is called
    _decoding_kernels = "auto"

    @torch.no_grad()
    def generate_tokens(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        token_ar_mask: torch.Tensor,
        max_new_tokens: int | None = None,
        temperature: float = 0.0,
        generator: torch.Generator | None = None,
        **unused: Any,
    ) -> torch.Tensor:
        """Decode up to `max_new_tokens` (default `config.max_decoding_steps`) tokens after the prompt.

        openpi's `sample_actions`: prefill once (`prepare_decoding`), then one token per step against the static
        k/v cache; greedy (`temperature=0`, the first of equal maxima) or sampled from `softmax(logits /
        temperature)` with `generator`. Decoding stops after the first step at which every row's new token is EOS
        (`config.eos_token_id`; None: never); the steps not run stay 0. The only host synchronization per token is
        that check. Decoded tokens attend as `decoding_kernels` says, and replay CUDA graphs after `capture_decoding`.

        Returns:
            long `[B, max_new_tokens]` token ids (`PI0FastProcessor.extract_actions` turns them into actions).
        """
        self._check_inputs(pixel_values, image_masks, input_ids, attention_mask, token_ar_mask)
        max_new_tokens = self.config.max_decoding_steps if max_new_tokens is None else int(max_new_tokens)
        if max_new_tokens < 1:
            raise ValueError(f"max_new_tokens must be >= 1, got {max_new_tokens}")
        if temperature < 0:
            raise ValueError(f"temperature must be >= 0, got {temperature}")
        slots = self.decoding_slots(pixel_values.shape[1], input_ids.shape[1], max_new_tokens)
        inputs = (pixel_values, image_masks, input_ids, attention_mask, token_ar_mask, max_new_tokens)
        eager = (self.prepare_decoding, self.decode_step)
        if self._compiled_prefill is None:  # (compiled decoding traces the modules: see `compile_decoding`)
            weights = functools.cache(lambda: decoder_sampling_weights(self.layers))  # (the call's plain-weights check,
            # made once where something reads it: the gate, then the fused layers)
            reason = self.decoding_kernels_reason(pixel_values.device, self.dtype, len(pixel_values), slots, weights)
            graphs = self._decoding_graphs if pixel_values.device.type == "cuda" else None
            functions = eager if graphs is None else (graphs.prepare, graphs.step)
            return self.decode(*functions, (*inputs, weights() if reason is None else None), temperature, generator)[0]
        inputs += (None,)  # (no fused layers)
        tokens, logits = self.decode(self._compiled_prefill, self._compiled_decode_step, inputs, temperature, generator)
        if self._calls_to_verify > 0:  # the compiled (CUDA graph) decoding against eager decoding of the same tokens
            self._calls_to_verify -= 1
            _, eager_logits = self.decode(*eager, inputs, temperature, None, forced=tokens)
            deviation = max(relative_deviation(got, want) for got, want in zip(logits, eager_logits))
            limit = bound(VERIFY_TOLERANCE, self.dtype)
            if not deviation <= limit:
                logger.warning("compiled decoding was refused: its logits deviate from eager decoding by %.3g of the "
                               "largest (bound %g); generate_tokens decodes eagerly from now on", deviation, limit)
                self.compile_decoding(disable=True)
                return self.decode(*eager, inputs, temperature, generator)[0]
        return tokens

    def decode(
        self,
        prepare: Callable[..., tuple[DecodingCache, torch.Tensor]],
        step: Callable[..., torch.Tensor],
        inputs: tuple[Any, ...],
        temperature: float,
        generator: torch.Generator | None,
        forced: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The decoding loop of `generate_tokens` with the given prefill and step functions (eager or compiled): the
        tokens `[B, max_new_tokens]` and the logits `[B, V]` each token was picked from. `inputs`: `prepare`'s
        arguments. `forced` `[B, T]`: feed these tokens instead of picking (to compare another decoding's logits along
        the same tokens)."""
        cache, logits = prepare(*inputs)
        batch, max_new_tokens = inputs[0].shape[0], inputs[5]
        output = torch.zeros(batch, max_new_tokens, dtype=torch.long, device=inputs[0].device)
        steps = torch.arange(max_new_tokens, device=inputs[0].device)
        seen = []
        for index in range(max_new_tokens):
            seen.append(logits.clone())  # (a compiled step's output is overwritten by its next replay)
            token = pick_token(logits, temperature, generator) if forced is None else forced[:, index]  # [B]
            output[:, index] = token
            eos = self.config.eos_token_id
            if index == max_new_tokens - 1 or (eos is not None and bool((token == eos).all())):
                break
            logits = step(cache, token, steps[index : index + 1])
        return output, seen

    @property
    def decoding_kernels(self) -> str:
        """What runs the decoder layers of each decoded token: "auto" (the fused Triton kernels around cuBLAS's GEMMs,
        `pi0_torch.inference.fast_decoding`, on CUDA in bf16 / fp16 where the kernels passed their check against the
        torch references on that device; else "torch"), "torch" (the modules, SDPA with a
        mask; the CPU's path) or "triton" (the fused kernels wherever triton runs them, `TRITON_INTERPRET=1` included,
        or a `ValueError` naming why not). The check runs once per batch size and cache length (triton compiles the
        kernels per class of arguments). The prefill always runs the modules."""
        return self._decoding_kernels

    @decoding_kernels.setter
    def decoding_kernels(self, kernels: str) -> None:
        if kernels not in self.DECODING_KERNELS:
            raise ValueError(f"decoding_kernels must be one of {self.DECODING_KERNELS}, got {kernels!r}")
        self._decoding_kernels = kernels

    def decoding_kernels_reason(self, device: torch.device, dtype: torch.dtype, batch: int = 1, slots: int = 1_104,
                                weights: Callable[[], list[SamplingWeights]] | None = None) -> str | None:
        """Why decoding `batch` rows on `device` in `dtype` with caches of `slots` (`decoding_slots`; the default is a
        full-size cache) does not run the fused kernels (None: it does); see `decoding_kernels`. `weights`: the call's
        plain-weights check, as a function that makes it once (made here where not given). Raises `ValueError` with
        the reason where "triton" was asked for and cannot be had."""
        config = self.config

        def check() -> str | None:
            plain = decoder_sampling_weights(self.layers) if weights is None else weights()
            return layers_reason(config.num_key_value_heads, config.head_dim, plain) or decoding_ops_reason(
                device, dtype, config.num_attention_heads, config.head_dim, config.intermediate_size, batch, slots)

        return setting_reason(self._decoding_kernels, "decoding_kernels", device, dtype, check)

    @property
    def decoding_compiled(self) -> bool:
        """Whether `generate_tokens` runs through `torch.compile` (see `compile_decoding`)."""
        return self._compiled_decode_step is not None

    def compile_decoding(self, verify: bool = True, **compile_kwargs: Any) -> None:
        """Opt in to `torch.compile` for `generate_tokens`: the prefill as one graph and the per-token step as
        another (the same graph for every step). `compile_kwargs` go to `torch.compile`, with `fullgraph=True`
        unless given; on CUDA `mode="reduce-overhead"` replays each as a CUDA graph. With `verify` (the default) the
        first `VERIFY_CALLS` calls of `generate_tokens` (CUDA graphs record on the second and replay from the third)
        also decode eagerly along the same tokens; logits that deviate beyond
        `pi0_torch.inference.checks.VERIFY_TOLERANCE` switch compiling off with a warning, and that call returns the
        eager tokens. `compile_decoding(disable=True)` goes back to eager.

        Compiled decoding traces the modules whatever `decoding_kernels` says (inductor makes its own kernels; the
        fused kernels are eager decoding's). Raises `ValueError` for `mode="reduce-overhead"` where
        `decoding_graphs_reason` names why it cannot run."""
        if compile_kwargs.get("disable"):
            self._compiled_decode_step = self._compiled_prefill = None
            self._calls_to_verify = 0
            return
        reason = self.decoding_graphs_reason() if compile_kwargs.get("mode") == "reduce-overhead" else None
        if reason is not None:
            raise ValueError(f"compile_decoding(mode='reduce-overhead'): {reason}")
        compile_kwargs.setdefault("fullgraph", True)
        self._decoding_graphs = None  # (one or the other: see `capture_decoding`)
        self._compiled_prefill = torch.compile(self.prepare_decoding, **compile_kwargs)
        self._compiled_decode_step = torch.compile(self.decode_step, **compile_kwargs)
        self._calls_to_verify = self.VERIFY_CALLS if verify else 0

    @property
    def decoding_captured(self) -> bool:
        """Whether `generate_tokens` on CUDA replays CUDA graphs of its prefill and each decoded token (see
        `capture_decoding`)."""
        return self._decoding_graphs is not None

    def capture_decoding(self, disable: bool = False, verify: bool = True) -> None:
        """Opt in to CUDA graphs for `generate_tokens` on CUDA, captured by hand (no compiler, so also on torch < 2.12,
        where `compile_decoding(mode="reduce-overhead")` is refused): for each input signature (batch size, cameras,
        prompt length, new tokens, dtype, `decoding_kernels`' choice) the prefill and the per-token step are recorded
        once, on the first call (warm-up runs, then the captures), and replayed by every later call and token. Inputs
        are copied into the graphs' static buffers. A model moved to another device or dtype captures again; on the
        CPU decoding stays eager.

        Every graph is verified when captured (`verify=True`): the first replays must give the logits of an eager
        prefill and an eager step of the same token within `pi0_torch.inference.checks.VERIFY_TOLERANCE`; graphs that
        do not, or that CUDA refuses to record, are refused with a warning and their signature decodes eagerly from
        then on. Switches `compile_decoding` off (and `compile_decoding` switches this off).
        `capture_decoding(disable=True)` goes back to eager. See `pi0_torch.inference.decoding_graphs`."""
        from pi0_torch.inference.decoding_graphs import DecodingGraphs

        if disable:
            self._decoding_graphs = None
            return
        self.compile_decoding(disable=True)
        self._decoding_graphs = DecodingGraphs(self, verify)

    def decoding_graphs_reason(self) -> str | None:
        """Why compiled decoding cannot replay as CUDA graphs here (`compile_decoding(mode="reduce-overhead")`; None:
        it can, or the model is not on CUDA). On CUDA with torch before 2.12 inductor's CUDA-graph partition of the
        decoding step crashes the process: SIGSEGV in its static triton launcher, or with that launcher off a
        `TypeError` for a kernel argument that is no pointer (torch 2.11, triton 3.6, an H200; the modules and the
        fused kernels alike). Newer torch is not measured on a GPU yet."""
        if self.device.type != "cuda" or torch.__version__ >= (2, 12):  # (torch's TorchVersion compares with tuples)
            return None
        return (f"π0-FAST's compiled decoding replayed as CUDA graphs crashes the process with torch {torch.__version__} "
                "(SIGSEGV in inductor's CUDA-graph partition of the decoding step, seen with torch 2.11 on an H200); "
                "replay hand-captured CUDA graphs instead (capture_decoding(), no compiler), decode eagerly, or "
                "compile without CUDA graphs (compile_decoding())")

    def _apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """`nn.Module._apply` (what `.to()`, `.cuda()`, `.half()` ... run): captured decoding graphs read the old
        tensors, so they are dropped and captured again on the next call."""
        if getattr(self, "_decoding_graphs", None) is not None:
            self._decoding_graphs.clear()
        return super()._apply(fn, *args, **kwargs)


def pick_token(logits: torch.Tensor, temperature: float, generator: torch.Generator | None) -> torch.Tensor:
    """The next token `[B]` from logits `[B, V]`: argmax (first of equal maxima) or a draw at `temperature`."""
    if temperature == 0:
        return logits.argmax(dim=-1)
    probs = torch.softmax(logits.float() / temperature, dim=-1)
    return torch.multinomial(probs, 1, generator=generator)[:, 0]
