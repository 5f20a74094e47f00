"""Raw robot observations -> model inputs and model actions -> robot actions: images, prompts, normalization
(imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
    from pi0_torch.processing.normalization import (
        NormStats,
        compute_norm_stats,
        load_openpi_norm_stats,
        save_openpi_norm_stats,
    )
    from pi0_torch.processing.processing_pi0 import PI0Processor
    from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor

_EXPORTS = {
    "FASTActionTokenizer": "pi0_torch.processing.fast_tokenizer",
    "NormStats": "pi0_torch.processing.normalization",
    "PI0FastProcessor": "pi0_torch.processing.processing_pi0_fast",
    "PI0Processor": "pi0_torch.processing.processing_pi0",
    "compute_norm_stats": "pi0_torch.processing.normalization",
    "load_openpi_norm_stats": "pi0_torch.processing.normalization",
    "save_openpi_norm_stats": "pi0_torch.processing.normalization",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
