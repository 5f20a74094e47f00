"""pi0-torch: Physical Intelligence's π0, π0.5 and π0-FAST vision-language-action models in PyTorch."""

from transformers import AutoConfig, AutoModel

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration, PI0Output
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration, PI0FastOutput
from pi0_torch.processing.normalization import NormStats, compute_norm_stats, load_openpi_norm_stats, save_openpi_norm_stats
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor

__version__ = "0.1.0"

AutoConfig.register(PI0Config.model_type, PI0Config, exist_ok=True)
AutoModel.register(PI0Config, PI0ForActionGeneration, exist_ok=True)
AutoConfig.register(PI0FastConfig.model_type, PI0FastConfig, exist_ok=True)
AutoModel.register(PI0FastConfig, PI0FastForActionGeneration, exist_ok=True)

__all__ = [
    "FASTActionTokenizer",
    "NormStats",
    "PI0Config",
    "PI0FastConfig",
    "PI0FastForActionGeneration",
    "PI0FastOutput",
    "PI0FastProcessor",
    "PI0ForActionGeneration",
    "PI0Output",
    "PI0Processor",
    "__version__",
    "compute_norm_stats",
    "load_openpi_norm_stats",
    "save_openpi_norm_stats",
]
