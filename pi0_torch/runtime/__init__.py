"""Running a policy: one observation in, actions out (`PI0Policy`), and openpi's websocket server (imported on first
use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.runtime.observation_formats import ObservationError, ObservationFormat
    from pi0_torch.runtime.policy import PI0Policy

_EXPORTS = {
    "ObservationError": "pi0_torch.runtime.observation_formats",
    "ObservationFormat": "pi0_torch.runtime.observation_formats",
    "PI0Policy": "pi0_torch.runtime.policy",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
