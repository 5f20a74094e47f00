"""Running a policy: one observation in, actions out (`PI0Policy`), and openpi's websocket server."""

from pi0_torch.runtime.observation_formats import ObservationError, ObservationFormat
from pi0_torch.runtime.policy import PI0Policy

__all__ = ["ObservationError", "ObservationFormat", "PI0Policy"]
