"""The models: configurations, the π0 / π0.5 network and its flow-matching pieces, and π0-FAST (imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.models.configuration_pi0 import PI0Config, preset_names
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig, fast_preset_names
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration, PI0Output
    from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration, PI0FastOutput

_EXPORTS = {
    "PI0Config": "pi0_torch.models.configuration_pi0",
    "PI0FastConfig": "pi0_torch.models.configuration_pi0_fast",
    "PI0FastForActionGeneration": "pi0_torch.models.modeling_pi0_fast",
    "PI0FastOutput": "pi0_torch.models.modeling_pi0_fast",
    "PI0ForActionGeneration": "pi0_torch.models.modeling_pi0",
    "PI0Output": "pi0_torch.models.modeling_pi0",
    "fast_preset_names": "pi0_torch.models.configuration_pi0_fast",
    "preset_names": "pi0_torch.models.configuration_pi0",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
