"""Observation layouts a policy server accepts, and their mapping to pi0-torch's default layout.

The default layout is what [`PI0Policy.infer`] takes:

    {"images": {camera_name: HxWx3 uint8 frame}, "state": 1-D float array, "prompt": str}

Robot stacks written for openpi send other keys. An [`ObservationFormat`] says where each piece lives in an incoming
message. As a JSON file (`pi0-torch serve --obs-format my_robot.json`):

    {
      "images": {"base_0_rgb": "observation/exterior_image_1_left",
                 "left_wrist_0_rgb": "observation/wrist_image_left"},
      "optional_images": [],
      "state": ["observation/joint_position", "observation/gripper_position"],
      "state_sizes": [7, 1],
      "prompt": "prompt"
    }

- A *source* is a string (one top-level key, taken verbatim, slashes included: openpi's LIBERO and DROID clients send
  flat keys such as `"observation/image"`) or a list of strings (a path into nested dicts: `["images", "cam_high"]`).
- `images` is either a dict {model camera name: source}, or one source whose value is itself a dict
  {model camera name: frame} (the default layout). In the dict form every camera is required unless listed in
  `optional_images`; a model camera that is not mapped, or optional and absent, is fed as a missing (masked) camera.
- `state` is a list of sources; their 1-D values are concatenated in order (DROID: joints, then gripper).
  `state_sizes` (optional, one length per source, `null` for any) refuses a source of another length: the total
  alone cannot tell 1 joint + 7 gripper values from 7 joints + 1 gripper.
- `prompt` is a source; a message without it gets the processor's default prompt (`--default-prompt`), if any.

The optional real-time chunking fields of [`PI0Policy`] (`previous_actions`, `inference_delay`, `execution_horizon`,
`rtc_method`) and `noise_seed` are top-level keys in every layout and passed on as they are.

Frames are passed on as they come; [`PI0Processor`] accepts what openpi's input transforms accept (HxWx3 or 3xHxW,
uint8 or float in [0, 1]) and checks them. Keys of a message that the format does not name are ignored, as openpi
does.

```python
>>> import numpy as np
>>> fmt = ObservationFormat.from_preset("droid")
>>> message = {
...     "observation/exterior_image_1_left": np.zeros((224, 224, 3), np.uint8),
...     "observation/wrist_image_left": np.zeros((3, 224, 224), np.uint8),
...     "observation/joint_position": np.zeros(7),
...     "observation/gripper_position": np.zeros(1),
...     "prompt": "pick up the cup",
... }
>>> obs = fmt.to_default(message)
>>> sorted(obs["images"]), obs["state"].shape, obs["prompt"]
(['base_0_rgb', 'left_wrist_0_rgb'], (8,), 'pick up the cup')

```
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Union

import numpy as np

from pi0_torch.utils.validation import check_int

CHUNK_FIELDS = ("previous_actions", "inference_delay", "execution_horizon", "rtc_method", "noise_seed")
Source = Union[str, tuple[str, ...]]  # a top-level key, or a path of keys into nested dicts


class ObservationError(ValueError):
    """An observation that cannot be used; the message names the field, what was expected and what came."""


@dataclasses.dataclass(frozen=True)
class ObservationFormat:
    """Where the images, state and prompt of an incoming observation live (see the module docstring)."""

    name: str
    images: Source | Mapping[str, Source]
    state: tuple[Source, ...]
    prompt: Source = "prompt"
    optional_images: frozenset[str] = frozenset()
    state_sizes: tuple[int | None, ...] = ()  # the length of each state source (None: any); () checks none

    def __post_init__(self) -> None:
        if self.state_sizes and len(self.state_sizes) != len(self.state):
            raise ValueError(f"observation format {self.name!r}: 'state_sizes' gives {len(self.state_sizes)} lengths "
                             f"for {len(self.state)} state sources; expected one per source")
        for size in self.state_sizes:
            if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
                raise ValueError(f"observation format {self.name!r}: 'state_sizes' holds {size!r}; expected "
                                 "positive integers or null")

    @classmethod
    def from_preset(cls, name: str) -> ObservationFormat:
        """A built-in layout: `default`, `libero`, `droid` or `aloha` (openpi's example clients), or for π0-FAST's
        cameras `libero_fast`, `droid_fast`, `aloha_fast`."""
        if name not in PRESETS:
            raise ValueError(f"unknown observation format {name!r}; expected one of {', '.join(PRESETS)} or a .json path")
        return PRESETS[name]

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any], name: str = "custom") -> ObservationFormat:
        """Build a format from its JSON form (keys `images`, `state`, optional `state_sizes`, `prompt`,
        `optional_images`)."""
        unknown = set(spec) - {"images", "state", "state_sizes", "prompt", "optional_images"}
        if unknown:
            raise ValueError(f"observation format {name!r}: unknown keys {sorted(unknown)}")
        for required in ("images", "state"):
            if required not in spec:
                raise ValueError(f"observation format {name!r}: missing key {required!r}")
        images = spec["images"]
        if isinstance(images, Mapping):
            images = {str(camera): _source(source, f"images.{camera}") for camera, source in images.items()}
            if not images:
                raise ValueError(f"observation format {name!r}: 'images' maps no camera")
        else:
            images = _source(images, "images")
        state = spec["state"]
        if isinstance(state, str) or not isinstance(state, Sequence) or not state:
            raise ValueError(f"observation format {name!r}: 'state' must be a non-empty list of sources, got {state!r}")
        sizes = spec.get("state_sizes") or []
        if isinstance(sizes, str) or not isinstance(sizes, Sequence):
            raise ValueError(f"observation format {name!r}: 'state_sizes' must be a list of lengths, one per state "
                             f"source, got {sizes!r}")
        optional = spec.get("optional_images", [])
        if isinstance(optional, str) or not isinstance(optional, Sequence):
            raise ValueError(f"observation format {name!r}: 'optional_images' must be a list of camera names")
        if isinstance(images, Mapping) and set(optional) - set(images):
            raise ValueError(f"observation format {name!r}: optional_images {sorted(set(optional) - set(images))} "
                             "are not mapped in 'images'")
        return cls(
            name=name,
            images=images,
            state=tuple(_source(s, f"state[{i}]") for i, s in enumerate(state)),
            prompt=_source(spec.get("prompt", "prompt"), "prompt"),
            optional_images=frozenset(str(c) for c in optional),
            state_sizes=tuple(sizes),
        )

    @classmethod
    def from_json(cls, path: str | Path) -> ObservationFormat:
        """Load a format from a JSON file (see the module docstring for the schema)."""
        path = Path(path)
        with open(path, encoding="utf-8") as f:
            return cls.from_dict(json.load(f), name=path.stem)

    @classmethod
    def resolve(cls, name_or_path: str) -> ObservationFormat:
        """A preset name, or the path of a JSON file when the argument ends in `.json`."""
        if name_or_path.endswith(".json"):
            return cls.from_json(name_or_path)
        return cls.from_preset(name_or_path)

    def check_cameras(self, camera_names: Sequence[str]) -> None:
        """Fail early when the format maps a camera the model does not have."""
        if isinstance(self.images, Mapping):
            unknown = set(self.images) - set(camera_names)
            if unknown:
                raise ValueError(f"observation format {self.name!r} maps cameras {sorted(unknown)} that the model does "
                                 f"not have; model cameras: {list(camera_names)}")

    def describe(self) -> dict[str, Any]:
        """The format as plain JSON-able data (sent to clients in the server metadata)."""
        def plain(source: Source) -> str | list[str]:
            return source if isinstance(source, str) else list(source)

        images = {c: plain(s) for c, s in self.images.items()} if isinstance(self.images, Mapping) else plain(self.images)
        return {
            "name": self.name,
            "images": images,
            "optional_images": sorted(self.optional_images),
            "state": [plain(s) for s in self.state],
            **({"state_sizes": list(self.state_sizes)} if self.state_sizes else {}),
            "prompt": plain(self.prompt),
        }

    def to_default(self, message: Mapping[str, Any]) -> dict[str, Any]:
        """Pick images, state and prompt out of `message` into the default layout.

        Frames are passed through; the state comes out as one 1-D float64 array (the policy checks values and sizes);
        an absent prompt comes out as None.
        Raises [`ObservationError`] naming the missing or malformed field.
        """
        if not isinstance(message, Mapping):
            raise ObservationError(f"observation must be a dict, got {type(message).__name__}")
        chunk_fields = {name: message[name] for name in CHUNK_FIELDS if name in message}  # the same in every layout
        return {
            "images": self._images(message),
            "state": self._state(message),
            "prompt": self._prompt(message),
            **chunk_fields,
        }

    def _images(self, message: Mapping[str, Any]) -> dict[str, np.ndarray]:
        if isinstance(self.images, Mapping):
            frames = {}
            for camera, source in self.images.items():
                value = _lookup(message, source)
                if value is _MISSING:
                    if camera in self.optional_images:
                        continue
                    raise ObservationError(f"missing image {_name(source)!r} (camera {camera!r})")
                frames[camera] = value
        else:
            value = _lookup(message, self.images)
            if value is _MISSING:
                raise ObservationError(f"missing {_name(self.images)!r}: a dict {{camera name: frame}}")
            if not isinstance(value, Mapping):
                raise ObservationError(f"{_name(self.images)!r} must be a dict {{camera name: image}}, "
                                       f"got {type(value).__name__}")
            frames = {str(camera): frame for camera, frame in value.items()}
        if not frames:
            raise ObservationError("observation holds no image")
        return frames

    def _state(self, message: Mapping[str, Any]) -> np.ndarray:
        parts = []
        for index, source in enumerate(self.state):
            value = _lookup(message, source)
            if value is _MISSING:
                raise ObservationError(f"missing state field {_name(source)!r}")
            array = np.asarray(value)
            if array.dtype.kind not in "biuf":
                raise ObservationError(f"state field {_name(source)!r} must be numeric, got dtype {array.dtype}")
            if array.ndim > 1:
                raise ObservationError(f"state field {_name(source)!r} must be 1-D, got shape {array.shape}")
            size = self.state_sizes[index] if self.state_sizes else None
            if size is not None and array.size != size:
                raise ObservationError(f"state field {_name(source)!r} must hold {size} values ({self.name} format), "
                                       f"got {array.size}")
            parts.append(array.astype(np.float64).reshape(-1))  # (in float32, 1e308 would already be inf)
        return np.concatenate(parts)

    def _prompt(self, message: Mapping[str, Any]) -> str | None:
        value = _lookup(message, self.prompt)
        if value is _MISSING:
            return None  # the processor falls back to its default prompt, or says that one is required
        if isinstance(value, np.ndarray) and value.ndim == 0:
            value = value.item()  # a numpy string scalar packed as a 0-d array
        if isinstance(value, bytes):
            value = value.decode("utf-8", errors="replace")
        if not isinstance(value, str):
            raise ObservationError(f"prompt {_name(self.prompt)!r} must be a string, got {type(value).__name__}")
        return value


def default_layout_sample(observation: Any, state_dim: int,
                          no_continuation: str | None = None) -> tuple[dict[str, Any], int | None]:
    """The checks every policy makes of a default-layout observation before its processor sees it: a dict, a state
    vector (not a batch), no chunk-continuation fields where the policy does not continue chunks (`no_continuation`
    says why: "this pi0_fast policy decodes tokens"), a `noise_seed` in `[0, 2**63 - 1]`. Returns the processor's
    sample (`images`, `state`, `prompt`) and the noise seed (or None); raises [`ObservationError`] naming the
    field."""
    if not isinstance(observation, Mapping):
        raise ObservationError(f"observation must be a dict, got {type(observation).__name__}")
    state = observation.get("state")
    if state is not None and np.ndim(state) != 1:  # a 2-D state would mean a batch to the processor
        raise ObservationError(f"observation.state: expected shape [{state_dim}], got {list(np.shape(state))}")
    chunk_fields = [name for name in CHUNK_FIELDS if name != "noise_seed" and observation.get(name) is not None]
    if chunk_fields and no_continuation is not None:
        raise ObservationError(f"{', '.join(chunk_fields)}: {no_continuation}; it does not continue chunks")
    seed = observation.get("noise_seed")
    if seed is not None:
        seed = step_count(seed, "noise_seed", 0, 2**63 - 1)
    return {"images": observation.get("images"), "state": state, "prompt": observation.get("prompt")}, seed


def step_count(value: Any, name: str, low: int, high: int) -> int:
    """An integer field of an observation in `[low, high]` (a 0-d array too), or an `ObservationError` naming it."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    try:
        return check_int(name, value, low, high)
    except ValueError as error:
        raise ObservationError(str(error)) from None


class _Missing:
    pass


_MISSING = _Missing()


def _lookup(message: Mapping[str, Any], source: Source) -> Any:
    if isinstance(source, str):
        return message.get(source, _MISSING)
    value: Any = message
    for key in source:
        if not isinstance(value, Mapping) or key not in value:
            return _MISSING
        value = value[key]
    return value


def _name(source: Source) -> str:
    return source if isinstance(source, str) else "/".join(source)


def _source(value: Any, where: str) -> Source:
    if isinstance(value, str) and value:
        return value
    if isinstance(value, Sequence) and value and all(isinstance(k, str) and k for k in value):
        return tuple(value)
    raise ValueError(f"observation format: {where} must be a key (string) or a key path (list of strings), got {value!r}")


def _fast_cameras(preset: ObservationFormat, slots: Mapping[str, str]) -> ObservationFormat:
    """The π0-FAST form of a π0 preset, `<name>_fast`: the same sources, fed into π0-FAST's camera slots (`slots`:
    π0 camera -> π0-FAST camera)."""
    assert isinstance(preset.images, Mapping)
    return dataclasses.replace(preset, name=f"{preset.name}_fast",
                               images={slots[camera]: source for camera, source in preset.images.items()},
                               optional_images=frozenset(slots[camera] for camera in preset.optional_images))


# Presets. openpi's example clients: LIBERO (examples/libero/main.py, policies/libero_policy.py), DROID
# (examples/droid/main.py, policies/droid_policy.py), ALOHA (examples/aloha_*/, policies/aloha_policy.py: nested
# "images" dict of 3xHxW frames; cam_low is not used by π0, wrist cameras may be absent).
_LIBERO = ObservationFormat(
    name="libero",
    images={"base_0_rgb": "observation/image", "left_wrist_0_rgb": "observation/wrist_image"},
    state=("observation/state",),
)
_DROID = ObservationFormat(
    name="droid",
    images={"base_0_rgb": "observation/exterior_image_1_left", "left_wrist_0_rgb": "observation/wrist_image_left"},
    state=("observation/joint_position", "observation/gripper_position"),
    state_sizes=(7, 1),  # openpi's DroidInputs: 7 joint positions, then the gripper
)
_ALOHA = ObservationFormat(
    name="aloha",
    images={
        "base_0_rgb": ("images", "cam_high"),
        "left_wrist_0_rgb": ("images", "cam_left_wrist"),
        "right_wrist_0_rgb": ("images", "cam_right_wrist"),
    },
    optional_images=frozenset({"left_wrist_0_rgb", "right_wrist_0_rgb"}),
    state=("state",),
)
# π0-FAST's cameras: its model embeds the images in the order of their sorted names, so what counts is the slot
# (position) each frame lands in. openpi's *Inputs for ModelType.PI0_FAST: DROID gives [base, padding, wrist]
# (base_0_rgb, base_1_rgb, wrist_0_rgb); LIBERO keeps π0's names (base_0_rgb, left_wrist_0_rgb, right_wrist_0_rgb):
# [base, wrist, padding]; ALOHA's left wrist is base_1_rgb and its right wrist wrist_0_rgb.
_DROID_FAST_SLOTS = {"base_0_rgb": "base_0_rgb", "left_wrist_0_rgb": "wrist_0_rgb"}
_LIBERO_FAST_SLOTS = {"base_0_rgb": "base_0_rgb", "left_wrist_0_rgb": "base_1_rgb"}
_TWO_ARM_FAST_SLOTS = {"base_0_rgb": "base_0_rgb", "left_wrist_0_rgb": "base_1_rgb", "right_wrist_0_rgb": "wrist_0_rgb"}
PRESETS: dict[str, ObservationFormat] = {
    "default": ObservationFormat(name="default", images="images", state=("state",)),
    "libero": _LIBERO,
    "droid": _DROID,
    "aloha": _ALOHA,
    "libero_fast": _fast_cameras(_LIBERO, _LIBERO_FAST_SLOTS),
    "droid_fast": _fast_cameras(_DROID, _DROID_FAST_SLOTS),
    "aloha_fast": _fast_cameras(_ALOHA, _TWO_ARM_FAST_SLOTS),
    # Gymnasium simulators of LeRobot (`pi0-torch eval --env ...`): gym_pusht with obs_type "pixels_agent_pos", and
    # gym_aloha with obs_type "pixels_agent_pos" (one "top" camera; no prompt: the policy's default prompt is used).
    "pusht": ObservationFormat(name="pusht", images={"base_0_rgb": "pixels"}, state=("agent_pos",)),
    "gym_aloha": ObservationFormat(name="gym_aloha", images={"base_0_rgb": ("pixels", "top")}, state=("agent_pos",)),
}
