"""What fine-tuning π0-FAST adds to `pi0-torch train`: its processor, with a FAST tokenizer given or fitted to the
dataset's action chunks.

Everything else is the π0 run: the same dataset reader and collator (the processor decides the batch: prompt with
`Action: <FAST tokens>|<eos>`, block and loss masks), the same `Trainer` and recipe; the model's forward gives
openpi's loss (next-token cross-entropy on the action tokens), so no noise or flow time is drawn. `--lora` is
openpi's `gemma_2b_lora` (`pi0_torch.training.lora`): rank 16, alpha 16, per head on every Gemma projection, the rest
of the Gemma (embedding, norms) frozen and rounded to bf16, the vision tower and its projection trained in full.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pi0_torch.data.lerobot_dataset import LeRobotEpisodeDataset
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.processing.tokenization import PromptTokenizer

logger = logging.getLogger(__name__)

FIT = "fit"  # `--fast-tokenizer fit`: fit one to the training episodes
FAST_SCALE = 10  # the FAST paper's (and the public tokenizer's) DCT scale
FAST_VOCAB = 1024  # BPE vocabulary of a fitted tokenizer (at most what fits below the prompt vocabulary's end)


def model_space_chunks(encoder: PI0Processor, dataset: LeRobotEpisodeDataset) -> list[np.ndarray]:
    """Every action chunk of the dataset `[horizon, action_dim]` as the model sees it: converted, made relative to
    the state on the delta dims, normalized and padded by `encoder` (a processor with the run's settings)."""
    chunks = []
    for episode in dataset.iter_state_action_chunks():
        for state, actions in zip(episode["state"], episode["actions"]):
            model_state = encoder._model_space_state(np.asarray(state, np.float64))
            chunks.append(encoder._encode_actions(actions, model_state, ""))
    return chunks


def fit_action_tokenizer(
    encoder: PI0Processor, dataset: LeRobotEpisodeDataset, vocab_size: int, scale: float = FAST_SCALE
) -> FASTActionTokenizer:
    """A FAST tokenizer fitted to the dataset's model-space action chunks (see `model_space_chunks`)."""
    chunks = model_space_chunks(encoder, dataset)
    logger.info("fitting a FAST tokenizer (scale %s, vocab %d) to %d action chunks", scale, vocab_size, len(chunks))
    return FASTActionTokenizer.fit(chunks, scale=scale, vocab_size=vocab_size)


def build_fast_processor(
    config: PI0FastConfig,
    tokenizer: PromptTokenizer | str | Path,
    norm_stats: Mapping[str, NormStats] | None,
    dataset: LeRobotEpisodeDataset,
    action_tokenizer: FASTActionTokenizer | str | None,
    **settings: Any,
) -> PI0FastProcessor:
    """The π0-FAST processor of a run. `action_tokenizer`: a tokenizer, a FAST tokenizer folder, or `"fit"` (fitted
    to the dataset with a vocabulary that fits below the prompt vocabulary's special tokens). `settings`: the
    processor's robot settings (`state_dim`, `action_dim_robot`, `delta_action_mask`, `value_conversion`)."""
    if action_tokenizer is None:
        raise ValueError("π0-FAST needs a FAST tokenizer: --fast-tokenizer DIR (e.g. physical-intelligence/fast), or "
                         "--fast-tokenizer fit to fit one to the training episodes")
    if isinstance(action_tokenizer, str) and action_tokenizer == FIT:
        encoder = PI0Processor(
            tokenizer, camera_names=config.camera_names, norm_stats=norm_stats, model_action_dim=config.action_dim,
            action_horizon=config.action_horizon, **{"norm_mode": "quantile", **settings},
        )
        room = encoder.tokenizer.vocab_size - 1 - config.fast_skip_tokens
        action_tokenizer = fit_action_tokenizer(encoder, dataset, vocab_size=min(FAST_VOCAB, room))
    return PI0FastProcessor.from_config(config, tokenizer, action_tokenizer, norm_stats, **settings)
