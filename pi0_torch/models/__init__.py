"""The models: configurations, the π0 / π0.5 network and its flow-matching pieces, and π0-FAST."""

from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration, PI0Output
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration, PI0FastOutput

__all__ = [
    "PI0Config",
    "PI0FastConfig",
    "PI0FastForActionGeneration",
    "PI0FastOutput",
    "PI0ForActionGeneration",
    "PI0Output",
    "fast_preset_names",
    "preset_names",
]
