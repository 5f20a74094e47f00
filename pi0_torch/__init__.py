"""pi0-torch: Physical Intelligence's π0 and π0.5 vision-language-action models in PyTorch."""

from transformers import AutoConfig, AutoModel

from .configuration_pi0 import PI0Config
from .modeling_pi0 import PI0ForActionGeneration, PI0Output

__version__ = "0.1.0"

AutoConfig.register(PI0Config.model_type, PI0Config, exist_ok=True)
AutoModel.register(PI0Config, PI0ForActionGeneration, exist_ok=True)

__all__ = ["PI0Config", "PI0ForActionGeneration", "PI0Output", "__version__"]
