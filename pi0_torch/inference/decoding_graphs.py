"""π0-FAST's decoding as CUDA graphs, captured by hand (no compiler): `PI0FastForActionGeneration.capture_decoding`.

Eager decoding is bound by the host's launches: the prefill (SigLIP on every camera, the prompt through the decoder) is
about a thousand of them, and each decoded token about two hundred more. Neither reads the device from the host, and
neither's shapes change from call to call of one input signature (batch size, cameras, prompt length, new tokens,
dtype, kernels) or, for the step, from token to token (the token's step and slot are device values). So each signature
gets two graphs, recorded once:

- the prefill: `prepare_decoding` on static copies of the inputs, its cache and the first token's logits copied into
  static buffers (the step's cache, allocated outside the graph);
- the step: `decode_step` on that static cache, a static token and step, into static logits.

A call copies its inputs in and replays the prefill, then per token copies the token and step in and replays the step.
Both graphs are recorded by `graphs.GraphRecorder` and verified when captured, against the last warm-up runs (eager
prefill, eager step of the same token); see `TokenDecoding.capture_decoding`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from pi0_torch.inference.graphs import GraphCaptureError, GraphRecorder, replay_refusal

if TYPE_CHECKING:
    from pi0_torch.inference.token_decoding import DecodingCache, TokenDecoding

logger = logging.getLogger(__name__)


@dataclass
class CapturedDecoding:
    prefill: Any  # torch.cuda.CUDAGraph: the prefill of `inputs` into `cache` and `first_logits`
    inputs: list[torch.Tensor]  # static pixel_values, image_masks, input_ids, attention_mask, token_ar_mask
    first_logits: torch.Tensor  # [B, V]: the logits that pick the first token
    step: Any  # torch.cuda.CUDAGraph: `decode_step(cache, token, step_index)` into `logits`
    cache: DecodingCache  # the static cache (the prefill writes it, each step writes its token's k/v)
    token: torch.Tensor  # long [B]: the token a step replay feeds
    step_index: torch.Tensor  # long [1]: its step
    logits: torch.Tensor  # [B, V]: where a step replay writes the next token's logits


def cache_tensors(cache: DecodingCache) -> list[torch.Tensor]:
    """Every tensor of `cache`, in a fixed order (the absent mask left out)."""
    tensors = [*cache.keys, *cache.values, cache.cos, cache.sin, cache.slots, cache.first]
    return tensors + ([] if cache.masks is None else [cache.masks]) + ([] if cache.fused is None else cache.fused.tensors())


def input_signature(inputs: tuple[Any, ...]) -> tuple[Any, ...]:
    """What a call's graphs are specialised to: `prepare_decoding`'s inputs (five tensors, then the number of new
    tokens and the fused layers' weights), each tensor by shape, dtype and device, and whether the fused kernels run."""
    return (*((tuple(tensor.shape), tensor.dtype, tensor.device) for tensor in inputs[:5]), inputs[5], inputs[6] is not None)


class DecodingGraphs:
    """The captured prefill and step graphs of one model, by input signature, and the signatures refused at capture.

    `prepare` and `step` stand in for `prepare_decoding` and `decode_step` in `PI0FastForActionGeneration.decode`."""

    def __init__(self, model: TokenDecoding, verify: bool = True) -> None:
        self.model = model
        self.verify = verify  # compare each graph's first replay with an eager run (see the module docstring)
        self.graphs: dict[tuple[Any, ...], CapturedDecoding] = {}
        self.refused: dict[tuple[Any, ...], str] = {}  # signature -> why its graphs were refused: it decodes eagerly
        self.replays: dict[int, CapturedDecoding] = {}  # id(static cache) -> its graphs (what `step` looks up)
        self.recorder = GraphRecorder()

    def clear(self) -> None:
        """Drop every graph (the model's tensors moved, or its kernels changed)."""
        self.graphs.clear()
        self.refused.clear()
        self.replays.clear()
        self.recorder = GraphRecorder()

    def prepare(self, *inputs: Any) -> tuple[DecodingCache, torch.Tensor]:
        """`prepare_decoding(*inputs)`: a replay of the signature's prefill graph (captured and verified on first use)
        into its static cache, which `step` continues from, and the first token's logits (overwritten by the next
        call's prefill); eagerly where the signature's graphs were refused."""
        key = input_signature(inputs)
        if key in self.refused:
            return self.model.prepare_decoding(*inputs)
        captured = self.graphs.get(key)
        if captured is None:
            try:
                captured, eager_first, eager_step = self._capture(inputs)
            except GraphCaptureError as error:
                captured, refusal = None, f"CUDA could not record them ({error})"
            else:  # (the prefill's first logits, then the step's on the replayed prefill's cache)
                refusal, dtype = None, self.model.dtype
                if self.verify:
                    refusal = (replay_refusal(captured.prefill, captured.first_logits, eager_first, dtype,
                                              "the prefill's", "an eager run", "logit")
                               or replay_refusal(captured.step, captured.logits, eager_step, dtype, "the step's",
                                                 "an eager run", "logit"))
            if refusal is not None:
                self.refused[key] = refusal
                batch, cameras = inputs[0].shape[:2]
                logger.warning("the CUDA graphs of π0-FAST's decoding (batch %d, %d cameras, %d prompt tokens, %d new "
                               "tokens) were refused: %s; it decodes eagerly from now on", batch, cameras,
                               inputs[2].shape[1], inputs[5], refusal)
                return self.model.prepare_decoding(*inputs)
            self.graphs[key] = self.replays[id(captured.cache)] = captured
        with torch.inference_mode():
            torch._foreach_copy_(captured.inputs, list(inputs[:5]))
            captured.prefill.replay()
        return captured.cache, captured.first_logits

    def step(self, cache: DecodingCache, token: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """`decode_step(cache, token, step)`: a replay of the step graph whose static cache `cache` is (its logits are
        overwritten by the next replay), or the eager step for any other cache."""
        captured = self.replays.get(id(cache))
        if captured is None or captured.cache is not cache:
            return self.model.decode_step(cache, token, step)
        with torch.inference_mode():
            captured.token.copy_(token)
            captured.step_index.copy_(step)
            captured.step.replay()
        return captured.logits

    def _capture(self, inputs: tuple[Any, ...]) -> tuple[CapturedDecoding, torch.Tensor, torch.Tensor]:
        """Record the prefill and the step of `inputs`' signature: the graphs with their static buffers (an eager
        prefill of `inputs` allocates them), and the last warm-up runs' logits (prefill, then the step feeding the
        most likely first token at step 0, whose slot the call's own first step writes again)."""
        tensors, settings = list(inputs[:5]), inputs[5:]
        with torch.inference_mode():
            static_inputs = [tensor.clone() for tensor in tensors]
            cache, first_logits = self.model.prepare_decoding(*static_inputs, *settings)

            def prefill() -> torch.Tensor:
                fresh, logits = self.model.prepare_decoding(*static_inputs, *settings)
                torch._foreach_copy_([*cache_tensors(cache), first_logits], [*cache_tensors(fresh), logits])
                return first_logits

            prefill_graph, _, eager_first = self.recorder.record(prefill, self.model.device)
            token = first_logits.argmax(dim=-1)  # [B]
            step_index = torch.zeros(1, dtype=torch.long, device=token.device)
            step_graph, logits, eager_step = self.recorder.record(
                lambda: self.model.decode_step(cache, token, step_index), self.model.device)
        captured = CapturedDecoding(prefill_graph, static_inputs, first_logits, step_graph, cache, token, step_index, logits)
        return captured, eager_first, eager_step
