"""The checks every entry point shares: model tensors, numbers and settings, frames, text, and model locations.

One layer, so that a value is judged the same way wherever it comes in (`generate_actions`, the processor, a config,
a CLI flag, a websocket request) and every refusal reads alike: a `ValueError` whose one-line message names the
argument, what was expected and what came.

```python
>>> import torch
>>> check_int("action_horizon", 50, minimum=1)
50
>>> check_int("action_horizon", "50", minimum=1)
Traceback (most recent call last):
ValueError: action_horizon must be an integer >= 1, got '50' (str)
>>> check_tensor("state", torch.tensor([[0.0, float("nan")]]), (1, 2), floating=True)
Traceback (most recent call last):
ValueError: state must be finite, got 1 NaN/inf value (the first at index (0, 1))

```
"""

from __future__ import annotations

import json
import math
import stat
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pi0_torch.utils.optional import is_torch_tensor

if TYPE_CHECKING:  # (imported where used: the processing code runs without torch, `pi0_torch.utils.optional`)
    import torch

FLOAT32_MAX = float(np.finfo(np.float32).max)
MAX_ERROR_CHARS = 500
PACKAGE_NAMESPACE = "pi0_torch"  # `pi0_torch/<folder>` names a folder of this package, not a hub repository
MAX_JSON_BYTES = 64 * 2**20  # a settings or statistics file; the largest real one (norm stats of 32 dims) is kilobytes
MAX_SEED = 2**63 - 1  # seeds are stored as int64 (dataset columns) and fed to numpy's generators


# --------------------------------------------------------------------------------------------- messages


def first_line(error: BaseException) -> str:
    """The first line of an error's message (its type when it has none): for one-line error reports."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def one_line(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """`text` as one line of at most `limit` characters (for errors sent to clients, which may echo their input)."""
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def describe(value: Any) -> str:
    """A short description of a value for error messages: shape and dtype of tensors and arrays, else the type."""
    if isinstance(value, np.ndarray) or is_torch_tensor(value):
        return f"shape {tuple(value.shape)} dtype {value.dtype}"
    return type(value).__name__


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


# --------------------------------------------------------------------------------------------- numbers


def check_int(name: str, value: Any, minimum: int | None = None, maximum: int | None = None) -> int:
    """`value` if it is an integer (not a bool, not a string) within `[minimum, maximum]`; else `ValueError`."""
    is_integer = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if is_integer and (minimum is None or value >= minimum) and (maximum is None or value <= maximum):
        return int(value)
    raise ValueError(f"{name} must be an integer{_range_text(minimum, maximum)}, got {_shown(value)} ({type(value).__name__})")


def check_float(
    name: str, value: Any, minimum: float | None = None, maximum: float | None = None, exclusive_minimum: bool = False
) -> float:
    """`value` as a float if it is a finite real number (ints welcome, bools and strings not) within range."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
        number = float(value)
        above = minimum is None or (number > minimum if exclusive_minimum else number >= minimum)
        if math.isfinite(number) and above and (maximum is None or number <= maximum):
            return number
    low = f" > {_number(minimum)}" if exclusive_minimum and minimum is not None else _range_text(minimum, None)
    high = f"{' and' if low else ''} <= {_number(maximum)}" if maximum is not None else ""
    raise ValueError(f"{name} must be a finite number{low}{high}, got {_shown(value)} ({type(value).__name__})")


def _range_text(minimum: float | None, maximum: float | None) -> str:
    if minimum is not None and maximum is not None:
        return f" in [{_number(minimum)}, {_number(maximum)}]"
    if minimum is not None:
        return f" >= {_number(minimum)}"
    return f" <= {_number(maximum)}" if maximum is not None else ""


def _number(value: float) -> str:
    """Integers in full (a seed bound of 2**63 - 1 stays exact), other numbers in short form."""
    return str(value) if isinstance(value, (int, np.integer)) else f"{value:g}"


# --------------------------------------------------------------------------------------------- tensors and arrays


def check_tensor(
    name: str,
    value: Any,
    shape: Sequence[int],
    floating: bool = False,
    dtypes: tuple[torch.dtype, ...] = (),
    finite: bool = True,
    device: torch.device | None = None,
) -> None:
    """A torch tensor of exactly `shape`; floating point if `floating` (and then finite unless `finite=False`);
    with a dtype in `dtypes` when given; on `device` (the model's) when given."""
    import torch

    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {tuple(shape)}, got {describe(value)}")
    if tuple(value.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(value.shape)}")
    if device is not None and value.device != device:
        raise ValueError(f"{name} is on {value.device} but the model is on {device}: move the inputs to the model's "
                         "device first (a processor's output: `inputs.to(model.device)`)")
    if floating and not value.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    if dtypes and value.dtype not in dtypes:
        raise ValueError(f"{name} must have dtype in {[str(d) for d in dtypes]}, got {value.dtype}")
    if floating and finite and not bool(torch.isfinite(value).all()):
        raise nonfinite_error(name, value)


def nonfinite_error(name: str, value: torch.Tensor) -> ValueError:
    """The error for a tensor with NaN/inf values: how many, and the index of the first."""
    import torch

    bad = (~torch.isfinite(value)).nonzero()
    count = bad.shape[0]
    return ValueError(f"{name} must be finite, got {count} NaN/inf value{'s' if count > 1 else ''} "
                      f"(the first at index {tuple(bad[0].tolist())})")


def check_finite(name: str, values: np.ndarray) -> None:
    """Numbers that stay finite as float32 (the model's dtype): NaN, inf and values beyond ±3.4e38 are refused.

    The message gives the positions: `dims [2]` for a vector, indices for arrays of more dimensions.
    """
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.isfinite(values)
        too_large = ~bad & (np.abs(values) > FLOAT32_MAX)
    for mask, problem in ((bad, "contains NaN or inf"), (too_large, "has values beyond float32's range (±3.4e38)")):
        if mask.any():
            where = [int(i) for i in np.flatnonzero(mask)[:8]] if values.ndim <= 1 else [
                tuple(int(i) for i in index) for index in np.argwhere(mask)[:8]
            ]
            raise ValueError(f"{name}: {problem} at {'dims' if values.ndim <= 1 else 'indices'} {where}")


def check_frame_size(name: str, height: int, width: int) -> None:
    """A camera frame of at least 1x1 pixels."""
    if height < 1 or width < 1:
        raise ValueError(f"{name}: a frame of {height}x{width} pixels; expected at least 1x1")


# --------------------------------------------------------------------------------------------- model locations


def is_hub_id(name_or_path: Any) -> bool:
    """Whether `name_or_path` could name a model on the Hugging Face hub rather than a local folder.

    That is a string `namespace/name` that the hub accepts as a repository id (letters, digits, `-`, `_`, `.`; no
    `--` or `..`), that is not an existing path, and whose first part is not an existing local folder
    (`converted/pi05_droid` next to a local `converted/` folder means that folder). `Path` objects, absolute and
    relative paths (`/x`, `./x`, `../x`, `~/x`) and bare names without a namespace are local: pi0-torch models on the
    hub always have an owner. `pi0_torch/...` names this package's own folders (`pi0_torch/demo_policy`), never
    the hub.

    ```python
    >>> is_hub_id("someone/pi05_droid"), is_hub_id("pi05_droid"), is_hub_id("/data/pi05_droid"), is_hub_id("./x/y")
    (True, False, False, False)
    >>> is_hub_id("pi0_torch/demo_policy")
    False

    ```
    """
    if not isinstance(name_or_path, str) or name_or_path.count("/") != 1:
        return False
    try:
        from huggingface_hub.utils import HFValidationError, validate_repo_id
    except ImportError:  # (a torch-free deploy install: no hub to load from, every location is local)
        return False
    try:
        validate_repo_id(name_or_path)
    except HFValidationError:
        return False
    namespace = name_or_path.split("/")[0]
    return namespace != PACKAGE_NAMESPACE and not Path(name_or_path).exists() and not Path(namespace).is_dir()


def read_json_file(path: str | Path, max_bytes: int = MAX_JSON_BYTES) -> Any:
    """The JSON value in the file at `path`, or a one-line `ValueError` that names the file and what is wrong with
    it: not a regular file (a folder, a device such as `/dev/zero`, a link to one), larger than `max_bytes`, not
    UTF-8, not JSON, nested too deeply for Python's parser, or holding an integer too long for Python to read.
    (`FileNotFoundError` where nothing is there.)"""
    path = Path(path)
    try:
        info = path.stat()  # (follows links: a link to a device is refused as the device)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} not found") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error.strerror or error})") from None
    if not stat.S_ISREG(info.st_mode):
        raise ValueError(f"{path}: expected a JSON file, found {'a folder' if stat.S_ISDIR(info.st_mode) else 'no regular file'}")
    if info.st_size > max_bytes:
        raise ValueError(f"{path}: {info.st_size:,} bytes, more than a JSON settings file holds ({max_bytes:,} at most)")
    try:
        with open(path, "rb") as file:
            return json.loads(file.read(max_bytes + 1).decode("utf-8"))
    except RecursionError:
        raise ValueError(f"{path}: not a readable JSON file (nested too deeply)") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:  # (ValueError: JSON syntax, an integer of 4,300+ digits)
        raise ValueError(f"{path}: not a readable JSON file ({one_line(str(error), 200)})") from None


def check_pretrained_location(name_or_path: Any, required_file: str | None, what: str) -> None:
    """Refuse, before any download is tried, a location that is neither a usable local folder nor a hub id.

    A local folder must exist and hold `required_file` (e.g. `config.json`); a hub id (see [`is_hub_id`]) is left to
    the hub. `what` names the kind of folder in messages ("model", "processor").
    """
    if is_hub_id(name_or_path):
        return
    if not isinstance(name_or_path, (str, Path)):
        raise ValueError(f"expected the path of a {what} folder or a hub id 'namespace/name', got {type(name_or_path).__name__}")
    path = Path(name_or_path)
    convert_hint = (f"a {what} folder is written by `pi0-torch convert` (from openpi, LeRobot or transformers "
                    "checkpoints) or by save_pretrained")
    if not path.exists():
        if path.parts[:1] == (PACKAGE_NAMESPACE,):  # the docs' path of the shipped policy, outside a clone
            convert_hint = ("the demo policy shipped with the package is pi0_torch.demo_policy_dir() "
                            "(--policy demo on the command line)")
        raise FileNotFoundError(f"no {what} folder at {path} (and {str(name_or_path)!r} is not a hub id 'namespace/name'); "
                                f"{convert_hint}")
    if not path.is_dir():
        raise FileNotFoundError(f"{path} is a file; expected a {what} folder ({convert_hint})")
    if required_file is not None and not (path / required_file).is_file():
        present = sorted(p.name for p in path.iterdir())
        listing = ", ".join(present[:8]) + (" ..." if len(present) > 8 else "") if present else "nothing"
        if what == "processor" and "config.json" in present:  # a model converted without a tokenizer
            convert_hint = ("the model was converted without a processor: convert again with --tokenizer "
                            "(PaliGemma's SentencePiece file, or test offline), or build one with PI0Processor.from_config")
        raise FileNotFoundError(f"{path / required_file} is missing, so {path} is not a {what} folder "
                                f"(it holds {listing}); {convert_hint}")


class HubLoadError(OSError):
    """A hub id that could not be loaded (and that is no local folder either)."""


@contextmanager
def hub_errors(name_or_path: Any, what: str) -> Iterator[None]:
    """Around a hub download: an `OSError` for a hub id also says that no local folder of that name exists."""
    try:
        yield
    except OSError as error:
        if isinstance(error, HubLoadError) or not is_hub_id(name_or_path):
            raise
        raise HubLoadError(f"{name_or_path!r} is no local folder, and as a hub id it could not be loaded: "
                           f"{first_line(error)} (a local {what} folder is written by `pi0-torch convert` or "
                           "save_pretrained)") from error
