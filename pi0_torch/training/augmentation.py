"""openpi's training-time image augmentation, as torch ops on a batch (on the GPU when training there).

openpi augments every training sample (`models/model.py`, `preprocess_observation(train=True)`, with augmax 0.4.1):
each camera's image goes to [0, 1]; a camera whose name has no "wrist" is cropped to 95% of its size at a random
sub-pixel offset, resized back and rotated by up to 5 degrees, all in one bilinear resampling (augmax composes the
three into one coordinate map; outside the image is black); then every camera gets augmax's ColorJitter (brightness
0.3, contrast 0.4, hue 0.1, applied to half the images); then back to [-1, 1]. Here the same math, checked against
augmax's own outputs (`tests/fixtures/augmax_reference`, within 1e-5 on float images):

- the warp: output pixel (i, j) samples the input at
  `(y, x) = T S R (i - (H/2 - 0.5), j - (W/2 - 0.5)) + (H/2 - 0.5, W/2 - 0.5)` with `R` the rotation by `theta`
  (counter-clockwise as displayed, y down), `S = diag(ch / H, cw / W)` (crop 95%: `ch = int(0.95 H)`) and `T` the
  crop centre's offset `(cy, cx)`, uniform within the crop's slack; bilinear, zero outside (`grid_sample`);
- the colour jitter, in HSV: value `v` brightened (`v (1 + b)` for `b < 0`, else `v (1 - b) + b`), then through
  contrast's S-curve around 0.5 (`slant = tan((c + 1) pi / 4)`), the hue turned by `h`; saturation is drawn by augmax
  but has no effect there (augmax 0.4.1 discards it), and so here; no clipping.

Draws (`draw_augmentation`): per sample, from a random stream keyed by the sample's key (the trainer's `(seed,
step, position in the global batch)`), so runs are reproducible with `--seed` and independent across data-loader
workers and processes. As in openpi, every non-wrist camera of a sample gets the same crop, angle and jitter, and
every wrist camera the same jitter of its own (openpi reuses one key per sample for all cameras). A masked (absent)
camera is augmented like the others, as openpi does: it is black, and stays nearly so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

CROP_FRACTION = 0.95
MAX_ANGLE_DEGREES = 5.0
BRIGHTNESS, CONTRAST, HUE = 0.3, 0.4, 0.1  # ColorJitter's amounts (openpi's brightness and contrast, augmax's hue)
JITTER_PROBABILITY = 0.5  # augmax's default p, which openpi keeps


@dataclass
class AugmentationDraws:
    """One batch's random draws, per sample `[B]`: the warp of non-wrist cameras and a colour jitter for each kind of
    camera (index 0: non-wrist, 1: wrist)."""

    crop_offset: torch.Tensor  # float32 [B, 2]: (cy, cx), the crop centre's offset from the image centre, pixels
    angle: torch.Tensor  # float32 [B]: radians
    brightness: torch.Tensor  # float32 [B, 2]
    contrast: torch.Tensor  # float32 [B, 2]
    hue: torch.Tensor  # float32 [B, 2], in turns
    apply_jitter: torch.Tensor  # bool [B, 2]


def draw_augmentation(keys: Sequence[Sequence[int]], height: int, width: int) -> AugmentationDraws:
    """The draws of a batch: per sample, eleven uniform numbers of a stream keyed by the sample's key (a tuple of
    ints; `keyed_uniforms`)."""
    uniform = keyed_uniforms(keys, 11)  # [B, 11]
    slack = np.array([(height - int(CROP_FRACTION * height)) / 2, (width - int(CROP_FRACTION * width)) / 2])
    limit = math.radians(MAX_ANGLE_DEGREES)
    amounts = np.array([BRIGHTNESS, CONTRAST, HUE])
    offsets = slack * (2 * uniform[:, 0:2] - 1)  # [B, 2]
    angles = limit * (2 * uniform[:, 2] - 1)  # [B]
    jitters = amounts * (2 * uniform[:, 3:9].reshape(-1, 2, 3) - 1)  # [B, 2 kinds, 3 amounts]
    as_float = lambda array: torch.as_tensor(array, dtype=torch.float32)  # noqa: E731
    return AugmentationDraws(as_float(offsets), as_float(angles), as_float(jitters[..., 0]), as_float(jitters[..., 1]),
                             as_float(jitters[..., 2]), torch.as_tensor(uniform[:, 9:11] < JITTER_PROBABILITY))


def keyed_uniforms(keys: Sequence[Sequence[int]], count: int) -> np.ndarray:
    """`count` uniform numbers in [0, 1) per key (float64 `[len(keys), count]`, 53 random bits each): SplitMix64's
    stream (Steele, Lea and Flood, 2014) from a hash of the key's ints, all keys at once (a numpy generator per key
    cost as much as the images' augmentation on a demo-size CPU batch). Keys of one call have the same length."""
    with np.errstate(over="ignore"):  # (uint64 arithmetic wraps, as SplitMix64 means it to)
        state = np.zeros(len(keys), np.uint64)
        for part in np.asarray(keys, dtype=np.int64).reshape(len(keys), -1).T.astype(np.uint64):
            state = _splitmix64(state ^ part)
        bits = _splitmix64(state[:, None] + np.arange(1, count + 1, dtype=np.uint64) * _GOLDEN_GAMMA)
    return (bits >> np.uint64(11)).astype(np.float64) * 2.0**-53


_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)  # SplitMix64's increment


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's step and output mix: `x + gamma`, then two xor-shift-multiplies and a xor-shift (uint64)."""
    x = x + _GOLDEN_GAMMA
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def warp(images: torch.Tensor, crop_offset: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Crop to 95%, resize back and rotate, as one bilinear resampling: `images` `[N, 3, H, W]` in [0, 1], per image
    `crop_offset` `[N, 2]` (cy, cx) and `angle` `[N]` (radians). Outside the image counts as black."""
    height, width = images.shape[-2:]
    size = torch.tensor([height, width], dtype=torch.float32, device=angle.device)
    scale = torch.tensor([int(CROP_FRACTION * height), int(CROP_FRACTION * width)], dtype=torch.float32,
                         device=angle.device) / size
    cos, sin = torch.cos(angle.float()), torch.sin(angle.float())
    rotation = torch.stack([torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)], -2)  # [N, 2, 2], on (y, x)
    # output pixel (i, j) samples the input at `S R ((i, j) - centre) + offset + centre`; in grid_sample's coordinates
    # (align_corners=False: u = 2 (pixel - centre) / size) that is `diag(1 / size) S R diag(size) u + 2 offset / size`
    linear = scale[:, None] * rotation * size / size[:, None]  # [N, 2, 2], on (y, x)
    shift = 2 * crop_offset.float() / size  # [N, 2]
    theta = torch.cat([linear.flip(1, 2), shift.flip(1)[:, :, None]], -1)  # [N, 2, 3]: affine_grid's (x, y) order
    grid = F.affine_grid(theta.to(images.device), list(images.shape), align_corners=False)  # [N, H, W, 2]
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def color_jitter(images: torch.Tensor, brightness: torch.Tensor, contrast: torch.Tensor, hue: torch.Tensor,
                 apply: torch.Tensor | None = None) -> torch.Tensor:
    """augmax's ColorJitter on `images` `[N, 3, H, W]` in [0, 1] with per-image amounts `[N]`; images where `apply`
    `[N]` is False come back unchanged (None: every image is jittered)."""
    shape = (-1, 1, 1)
    red, green, blue = images.unbind(1)  # [N, H, W] each (elementwise: several times faster than max/min over dim 1)
    value = torch.maximum(torch.maximum(red, green), blue)
    spread = value - torch.minimum(torch.minimum(red, green), blue)
    saturation = (spread / value).nan_to_num_(0.0)  # (0 / 0: black)
    red_first = (red >= green) & (red >= blue)  # the first largest channel: red, else green, else blue
    green_first = ~red_first & (green >= blue)
    # the hue in sixths of a turn: 2 x the largest channel's index plus the next channel minus the one after it
    # (cyclically: g - b, b - r or r - g) over the spread; 0 / 0 for grey pixels
    sixths = torch.where(red_first, green - blue, torch.where(green_first, torch.add(blue - red, spread, alpha=2),
                                                              torch.add(red - green, spread, alpha=4)))
    sixths = sixths.div_(spread).nan_to_num_(0.0).add_(6 * hue.float().view(shape))

    # brightness b: v (1 + b) for b < 0, else v (1 - b) + b (per image, a scale and a shift)
    b = brightness.float()
    value = torch.addcmul(b.clamp(min=0).view(shape), value, torch.where(b < 0, 1 + b, 1 - b).view(shape))
    # contrast's S-curve around 0.5, slant = tan((c + 1) pi / 4): augmax's v / slant below `slant / (2 (1 + slant))`,
    # v / slant + 1 - 1 / slant above 1 minus that, slant (v - 0.5) + 0.5 between; the three lines meet at those
    # points, so the curve is the middle line clamped between the outer two (which is below depends on the slant)
    slant = torch.tan((contrast.float().view(shape) + 1) * (math.pi / 4))
    lower, shift = value / slant, 1 - 1 / slant  # the outer lines: `lower` and `lower + shift`
    middle = torch.addcmul(0.5 - 0.5 * slant, value, slant)
    value = middle.clamp_(lower + shift.clamp(max=0), lower.add_(shift.clamp(min=0)))

    k = sixths[:, None] + images.new_tensor([5.0, 3.0, 1.0]).view(1, 3, 1, 1)  # [N, 3, H, W]
    k = k.sub_(torch.floor(k / 6).mul_(6))  # (k mod 6: torch.remainder's float kernel takes several times longer)
    shade = torch.minimum(k, 4 - k).clamp_(0, 1)
    jittered = torch.addcmul(value[:, None], (value * saturation)[:, None], shade, value=-1)
    return jittered if apply is None else torch.where(apply.view(-1, 1, 1, 1), jittered, images)


def check_augmentable(pixel_values: torch.Tensor) -> None:
    """Refuse, by name, images the augmentation cannot take: it needs 3-channel float images `[B, C, 3, H, W]` in
    [-1, 1] (a processor's `pixel_values`). Reads the values' range from the device once."""
    if pixel_values.dim() != 5 or pixel_values.shape[2] != 3 or not pixel_values.is_floating_point():
        raise ValueError(f"augmentation takes 3-channel float images [B, C, 3, H, W] in [-1, 1], got shape "
                         f"{tuple(pixel_values.shape)} dtype {pixel_values.dtype} (--no-augment trains without it)")
    low, high = (float(value) for value in pixel_values.aminmax())
    if not -1.001 <= low <= high <= 1.001:
        raise ValueError(f"augmentation takes images in [-1, 1] (a processor's pixel_values), got values in "
                         f"[{low:.4g}, {high:.4g}] (--no-augment trains without it)")


def augment_images(pixel_values: torch.Tensor, camera_names: Sequence[str], draws: AugmentationDraws) -> torch.Tensor:
    """openpi's augmentation of a batch `pixel_values` `[B, C, 3, H, W]` in [-1, 1] (cameras in `camera_names`
    order) with `draws` (`draw_augmentation`); returns the augmented batch, same shape, in [-1, 1]."""
    batch, cameras, channels, height, width = pixel_values.shape
    if channels != 3 or not pixel_values.is_floating_point():
        raise ValueError(f"augmentation takes 3-channel float images [B, C, 3, H, W] in [-1, 1], got shape "
                         f"{tuple(pixel_values.shape)} dtype {pixel_values.dtype}")
    device = pixel_values.device
    kinds = [int("wrist" in name) for name in camera_names]  # per camera: 0 non-wrist, 1 wrist
    # camera-major [C * B, 3, H, W] in [0, 1]: one copy, then in place (the batch's own tensor is never written)
    images = torch.empty(cameras, batch, channels, height, width, device=device)
    images = torch.mul(pixel_values.transpose(0, 1), 0.5, out=images).add_(0.5).view(-1, channels, height, width)
    for index, kind in enumerate(kinds):
        if not kind:
            rows = slice(index * batch, (index + 1) * batch)
            images[rows] = warp(images[rows], draws.crop_offset, draws.angle)
    # one jitter over the images it applies to (half of them: augmax's p), each with its camera kind's amounts
    brightness, contrast, hue, apply = (torch.cat([getattr(draws, name)[:, kind] for kind in kinds]).to(device)
                                        for name in ("brightness", "contrast", "hue", "apply_jitter"))
    chosen = apply.nonzero()[:, 0]
    if len(chosen):
        images[chosen] = color_jitter(images[chosen], brightness[chosen], contrast[chosen], hue[chosen])
    images = images.mul_(2.0).sub_(1.0)
    return images.view(cameras, batch, channels, height, width).transpose(0, 1).to(pixel_values.dtype)
