"""Camera frames -> the model's image tensors: resize-with-pad and conversion to channels-first [-1, 1].

Accepted frames (one camera, one time step):

- `PIL.Image.Image` of an 8-bit mode (converted to RGB) or mode 'F' (float, as a float frame); integer modes ('I',
  'I;16': depth, 16-bit) are refused by name ([`pil_frame`]);
- `numpy.ndarray` or `torch.Tensor`, channels last `[H, W, 3]` or channels first `[3, H, W]` (a frame whose first
  and last axes are both 3 is ambiguous and rejected), with dtype
  - `uint8`: values 0..255 (openpi's data pipeline);
  - float: values in `float_range`, `(0, 1)` by default (LeRobot / torchvision frames, and what openpi's policy input
    transforms assume for float frames) or `(-1, 1)` (already model range). A float frame outside its declared range
    (by more than 1e-3) is rejected: values up to 255 mean an unconverted uint8 frame, negative values under `(0, 1)`
    mean a frame that is already in [-1, 1].

Resizing follows openpi (`openpi_client.image_tools.resize_with_pad`, used by openpi's `ResizeImages` transform):
scale by `min(height / h, width / w)` keeping the aspect ratio (`int` truncation of the new size), bilinear with
antialiasing when shrinking, then pad with black (0 for uint8, -1 for [-1, 1] floats); when the padding is odd the
extra row/column goes to the bottom/right. uint8 frames are resized with PIL exactly as openpi's data pipeline does;
float frames are resized in float32 with `torch.nn.functional.interpolate(..., antialias=True)`, which agrees with
openpi's `jax.image.resize` version to ~1e-5 (and float frames are not quantized to uint8 first, unlike openpi's
policy transforms, a difference of at most one gray level).

`to_model_images` converts several frames (an observation's cameras) on a few threads at once: PIL and numpy release
the GIL while they resize and scale, so a policy computer's cores share the work. Three 480x640 frames take 4-6 ms
on one core of the development machine, half of the 10 ms that a whole chunk is meant to take on a GPU. The result
is the same as converting the frames one by one.

```python
>>> import numpy as np
>>> frame = np.full((180, 320, 3), 255, np.uint8)
>>> out = resize_with_pad(frame, 224, 224)
>>> out.shape, out[0, 0].tolist(), out[112, 112].tolist()
((224, 224, 3), [0, 0, 0], [255, 255, 255])
>>> x = to_model_image(frame, 224)
>>> x.shape, float(x.min()), float(x.max())
((3, 224, 224), -1.0, 1.0)

```
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, TypeVar, Union

import numpy as np
from PIL import Image

from pi0_torch.utils.optional import is_torch_tensor
from pi0_torch.utils.validation import check_frame_size

if TYPE_CHECKING:  # (imported where used: uint8 frames are resized without torch, `pi0_torch.utils.optional`)
    import torch

FLOAT_RANGES: tuple[tuple[float, float], ...] = ((0.0, 1.0), (-1.0, 1.0))
RANGE_TOLERANCE = 1e-3
MAX_FRAME_THREADS = 8  # threads of `to_model_images` (at most one per usable core)
MIN_PIXELS_FOR_THREADS = 100_000  # below it (tiny simulator frames) starting the threads costs more than it saves

ImageT = TypeVar("ImageT", np.ndarray, "torch.Tensor")
Frame = Union[np.ndarray, "torch.Tensor", Image.Image]


def _resized_size(height: int, width: int, target_height: int, target_width: int) -> tuple[int, int]:
    ratio = max(width / target_width, height / target_height)
    # at least one pixel: a 1x20000 strip would truncate to 0 rows (where openpi's resize fails)
    return max(1, int(height / ratio)), max(1, int(width / ratio))


def _padding(resized: int, target: int) -> tuple[int, int]:
    before = (target - resized) // 2
    return before, target - resized - before  # the odd pixel goes after (bottom / right)


def resize_with_pad(images: ImageT, height: int, width: int) -> ImageT:
    """Resize channels-last images `[..., h, w, c]` to `[..., height, width, c]`, keeping the aspect ratio (pad black).

    uint8 images (numpy or torch) are resized with PIL's bilinear filter (openpi's data pipeline) and padded with 0;
    float images must be in [-1, 1] (as in openpi's `image_tools.resize_with_pad`) and are padded with -1. The output
    has the input's type and dtype. Images already at the target size are returned unchanged.
    """
    if images.ndim < 3:
        raise ValueError(f"images must be [..., h, w, c], got shape {tuple(images.shape)}")
    cur_height, cur_width = int(images.shape[-3]), int(images.shape[-2])
    check_frame_size("images", cur_height, cur_width)
    if (cur_height, cur_width) == (height, width):
        return images
    new_height, new_width = _resized_size(cur_height, cur_width, height, width)
    top, bottom = _padding(new_height, height)
    left, right = _padding(new_width, width)
    is_torch = is_torch_tensor(images)

    if images.dtype == np.uint8 or (is_torch and str(images.dtype) == "torch.uint8"):
        array = images.cpu().numpy() if is_torch else images
        flat = array.reshape(-1, *array.shape[-3:])
        out = np.zeros((flat.shape[0], height, width, flat.shape[-1]), np.uint8)
        for i, image in enumerate(flat):
            pil = Image.fromarray(np.ascontiguousarray(image[..., 0] if image.shape[-1] == 1 else image))
            resized = np.asarray(pil.resize((new_width, new_height), resample=Image.BILINEAR))
            out[i, top : top + new_height, left : left + new_width] = resized.reshape(new_height, new_width, -1)
        out = out.reshape(*array.shape[:-3], height, width, array.shape[-1])
        if is_torch:
            import torch

            return torch.from_numpy(out).to(images.device)
        return out

    import torch  # (float images: resized in float32 with torch's antialiased bilinear filter)
    import torch.nn.functional as F

    tensor = images if is_torch else torch.from_numpy(np.ascontiguousarray(images))
    if not tensor.is_floating_point():
        raise ValueError(f"images must be uint8 or float, got dtype {images.dtype}")
    lead = tensor.shape[:-3]
    nchw = tensor.reshape(-1, cur_height, cur_width, tensor.shape[-1]).permute(0, 3, 1, 2).float()
    resized = F.interpolate(nchw, size=(new_height, new_width), mode="bilinear", align_corners=False, antialias=True)
    padded = F.pad(resized.clamp(-1.0, 1.0), (left, right, top, bottom), value=-1.0)
    out = padded.permute(0, 2, 3, 1).reshape(*lead, height, width, tensor.shape[-1]).to(tensor.dtype)
    return out if is_torch else out.numpy()


def _channels_last(array: np.ndarray | torch.Tensor, name: str) -> np.ndarray | torch.Tensor:
    """[H, W, 3] or [3, H, W] -> [H, W, 3]."""
    shape = tuple(array.shape)
    if len(shape) != 3:
        raise ValueError(f"{name}: expected one frame [H, W, 3] or [3, H, W], got shape {shape}")
    first, last = shape[0] == 3, shape[-1] == 3
    if first and last:
        raise ValueError(f"{name}: shape {shape} is ambiguous (channels first or last?); pass an [H, W, 3] frame")
    if last:
        return array
    if first:
        return array.permute(1, 2, 0) if is_torch_tensor(array) else np.moveaxis(array, 0, -1)
    raise ValueError(f"{name}: expected 3 color channels ([H, W, 3] or [3, H, W]), got shape {shape}")


def to_model_image(
    frame: Frame, size: int | tuple[int, int], float_range: Sequence[float] = (0.0, 1.0), name: str = "image"
) -> np.ndarray:
    """One camera frame (see the module docstring for what is accepted) -> float32 `[3, H, W]` in [-1, 1].

    `size` is the model's image size (an int for square images, or `(height, width)`). `name` is used in errors.
    """
    height, width = (size, size) if isinstance(size, int) else size
    low, _ = check_float_range(float_range)
    frame = _checked_frame(frame, float_range, name)
    if frame.dtype == np.uint8:
        model = resize_with_pad(frame, height, width).astype(np.float32) / 255.0 * 2.0 - 1.0
    else:
        model = resize_with_pad(frame * 2.0 - 1.0 if low == 0.0 else frame, height, width)
    return np.ascontiguousarray(np.moveaxis(model, -1, 0), dtype=np.float32)


def to_uint8_frame(
    frame: Frame, size: int | tuple[int, int], float_range: Sequence[float] = (0.0, 1.0), name: str = "image"
) -> np.ndarray:
    """One camera frame -> uint8 `[H, W, 3]` at the model's size: what an exported graph takes
    (`pi0_torch.deploy`). A uint8 frame is resized exactly as [`to_model_image`] resizes it (so the graph's
    `x / 255 * 2 - 1` gives its very values); a float frame is rounded to uint8 first, as openpi's policy transforms
    do (at most half a gray level from `to_model_image`'s float path). Needs no torch."""
    height, width = (size, size) if isinstance(size, int) else size
    low, _ = check_float_range(float_range)
    frame = _checked_frame(frame, float_range, name)
    if frame.dtype != np.uint8:
        unit = (frame + 1.0) / 2.0 if low == -1.0 else frame  # [0, 1]
        frame = np.round(unit * 255.0).astype(np.uint8)
    return np.ascontiguousarray(resize_with_pad(frame, height, width))


def _checked_frame(frame: Frame, float_range: Sequence[float], name: str) -> np.ndarray:
    """A frame as a channels-last numpy array `[h, w, 3]`: uint8, or float32 within `float_range` (clipped to it
    after the tolerance check); `ValueError` naming `name` otherwise."""
    low, high = check_float_range(float_range)
    if isinstance(frame, Image.Image):
        frame = pil_frame(frame, name)
    elif not (isinstance(frame, np.ndarray) or is_torch_tensor(frame)):
        raise ValueError(f"{name}: expected a numpy array, torch tensor or PIL image, got {type(frame).__name__}")
    frame = _channels_last(frame, name)
    check_frame_size(name, int(frame.shape[0]), int(frame.shape[1]))
    if is_torch_tensor(frame):
        frame = frame.detach().cpu()
        if str(frame.dtype) == "torch.bfloat16":
            frame = frame.float()
        frame = frame.numpy()
    if frame.dtype == np.uint8:
        return frame
    if not np.issubdtype(frame.dtype, np.floating):
        raise ValueError(f"{name}: expected dtype uint8 or float, got {frame.dtype}")
    frame = frame.astype(np.float32)
    if not np.all(np.isfinite(frame)):
        raise ValueError(f"{name}: contains NaN or inf")
    lo, hi = float(frame.min()), float(frame.max())
    if lo < low - RANGE_TOLERANCE or hi > high + RANGE_TOLERANCE:
        hint = ""
        if hi > 1.0 + RANGE_TOLERANCE:
            hint = " (values above 1 look like 0..255: pass a uint8 frame)"
        elif low == 0.0 and lo >= -1.0 - RANGE_TOLERANCE:
            hint = " (looks like a frame already in [-1, 1]: set float_image_range=(-1, 1))"
        raise ValueError(f"{name}: float frame must be in [{low:g}, {high:g}], got values in [{lo:.4g}, {hi:.4g}]{hint}")
    return np.clip(frame, low, high)


def pil_frame(image: Image.Image, name: str = "image") -> np.ndarray:
    """A PIL image as the frame array its values mean: 8-bit modes ('RGB', 'L', 'P', 'RGBA', ...) as uint8 `[H, W, 3]`
    (PIL's RGB conversion), 'F' (32-bit float, one channel) as float32 `[H, W, 3]` (then checked against the float
    range like any float frame). The integer modes ('I', 'I;16', ...: depth or 16-bit images) are refused by name:
    PIL's RGB conversion clips them to white or black, and an integer array of the same values is refused too."""
    if image.mode == "F":
        return np.repeat(np.asarray(image, dtype=np.float32)[..., None], 3, axis=-1)
    if image.mode.startswith("I"):
        raise ValueError(
            f"{name}: a PIL image of mode {image.mode!r} (integer pixels, e.g. depth or 16-bit): expected an 8-bit image "
            "(mode 'RGB' or 'L'; scale the values to 0..255) or float values in [0, 1] (mode 'F')"
        )
    return np.asarray(image.convert("RGB"))


def to_model_images(
    frames: Sequence[tuple[str, Frame]], size: int | tuple[int, int], float_range: Sequence[float] = (0.0, 1.0)
) -> list[np.ndarray]:
    """`to_model_image` of each `(name, frame)`, in order, on several threads where the machine has cores to spare.

    Threads are used for two frames or more with `MIN_PIXELS_FOR_THREADS` pixels in all (each frame's input or
    output, the larger), except inside a `DataLoader` worker (its processes already share the cores). A bad frame
    raises the same `ValueError` as `to_model_image`, the first bad one in order.
    """
    def convert(item: tuple[str, Frame]) -> np.ndarray:
        name, frame = item
        return to_model_image(frame, size, float_range, name)

    height, width = (size, size) if isinstance(size, int) else size
    pixels = sum(max(_pixel_count(frame), height * width) for _, frame in frames)
    if len(frames) < 2 or pixels < MIN_PIXELS_FOR_THREADS or _usable_cores() < 2 or _in_data_loader_worker():
        return [convert(item) for item in frames]
    return list(_frame_pool().map(convert, frames))


def _pixel_count(frame: Any) -> int:
    if isinstance(frame, Image.Image):
        return frame.width * frame.height
    shape = getattr(frame, "shape", ())
    return math.prod(shape) // 3 if len(shape) == 3 else 0  # (a bad frame: `to_model_image` says why)


def _in_data_loader_worker() -> bool:
    """Whether this process is a torch `DataLoader` worker (never where torch is not imported)."""
    if "torch" not in sys.modules:
        return False
    from torch.utils.data import get_worker_info

    return get_worker_info() is not None


def _usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


_frame_pools: dict[int, ThreadPoolExecutor] = {}  # process id -> its pool (a forked child must not use its parent's)


def _frame_pool() -> ThreadPoolExecutor:
    pid = os.getpid()
    if pid not in _frame_pools:
        _frame_pools.clear()
        _frame_pools[pid] = ThreadPoolExecutor(
            max_workers=min(MAX_FRAME_THREADS, _usable_cores()), thread_name_prefix="pi0-frames"
        )
    return _frame_pools[pid]


def missing_image(size: int | tuple[int, int]) -> np.ndarray:
    """The stand-in for an absent camera: all -1 (black), float32 `[3, H, W]` (its image mask is False)."""
    height, width = (size, size) if isinstance(size, int) else size
    return np.full((3, height, width), -1.0, np.float32)


def check_float_range(float_range: Any) -> tuple[float, float]:
    pair = tuple(float(v) for v in float_range)
    if pair not in FLOAT_RANGES:
        raise ValueError(f"float_image_range must be (0, 1) or (-1, 1), got {tuple(float_range)}")
    return pair
