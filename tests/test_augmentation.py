"""openpi's training-time image augmentation (`pi0_torch.training.augmentation`) against augmax's own outputs
(`tests/fixtures/augmax_reference`, recorded by `tests/fixtures/make_augmax_fixture.py` with openpi's pinned jax and augmax):
the same images for the same parameters within 1e-5, and parameters drawn from the same distributions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pi0_torch.training.augmentation import (AugmentationDraws, augment_images, check_augmentable, color_jitter,
                                             draw_augmentation, warp)

FIXTURE = Path(__file__).parent / "fixtures" / "augmax_reference" / "augmax_reference.npz"
CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")


@pytest.fixture(scope="module")
def augmax() -> dict[str, np.ndarray]:
    with np.load(FIXTURE) as arrays:
        return {key: arrays[key] for key in arrays.files}


def channels_first(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(array, -1, -3)))


def test_the_warp_is_augmax_crop_resize_rotate(augmax: dict[str, np.ndarray]) -> None:
    """Crop corners, fractional offsets, angles of 0, ±5 and 4.9 degrees: one resampling, as augmax composes them."""
    settings = len(augmax["geom/theta_rad"])
    images = channels_first(augmax["geom/in"])[None].repeat(settings, 1, 1, 1)
    offsets = torch.from_numpy(np.stack([augmax["geom/crop_cy"], augmax["geom/crop_cx"]], -1))
    warped = warp(images, offsets, torch.from_numpy(augmax["geom/theta_rad"]))
    assert float((warped - channels_first(augmax["geom/out"])).abs().max()) <= 1e-5


def test_the_colour_jitter_is_augmax_color_jitter(augmax: dict[str, np.ndarray]) -> None:
    """Each amount at its range's ends, contrast 0, saturation alone (no effect in augmax 0.4.1), mixed amounts."""
    settings = len(augmax["cj/hue"])
    images = channels_first(augmax["cj/in"])[None].repeat(settings, 1, 1, 1)
    jittered = color_jitter(images, torch.from_numpy(augmax["cj/brightness"]), torch.from_numpy(augmax["cj/contrast"]),
                            torch.from_numpy(augmax["cj/hue"]), torch.ones(settings, dtype=torch.bool))
    assert float((jittered - channels_first(augmax["cj/out"])).abs().max()) <= 1e-5
    unchanged = color_jitter(images[:1], *(torch.ones(1) * 0.2 for _ in range(3)), torch.zeros(1, dtype=torch.bool))
    assert torch.equal(unchanged, images[:1])  # (not applied: the very pixels, no colour-space round trip)


def test_openpis_whole_augmentation_for_the_draws_augmax_made(augmax: dict[str, np.ndarray]) -> None:
    """openpi's preprocessing with `train=True` of three cameras (two wrists), three seeds, two samples each."""
    inputs = torch.stack([channels_first(augmax[f"pipe/in/{camera}"]) for camera in CAMERAS], dim=1)  # [B, C, 3, H, W]
    for seed in range(len(augmax["pipe/seeds"])):
        def drawn(camera: str, name: str) -> torch.Tensor:
            return torch.from_numpy(augmax[f"pipe/params/{camera}/{name}"][seed])

        kinds = ("base_0_rgb", "left_wrist_0_rgb")  # (openpi: both wrists draw alike)
        draws = AugmentationDraws(
            torch.stack([drawn("base_0_rgb", "crop_cy"), drawn("base_0_rgb", "crop_cx")], -1), drawn("base_0_rgb", "theta_rad"),
            *(torch.stack([drawn(camera, name) for camera in kinds], -1) for name in ("brightness", "contrast", "hue", "apply")),
        )
        augmented = augment_images(inputs, CAMERAS, draws)
        for index, camera in enumerate(CAMERAS):
            expected = channels_first(augmax[f"pipe/out/{camera}"][seed])
            assert float((augmented[:, index] - expected).abs().max()) <= 1e-5, (seed, camera)


def test_the_draws_follow_augmaxs_distributions(augmax: dict[str, np.ndarray]) -> None:
    """Ranges, spread and the jitter's rate as augmax's 4,096 recorded draws (224 x 224), independent across samples,
    parameters and kinds of camera; reproducible from the keys."""
    height, width = (int(size) for size in augmax["dist/image_hw"])
    keys = [(7, 2, 0, position) for position in range(4096)]
    ours = draw_augmentation(keys, height, width)
    theirs = {name: augmax[f"dist/base_0_rgb/{name}"] for name in ("crop_cy", "crop_cx", "theta_rad", "brightness", "contrast", "hue")}
    mine = {"crop_cy": ours.crop_offset[:, 0], "crop_cx": ours.crop_offset[:, 1], "theta_rad": ours.angle,
            "brightness": ours.brightness[:, 0], "contrast": ours.contrast[:, 0], "hue": ours.hue[:, 0]}
    for name, values in mine.items():
        values, reference = values.numpy(), theirs[name]
        limit = np.abs(reference).max()
        assert np.abs(values).max() <= limit * 1.001 and np.abs(values).max() >= limit * 0.99, name  # the same range
        assert np.allclose(np.quantile(values, [0.1, 0.5, 0.9]), np.quantile(reference, [0.1, 0.5, 0.9]), atol=0.05 * limit), name
    assert abs(float(ours.apply_jitter.float().mean()) - float(augmax["dist/base_0_rgb/apply"].mean())) < 0.05
    columns = np.stack([*(value.numpy() for value in mine.values()), ours.brightness[:, 1].numpy(),
                        ours.apply_jitter[:, 0].float().numpy(), ours.apply_jitter[:, 1].float().numpy()])
    correlation = np.corrcoef(columns) - np.eye(len(columns))
    assert np.abs(correlation).max() < 0.06  # parameters and kinds of camera independent
    assert abs(np.corrcoef(mine["theta_rad"][:-1], mine["theta_rad"][1:])[0, 1]) < 0.06  # samples independent
    again = draw_augmentation(keys[:5], height, width)
    assert torch.equal(again.angle, ours.angle[:5]) and not torch.equal(again.angle, draw_augmentation([(8, *k[1:]) for k in keys[:5]], height, width).angle)


def test_images_the_augmentation_cannot_take_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"3-channel float images \[B, C, 3, H, W\]"):
        check_augmentable(torch.zeros(2, 1, 1, 8, 8))
    with pytest.raises(ValueError, match=r"in \[-1, 1\] .* got values in \[0, 255\]"):
        check_augmentable(torch.full((2, 1, 3, 8, 8), 255.0).index_fill_(0, torch.tensor([0]), 0.0))
    check_augmentable(torch.zeros(2, 1, 3, 8, 8))
