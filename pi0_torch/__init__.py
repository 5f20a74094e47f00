"""pi0-torch: Physical Intelligence's π0, π0.5 and π0-FAST vision-language-action models in PyTorch.

The public names below are imported when first used (`pi0_torch.utils.lazy`), so `import pi0_torch` and the
`pi0-torch` command start without importing torch; `AutoConfig` / `AutoModel` know the models once `pi0_torch` is
imported (`pi0_torch.models.auto_registration`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.models import auto_registration
from pi0_torch.utils import quiet_imports
from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.shipped_policy import demo_policy_dir
    from pi0_torch.models.configuration_pi0 import PI0Config
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
    from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration, PI0Output
    from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration, PI0FastOutput
    from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
    from pi0_torch.processing.normalization import NormStats, compute_norm_stats, load_openpi_norm_stats, save_openpi_norm_stats
    from pi0_torch.processing.processing_pi0 import PI0Processor
    from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor

__version__ = "0.1.0"

_EXPORTS = {
    "FASTActionTokenizer": "pi0_torch.processing.fast_tokenizer",
    "NormStats": "pi0_torch.processing.normalization",
    "PI0Config": "pi0_torch.models.configuration_pi0",
    "PI0FastConfig": "pi0_torch.models.configuration_pi0_fast",
    "PI0FastForActionGeneration": "pi0_torch.models.modeling_pi0_fast",
    "PI0FastOutput": "pi0_torch.models.modeling_pi0_fast",
    "PI0FastProcessor": "pi0_torch.processing.processing_pi0_fast",
    "PI0ForActionGeneration": "pi0_torch.models.modeling_pi0",
    "PI0Output": "pi0_torch.models.modeling_pi0",
    "PI0Processor": "pi0_torch.processing.processing_pi0",
    "compute_norm_stats": "pi0_torch.processing.normalization",
    "demo_policy_dir": "pi0_torch.shipped_policy",
    "load_openpi_norm_stats": "pi0_torch.processing.normalization",
    "save_openpi_norm_stats": "pi0_torch.processing.normalization",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = [*sorted(_EXPORTS), "__version__"]

auto_registration.install()
quiet_imports.install()
