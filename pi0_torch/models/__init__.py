"""The models: configurations, the π0 / π0.5 network and its flow-matching pieces."""

from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration, PI0Output

__all__ = ["PI0Config", "PI0ForActionGeneration", "PI0Output", "preset_names"]
