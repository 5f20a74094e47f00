"""mp4 video of uint8 frames (PyAV): the LeRobot writer's camera videos and `pi0-torch eval`'s rollout videos.

Needs `av`, which both `pip install 'pi0-torch[envs]'` and `'pi0-torch[train]'` bring.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

from pi0_torch.utils.extras import require_extra

require_extra("envs", __name__, modules=("av",))
import av


def encode_video(path: Path, frames: Sequence[np.ndarray], fps: int, codec: str) -> None:
    """Encode uint8 `[H, W, 3]` frames into an mp4 at `fps` (yuv420p, one frame per 1/fps second)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(codec, rate=fps)
        height, width = frames[0].shape[:2]
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.time_base = Fraction(1, fps)
        stream.codec_context.gop_size = 10
        if codec in ("libx264", "h264"):
            stream.options = {"crf": "8", "bf": "0"}
        for number, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(frame, format="rgb24")
            picture.pts = number
            container.mux(stream.encode(picture))
        container.mux(stream.encode(None))
