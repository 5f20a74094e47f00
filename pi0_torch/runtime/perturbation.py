"""`pi0-torch eval --perturb`: held-out episodes seen through a bumped camera and other light, to check what
training-time augmentation buys (`pi0_torch.training.augmentation`, openpi's).

Each episode draws, from its own seed, one shift of every non-wrist camera's frame by up to `shift` pixels each way
(the frame translated, its edge rows and columns repeated: a camera moved on its mount) and one brightness, contrast
and saturation factor in `[1 - jitter, 1 + jitter]` for every camera (the light of another room); the whole episode
keeps them. The same seeds give the same perturbations, so policies compare on equal terms.

```python
>>> import numpy as np
>>> frames = {"base_0_rgb": np.full((8, 8, 3), 100, np.uint8)}
>>> perturbed = Perturbation(shift=2, jitter=0.0).for_episode(7)(frames)
>>> perturbed["base_0_rgb"].shape, int(perturbed["base_0_rgb"].mean())
((8, 8, 3), 100)

```
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

MAX_SHIFT = 64  # pixels
MAX_JITTER = 0.9


@dataclass(frozen=True)
class Perturbation:
    shift: int = 4  # pixels each way, non-wrist cameras
    jitter: float = 0.2  # brightness, contrast and saturation factors in [1 - jitter, 1 + jitter], every camera

    def for_episode(self, seed: int) -> Callable[[Mapping[str, Any]], dict[str, Any]]:
        """The perturbation of the episode of `seed`: a function of its frames (camera -> uint8 `[H, W, 3]` or
        `[3, H, W]`) that returns them perturbed."""
        rng = np.random.default_rng([seed, 0x5EED])
        drawn: dict[str, tuple[int, int, float, float, float]] = {}  # camera -> (dy, dx, brightness, contrast, saturation)

        def perturb(frames: Mapping[str, Any]) -> dict[str, Any]:
            out = {}
            for camera in sorted(frames):  # (sorted: the same draws whatever the order of the frames)
                if camera not in drawn:
                    dy, dx = (0, 0) if "wrist" in camera else (int(v) for v in rng.integers(-self.shift, self.shift + 1, 2))
                    factors = rng.uniform(1 - self.jitter, 1 + self.jitter, 3)
                    drawn[camera] = (dy, dx, *map(float, factors))
                out[camera] = _perturbed(np.asarray(frames[camera]), *drawn[camera])
            return out

        return perturb


def _perturbed(frame: np.ndarray, dy: int, dx: int, brightness: float, contrast: float, saturation: float) -> np.ndarray:
    """`frame` (uint8, channels last or first) translated by `(dy, dx)` with its edges repeated, then colour-jittered."""
    channels_first = frame.ndim == 3 and frame.shape[0] == 3 and frame.shape[-1] != 3
    image = np.moveaxis(frame, 0, -1) if channels_first else frame
    height, width = image.shape[:2]
    padded = np.pad(image, ((abs(dy), abs(dy)), (abs(dx), abs(dx)), (0, 0)), mode="edge")
    image = padded[abs(dy) - dy : abs(dy) - dy + height, abs(dx) - dx : abs(dx) - dx + width].astype(np.float32)
    image = image * brightness
    image = (image - image.mean()) * contrast + image.mean()
    gray = image @ np.array([0.299, 0.587, 0.114], np.float32)
    image = gray[..., None] + (image - gray[..., None]) * saturation
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(np.moveaxis(image, -1, 0) if channels_first else image)


def parse_perturbation(text: str) -> Perturbation:
    """`--perturb SHIFT[,JITTER]` (e.g. `4,0.2`) as a `Perturbation`; a `ValueError` naming the option otherwise."""
    parts = text.split(",")
    try:
        shift = int(parts[0])
        jitter = float(parts[1]) if len(parts) > 1 else Perturbation.jitter
    except ValueError:
        raise ValueError(f"--perturb: expected SHIFT[,JITTER] (pixels, fraction), e.g. 4,0.2; got {text!r:.40}") from None
    if len(parts) > 2 or not 0 <= shift <= MAX_SHIFT or not 0 <= jitter <= MAX_JITTER:
        raise ValueError(f"--perturb: SHIFT must be in [0, {MAX_SHIFT}] pixels and JITTER in [0, {MAX_JITTER}], got "
                         f"{text!r:.40}")
    return Perturbation(shift, jitter)
