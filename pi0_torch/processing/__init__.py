"""Raw robot observations -> model inputs and model actions -> robot actions: images, prompts, normalization."""

from pi0_torch.processing.normalization import NormStats, compute_norm_stats, load_openpi_norm_stats, save_openpi_norm_stats
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor

__all__ = [
    "FASTActionTokenizer",
    "NormStats",
    "PI0FastProcessor",
    "PI0Processor",
    "compute_norm_stats",
    "load_openpi_norm_stats",
    "save_openpi_norm_stats",
]
