"""Image preprocessing against openpi's resize_with_pad references (tests/fixtures/openpi/*/reference.npz `preproc/*`)."""

from __future__ import annotations

import multiprocessing
import re
import threading

import numpy as np
import pytest
import torch
from PIL import Image

from pi0_torch.processing import images
from pi0_torch.processing.images import missing_image, resize_with_pad, to_model_image, to_model_images

from conftest import FIXTURES


@pytest.fixture(scope="module")
def preproc() -> dict[str, np.ndarray]:
    with np.load(FIXTURES / "pi0_small" / "reference.npz") as reference:
        return {k: reference[k] for k in reference.files if k.startswith("preproc/resize")}


def test_uint8_matches_openpi_pil_pipeline(preproc: dict[str, np.ndarray]) -> None:
    source, expected = preproc["preproc/resize_in_uint8"], preproc["preproc/resize_out_uint8_pil"]  # [2,180,320,3]
    ours = resize_with_pad(source, 224, 224)
    assert ours.shape == expected.shape and ours.dtype == np.uint8
    diff = np.abs(ours.astype(int) - expected.astype(int)).max()
    assert diff <= 1, f"max gray-level difference {diff}"
    # torch uint8 in -> torch uint8 out, same values
    ours_torch = resize_with_pad(torch.from_numpy(source), 224, 224)
    assert ours_torch.dtype == torch.uint8 and np.array_equal(ours_torch.numpy(), ours)
    # openpi's JAX uint8 version rounds differently; it stays within one gray level of the PIL one
    assert np.abs(ours.astype(int) - preproc["preproc/resize_out_uint8_jax"].astype(int)).max() <= 1


def test_float_matches_openpi_jax(preproc: dict[str, np.ndarray]) -> None:
    source, expected = preproc["preproc/resize_in_float"], preproc["preproc/resize_out_float_jax"]
    ours = resize_with_pad(source, 224, 224)
    assert ours.shape == expected.shape and ours.dtype == np.float32
    assert np.abs(ours - expected).max() < 1e-2
    ours_torch = resize_with_pad(torch.from_numpy(source), 224, 224)
    assert isinstance(ours_torch, torch.Tensor) and torch.equal(ours_torch, torch.from_numpy(ours))


@pytest.mark.parametrize(
    ("shape", "content", "pads"),
    [
        # (h, w) -> resized (h', w') inside 224x224; pads = (top, bottom, left, right): the odd pixel goes bottom/right
        ((101, 300), (75, 224), (74, 75, 0, 0)),
        ((300, 101), (224, 75), (0, 0, 74, 75)),
        ((180, 320), (126, 224), (49, 49, 0, 0)),
        ((64, 48), (224, 168), (0, 0, 28, 28)),  # upscaling
        ((97, 97), (224, 224), (0, 0, 0, 0)),
    ],
)
@pytest.mark.parametrize("kind", ["uint8", "float"])
def test_padding_sides_for_odd_sizes(shape: tuple[int, int], content: tuple[int, int], pads: tuple[int, ...], kind: str) -> None:
    top, bottom, left, right = pads
    if kind == "uint8":
        image, black, white = np.full((*shape, 3), 255, np.uint8), 0, 255
    else:
        image, black, white = np.ones((*shape, 3), np.float32), -1.0, 1.0
    out = resize_with_pad(image, 224, 224)
    assert out.shape == (224, 224, 3)
    inside = out[top : 224 - bottom, left : 224 - right]
    assert inside.shape[:2] == content
    assert np.abs(inside.astype(np.float64) - white).max() < 1e-5  # antialiasing weights sum to 1 up to rounding
    border = np.ones((224, 224), bool)
    border[top : 224 - bottom, left : 224 - right] = False
    assert np.all(out[border] == black)


def test_target_size_and_batch_axes() -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, size=(2, 3, 50, 80, 3), dtype=np.uint8)
    out = resize_with_pad(frames, 32, 40)
    assert out.shape == (2, 3, 32, 40, 3)
    assert np.array_equal(out[1, 2], resize_with_pad(frames[1, 2], 32, 40))
    same = rng.integers(0, 256, size=(224, 224, 3), dtype=np.uint8)
    assert resize_with_pad(same, 224, 224) is same


def test_to_model_image_layouts_agree(preproc: dict[str, np.ndarray]) -> None:
    frame = preproc["preproc/resize_in_uint8"][0]  # [180, 320, 3]
    expected = np.moveaxis(preproc["preproc/resize_out_uint8_pil"][0].astype(np.float32) / 255 * 2 - 1, -1, 0)
    hwc = to_model_image(frame, 224)
    assert hwc.shape == (3, 224, 224) and hwc.dtype == np.float32
    assert np.abs(hwc - expected).max() <= 2 / 255 + 1e-6
    for other in (
        np.moveaxis(frame, -1, 0),  # [3, H, W]
        torch.from_numpy(frame),
        torch.from_numpy(frame).permute(2, 0, 1),
        Image.fromarray(frame),
        Image.fromarray(frame).convert("RGBA"),
    ):
        assert np.array_equal(to_model_image(other, 224), hwc)


def test_float_frames_in_both_ranges() -> None:
    rng = np.random.default_rng(1)
    unit = rng.random((90, 160, 3), dtype=np.float32)  # [0, 1]
    from_unit = to_model_image(unit, 224)
    from_signed = to_model_image(unit * 2 - 1, 224, float_range=(-1, 1))
    assert np.allclose(from_unit, from_signed, atol=1e-6)
    assert from_unit.min() >= -1 and from_unit.max() <= 1
    # matches the uint8 path of the same picture within quantization
    as_uint8 = np.round(unit * 255).astype(np.uint8)
    assert np.abs(to_model_image(as_uint8, 224) - from_unit).max() < 0.02
    chw_torch = torch.from_numpy(unit).permute(2, 0, 1).to(torch.bfloat16)
    assert np.abs(to_model_image(chw_torch, 224) - from_unit).max() < 0.02


def test_missing_image() -> None:
    blank = missing_image(224)
    assert blank.shape == (3, 224, 224) and blank.dtype == np.float32 and np.all(blank == -1)


@pytest.mark.parametrize(
    ("frame", "kwargs", "message"),
    [
        (np.zeros((32, 32, 3), np.uint16), {}, "expected dtype uint8 or float, got uint16"),
        (np.zeros((32, 32, 3), np.int64), {}, "expected dtype uint8 or float, got int64"),
        (np.zeros((32, 32, 3), bool), {}, "expected dtype uint8 or float, got bool"),
        (np.zeros((32, 32, 4), np.uint8), {}, "expected 3 color channels"),
        (np.zeros((32, 32), np.uint8), {}, r"expected one frame \[H, W, 3\] or \[3, H, W\], got shape \(32, 32\)"),
        (np.zeros((3, 32, 3), np.uint8), {}, "ambiguous"),
        (np.full((32, 32, 3), np.nan, np.float32), {}, "NaN or inf"),
        (np.full((32, 32, 3), 200.0, np.float32), {}, "pass a uint8 frame"),
        (np.full((32, 32, 3), -0.5, np.float32), {}, r"set float_image_range=\(-1, 1\)"),
        (np.full((32, 32, 3), -1.5, np.float32), {"float_range": (-1, 1)}, r"must be in \[-1, 1\]"),
        (np.zeros((32, 32, 3), np.float32), {"float_range": (0, 255)}, "must be"),
        ([[1, 2, 3]], {}, "expected a numpy array, torch tensor or PIL image, got list"),
    ],
)
def test_bad_frames(frame: object, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        to_model_image(frame, 224, name="images['base_0_rgb']", **kwargs)


def test_error_names_the_camera() -> None:
    with pytest.raises(ValueError, match=r"^images\['wrist'\]: "):
        to_model_image(np.zeros((8, 8, 3), np.int32), 224, name="images['wrist']")


def _camera_frames(count: int = 3) -> list[tuple[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [(f"images['cam{i}']", rng.integers(0, 256, (120 + 8 * i, 160, 3), dtype=np.uint8)) for i in range(count)]


def _converting_threads(monkeypatch: pytest.MonkeyPatch) -> set[str]:
    """The names of the threads that run `to_model_image` from now on."""
    names: set[str] = set()
    convert = images.to_model_image

    def recording(*args: object, **kwargs: object) -> np.ndarray:
        names.add(threading.current_thread().name)
        return convert(*args, **kwargs)

    monkeypatch.setattr(images, "to_model_image", recording)
    return names


def test_frames_converted_on_threads_equal_one_by_one(monkeypatch: pytest.MonkeyPatch) -> None:
    frames = _camera_frames()
    one_by_one = [to_model_image(frame, 224, name=name) for name, frame in frames]
    monkeypatch.setattr(images, "_usable_cores", lambda: 4)  # threads even on a one-core runner
    threads = _converting_threads(monkeypatch)
    together = to_model_images(frames, 224)
    assert threads and all(name.startswith("pi0-frames") for name in threads)
    assert len(together) == 3 and all(np.array_equal(a, b) for a, b in zip(together, one_by_one))


def test_frames_on_threads_report_the_first_bad_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(images, "_usable_cores", lambda: 4)
    frames = _camera_frames()
    frames[1] = ("images['cam1']", np.zeros((8, 8, 3), np.int32))
    frames[2] = ("images['cam2']", np.full((8, 8, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"^images\['cam1'\]: expected dtype uint8 or float"):
        to_model_images(frames, 224)


def test_frames_one_by_one_in_a_data_loader_worker_or_when_small(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(images, "_usable_cores", lambda: 4)
    threads = _converting_threads(monkeypatch)
    tiny = [(name, frame[:32, :32]) for name, frame in _camera_frames()]
    to_model_images(tiny, 28)  # 3 x 32 x 32 pixels: threads would cost more than they save
    assert threads == {threading.current_thread().name}
    monkeypatch.setattr(torch.utils.data, "get_worker_info", lambda: object())  # what a DataLoader worker sees
    to_model_images(_camera_frames(), 224)
    assert threads == {threading.current_thread().name}


def _convert_in_child(queue: multiprocessing.Queue) -> None:
    queue.put([frame.shape for frame in to_model_images(_camera_frames(), 224)])


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="needs fork")
def test_a_forked_process_converts_frames_with_a_pool_of_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    # a forked child inherits the parent's pool object but not its threads: work sent there would never run
    monkeypatch.setattr(images, "_usable_cores", lambda: 4)
    to_model_images(_camera_frames(), 224)  # the parent's pool, its threads started
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_convert_in_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=60) == [(3, 224, 224)] * 3
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0


@pytest.mark.parametrize("mode, values, expected", [
    ("I;16", np.full((8, 8), 1000, np.uint16), "a PIL image of mode 'I;16' (integer pixels"),
    ("I", np.full((8, 8), 70_000, np.int32), "a PIL image of mode 'I' (integer pixels"),
    ("F", np.full((8, 8), np.nan, np.float32), "contains NaN or inf"),
    ("F", np.full((8, 8), 3.0, np.float32), "float frame must be in [0, 1], got values in [3, 3]"),
    ("F", np.full((8, 8), 0.25, np.float32), None),
])
def test_pil_images_of_every_mode_mean_their_values_or_are_refused(mode: str, values: np.ndarray, expected: str | None) -> None:
    """Issue 38.8: PIL images of modes I;16, I and F became all-white or all-black frames (NaN too): integer modes are
    refused by name, as integer arrays are; mode F is a float frame, checked like one."""
    image = Image.fromarray(values) if mode == "I;16" else Image.fromarray(values, mode=mode)
    assert image.mode == mode
    if expected is None:
        np.testing.assert_allclose(to_model_image(image, 8), np.full((3, 8, 8), -0.5), atol=1e-6)
        return
    with pytest.raises(ValueError, match=re.escape(f"base_0_rgb: {expected}") if "[" in expected else f"base_0_rgb: {re.escape(expected)}"):
        to_model_image(image, 8, name="base_0_rgb")
