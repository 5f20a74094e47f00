"""Raw robot observations -> model inputs and model actions -> robot actions: images, prompts, normalization."""

from pi0_torch.processing.normalization import NormStats, compute_norm_stats, load_openpi_norm_stats, save_openpi_norm_stats
from pi0_torch.processing.processing_pi0 import PI0Processor

__all__ = ["NormStats", "PI0Processor", "compute_norm_stats", "load_openpi_norm_stats", "save_openpi_norm_stats"]
