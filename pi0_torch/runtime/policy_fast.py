"""`PI0FastPolicy`: the π0-FAST member of the policy family (`pi0_torch.runtime.policy_base`: the same observation
checks, batching, warm-up and server interface as `PI0Policy`; the chunk comes from decoded FAST tokens).

`PI0Policy.from_pretrained(folder)` returns one for a π0-FAST folder, so `pi0-torch serve --model DIR` serves either
kind. openpi's π0-FAST configs use the cameras `base_0_rgb`, `base_1_rgb`, `wrist_0_rgb`.

```python
>>> import numpy as np
>>> from pi0_torch import FASTActionTokenizer, PI0FastConfig, PI0FastForActionGeneration, PI0FastProcessor
>>> from pi0_torch.processing.normalization import NormStats
>>> from pi0_torch.processing.tokenization import build_test_tokenizer
>>> rng = np.random.default_rng(0)
>>> fast = FASTActionTokenizer.fit([np.cumsum(rng.normal(0, .1, (10, 8)), 0) for _ in range(100)], vocab_size=256)
>>> stats = {key: NormStats(mean=np.zeros(8), std=np.ones(8), q01=-np.ones(8), q99=np.ones(8)) for key in ("state", "actions")}
>>> config = PI0FastConfig.from_preset("pi0_fast_small")
>>> processor = PI0FastProcessor.from_config(config, build_test_tokenizer(1024), fast, stats)
>>> policy = PI0FastPolicy(PI0FastForActionGeneration(config), processor, num_steps=4)
>>> observation = {"images": {"base_0_rgb": np.zeros((480, 640, 3), np.uint8)}, "state": np.zeros(8), "prompt": "pick up the fork"}
>>> policy.infer(observation)  # a random model decodes no chunk: withheld, naming the cause
Traceback (most recent call last):
...
pi0_torch.runtime.action_safety.UnsafeActionsError: the action chunk holds 80 NaN/inf values and was withheld; cause: the generated tokens decode to no action chunk (the logged warning shows them)

```
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np
import torch

from pi0_torch.models.configuration_base import SIZE_LIMITS
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.runtime.policy_base import BasePolicy, PreparedObservation
from pi0_torch.utils.validation import check_float

logger = logging.getLogger(__name__)


class PI0FastPolicy(BasePolicy):
    """[`PI0FastForActionGeneration`] + [`PI0FastProcessor`] behind openpi's policy interface: a [`BasePolicy`]
    whose chunks are decoded FAST tokens. It takes no real-time chunking requests (`previous_actions`, ...), and a
    request's `noise_seed` does not apply (no noise is drawn). Tokens that decode to no chunk give no actions: the
    chunk is withheld like a non-finite one (`UnsafeActionsError` naming the cause; the server replies
    `no actions: ...`), never returned as zeros.

    Args:
        model, processor: the π0-FAST model (on its device and dtype) and its processor.
        num_steps: the most tokens decoded per chunk (default `model.config.max_decoding_steps`; decoding stops
            earlier once every chunk of the batch emits EOS at the same step).
        seed: seeds the sampling when `temperature > 0` (greedy decoding needs none).
        compile: decode through `torch.compile` ([`PI0FastForActionGeneration.compile_decoding`]; CUDA graphs on
            CUDA); call [`warmup`] first. On CUDA with torch < 2.12, where inductor's graphs of the decoding step
            crashed the process, it replays hand-captured graphs instead (`cuda_graph`), with a warning.
        cuda_graph: on CUDA, replay the prefill and each decoded token as CUDA graphs captured by hand without a
            compiler ([`PI0FastForActionGeneration.capture_decoding`]); the first chunk of each batch size captures
            them and verifies them against eager decoding: call [`warmup`] first. With `compile` the compiled
            decoding's own graphs replay instead, where they can.
        temperature: 0 for greedy decoding (openpi's default), else sampling at this temperature.
    """

    model_class = PI0FastForActionGeneration
    processor_class = PI0FastProcessor
    num_steps_setting = "max_decoding_steps"
    max_num_steps = SIZE_LIMITS["max_decoding_steps"]

    def __init__(
        self,
        model: PI0FastForActionGeneration,
        processor: PI0FastProcessor,
        num_steps: int | None = None,
        seed: int | None = None,
        compile: bool = False,
        temperature: float = 0.0,
        cuda_graph: bool = False,
    ) -> None:
        super().__init__(model, processor, num_steps=num_steps, seed=seed)
        self.temperature = check_float("temperature", temperature, minimum=0.0)
        if cuda_graph and self.device.type != "cuda":
            raise ValueError(f"cuda_graph needs a CUDA device; this policy runs on {self.device}")
        if compile:
            reason = model.decoding_graphs_reason()
            if reason is not None:  # (inductor's graphs crash here: the hand-captured ones instead, said once)
                logger.warning("compile=True: decoding replays hand-captured CUDA graphs instead: %s", reason)
                cuda_graph = True
            else:
                model.compile_decoding(**({"mode": "reduce-overhead"} if self.device.type == "cuda" else {}))
        if cuda_graph and not model.decoding_compiled:  # (compiled decoding on CUDA replays inductor's graphs)
            model.capture_decoding()

    @property
    def compiled(self) -> bool:
        return self.model.decoding_compiled

    @property
    def captured(self) -> bool:
        """Whether decoding replays hand-captured CUDA graphs (`cuda_graph`)."""
        return self.model.decoding_captured

    @property
    def model_type(self) -> str:
        return "pi0_fast"

    def model_actions(self, batch: Mapping[str, torch.Tensor], warmup: bool = False) -> np.ndarray:
        """Decode tokens (greedy, or sampled at `temperature`) and extract the chunks `[B, horizon, action_dim]`; a
        chunk whose tokens do not decode is all NaN, so that `infer_prepared` withholds it (a warm-up logs it)."""
        tokens = self.model.generate_tokens(
            **batch,
            max_new_tokens=self.num_steps,
            temperature=self.temperature,
            generator=None if warmup else self.generator,
        )
        chunks = self.processor.extract_actions(tokens.cpu().numpy(), mark_undecodable=True)
        undecodable = int(np.isnan(chunks).any(axis=(1, 2)).sum())
        if warmup and undecodable:
            logger.warning("warm-up: the tokens generated for the blank observation decode to no action chunk (%d of "
                           "%d chunks); requests whose tokens do not decode get no actions ('no actions: ...'): if "
                           "real requests do too, check the model and its FAST tokenizer", undecodable, len(chunks))
        return chunks

    def _sampling_cause(self, prepared: PreparedObservation) -> str:
        """Why finite weights gave a chunk that is not finite: its tokens decode to no chunk (tokens are never NaN)."""
        return "the generated tokens decode to no action chunk (the logged warning shows them)"
