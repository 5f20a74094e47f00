"""Normalization statistics for robot states and actions, in openpi's `norm_stats.json` layout.

A [`NormStats`] holds per-dimension `mean`, `std`, `q01` and `q99` of one quantity (state or actions) at the robot's
own dimension. Three modes map a value into model space and back:

- `"zscore"` (π0): `(x - mean) / (std + 1e-6)`, inverse `y * (std + 1e-6) + mean`;
- `"quantile"` (π0.5): `(x - q01) / (q99 - q01 + 1e-6) * 2 - 1`, inverse `(y + 1) / 2 * (q99 - q01 + 1e-6) + q01`;
- `"none"`: identity.

These are openpi's formulas (`openpi.transforms.Normalize`/`Unnormalize`), unchanged for every dimension whose scale
(`std`, or `q99 - q01`) is at least `min_scale`.

**Near-constant dimensions.** openpi divides by `scale + 1e-6`, so a dimension that was constant in the training
data (a gripper that never moved, a padded joint) has a scale of ~0 and maps a deviation of 0.01 at inference time
to ~1e4, which the model has never seen. Here the scale is floored: `scale_used = max(scale, min_scale)` (default
`min_scale = 1e-3`, in the robot's units). For the data the statistics came from nothing changes (a constant value
still maps to exactly what openpi gives: the mean to 0, `q01` to -1), deviations map to at most `deviation /
min_scale`, and unnormalized model outputs stay within `min_scale`-sized steps of the constant. [`degenerate_dims`]
lists the affected dimensions; [`warn_degenerate`] (called by `PI0Processor` and [`compute_norm_stats`]) warns about
them. `min_scale=0` gives openpi's exact behaviour everywhere.

```python
>>> import numpy as np
>>> stats = NormStats(mean=[0.0, 1.0], std=[2.0, 0.5], q01=[-3.0, 0.0], q99=[3.0, 2.0])
>>> y = normalize(np.array([1.0, 1.5]), stats, "zscore")
>>> np.round(y, 4).tolist(), np.allclose(unnormalize(y, stats, "zscore"), [1.0, 1.5])
([0.5, 1.0], True)
>>> np.round(normalize(np.array([-3.0, 2.0]), stats, "quantile"), 4).tolist()
[-1.0, 1.0]

```
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar, Union

import numpy as np

from pi0_torch.utils import files
from pi0_torch.utils.optional import is_torch_tensor
from pi0_torch.utils.validation import read_json_file

if TYPE_CHECKING:  # (imported where used: the processing code runs without torch, `pi0_torch.utils.optional`)
    import torch

NormMode = Literal["zscore", "quantile", "none"]
NORM_MODES: tuple[str, ...] = ("zscore", "quantile", "none")
DEFAULT_MIN_SCALE = 1e-3
OPENPI_EPSILON = 1e-6  # openpi adds this to every scale
NUM_QUANTILE_BINS = 5000  # openpi's RunningStats histogram resolution
DEFAULT_MAX_EXACT_ROWS = 1_000_000  # rows per key kept for exact quantiles; beyond, the histogram estimate is used
# |mean|, std, |q01|, |q99| and min_scale in the robot's units: float32 (what the model reads) resolves whole units only
# up to 2^24, so a statistic beyond it cannot normalize any reading meaningfully; no robot's joint, position, gripper or
# encoder reading is that large, and a corrupted file (3.3e38, 1e30) is refused at load instead of reaching the robot
MAX_STATISTIC = float(2**24)

ArrayT = TypeVar("ArrayT", np.ndarray, "torch.Tensor")
ArrayLike = Union[np.ndarray, "torch.Tensor", Sequence[float]]


@dataclass(frozen=True)
class NormStats:
    """Per-dimension statistics of one quantity: `mean`, `std` (population), and the 1% / 99% quantiles.

    Arrays are 1-D float64 of the same length. `q01`/`q99` may be `None` (then only `"zscore"` works), as in openpi.
    """

    mean: np.ndarray
    std: np.ndarray
    q01: np.ndarray | None = None
    q99: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("mean", "std", "q01", "q99"):
            value = getattr(self, name)
            if value is None:
                if name in ("mean", "std"):
                    raise ValueError(f"NormStats.{name} is required")
                continue
            array = np.asarray(value, dtype=np.float64)
            if array.ndim != 1 or array.size == 0:
                raise ValueError(f"NormStats.{name} must be a non-empty 1-D vector, got shape {array.shape}")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"NormStats.{name} contains NaN or inf: {array.tolist()}")
            if array.size and np.abs(array).max() > MAX_STATISTIC:
                dim = int(np.abs(array).argmax())
                raise ValueError(f"NormStats.{name}[{dim}] is {array[dim]:.6g}, beyond ±{MAX_STATISTIC:.0f} (2^24) in the "
                                 "robot's units: no reading is that large (float32 stops resolving whole units there); "
                                 "recompute them from the data (compute_norm_stats; train --norm-stats dataset)")
            object.__setattr__(self, name, array)
        if (self.q01 is None) != (self.q99 is None):
            raise ValueError("NormStats.q01 and NormStats.q99 must be given together")
        present = [name for name in ("mean", "std", "q01", "q99") if getattr(self, name) is not None]
        lengths = {name: getattr(self, name).size for name in present}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"NormStats vectors must have one length, got {lengths}")
        if np.any(self.std < 0):
            raise ValueError(f"NormStats.std must be >= 0, got {self.std.tolist()}")
        if self.q01 is not None and np.any(self.q99 < self.q01):
            raise ValueError(
                f"NormStats.q99 must be >= q01 in every dim, got q01={self.q01.tolist()} q99={self.q99.tolist()}"
            )

    @property
    def dim(self) -> int:
        return int(self.mean.size)

    @property
    def has_quantiles(self) -> bool:
        return self.q01 is not None

    def truncated(self, dim: int) -> NormStats:
        """The statistics of the first `dim` dimensions (openpi slices stats to the data's length the same way)."""
        if dim > self.dim:
            raise ValueError(f"norm stats have {self.dim} dims, cannot take the first {dim}")
        cut = lambda a: None if a is None else a[:dim]  # noqa: E731
        return NormStats(self.mean[:dim], self.std[:dim], cut(self.q01), cut(self.q99))

    def to_dict(self) -> dict[str, list[float] | None]:
        """openpi's JSON form of one entry: `{"mean": [...], "std": [...], "q01": [...] | null, "q99": ...}`."""
        as_list = lambda a: None if a is None else [float(v) for v in a]  # noqa: E731
        return {name: as_list(getattr(self, name)) for name in ("mean", "std", "q01", "q99")}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> NormStats:
        missing = [k for k in ("mean", "std") if data.get(k) is None]
        if missing:
            raise ValueError(f"norm stats entry lacks {missing}; keys present: {sorted(data)}")
        return cls(mean=data["mean"], std=data["std"], q01=data.get("q01"), q99=data.get("q99"))


def _check_mode(mode: str) -> None:
    if mode not in NORM_MODES:
        raise ValueError(f"norm_mode must be one of {NORM_MODES}, got {mode!r}")


def _floored_scale(stats: NormStats, mode: str, min_scale: float) -> np.ndarray:
    """`std` (z-score) or `q99 - q01` (quantile), floored at `min_scale` (see the module docstring)."""
    if mode == "zscore":
        return np.maximum(stats.std, min_scale)
    if not stats.has_quantiles:
        raise ValueError("quantile normalization needs q01 and q99 in the norm stats; these stats only have mean/std")
    return np.maximum(stats.q99 - stats.q01, min_scale)


def _apply(x: ArrayT, stats: NormStats, mode: str, min_scale: float, inverse: bool) -> ArrayT:
    _check_mode(mode)
    if mode == "none":
        return x
    if x.shape[-1] != stats.dim:
        raise ValueError(f"last dim of the values is {x.shape[-1]}, the norm stats have {stats.dim} dims")
    scale = _floored_scale(stats, mode, min_scale) + OPENPI_EPSILON
    offset = stats.mean if mode == "zscore" else stats.q01
    if is_torch_tensor(x):
        import torch

        compute = torch.float64 if x.dtype == torch.float64 else torch.float32
        scale = torch.as_tensor(scale, dtype=compute, device=x.device)
        offset = torch.as_tensor(offset, dtype=compute, device=x.device)
        values = x.to(compute)
    else:
        values = np.asarray(x, dtype=np.float64)
    # openpi's formulas, literally
    if mode == "zscore":
        out = values * scale + offset if inverse else (values - offset) / scale
    else:
        out = (values + 1.0) / 2.0 * scale + offset if inverse else (values - offset) / scale * 2.0 - 1.0
    if isinstance(out, np.ndarray):
        return out.astype(x.dtype if np.issubdtype(x.dtype, np.floating) else np.float64)
    return out


def normalize(x: ArrayT, stats: NormStats, mode: NormMode, min_scale: float = DEFAULT_MIN_SCALE) -> ArrayT:
    """Map robot-space values `x` [..., stats.dim] into model space (see the module docstring for the formulas).

    numpy in -> numpy out (float dtype kept; computed in float64); torch in -> torch out on the same device
    (float64 kept, anything else computed and returned in float32).
    """
    return _apply(x, stats, mode, min_scale, inverse=False)


def unnormalize(x: ArrayT, stats: NormStats, mode: NormMode, min_scale: float = DEFAULT_MIN_SCALE) -> ArrayT:
    """Inverse of [`normalize`]: model-space values [..., stats.dim] back to robot units."""
    return _apply(x, stats, mode, min_scale, inverse=True)


def degenerate_dims(stats: NormStats, mode: NormMode, min_scale: float = DEFAULT_MIN_SCALE) -> list[int]:
    """Dimensions whose scale (`std` for z-score, `q99 - q01` for quantile) is below `min_scale` and gets floored."""
    _check_mode(mode)
    if mode == "none" or min_scale <= 0:
        return []
    if mode == "zscore":
        scale = stats.std
    elif stats.has_quantiles:
        scale = stats.q99 - stats.q01
    else:
        return []
    return [int(i) for i in np.flatnonzero(scale < min_scale)]


def warn_degenerate(stats: NormStats, mode: str, name: str, min_scale: float = DEFAULT_MIN_SCALE) -> list[int]:
    """Warn (UserWarning) when `stats` has near-constant dims in `mode`; returns those dims."""
    dims = degenerate_dims(stats, mode, min_scale)
    if dims:
        scale_name = "std" if mode == "zscore" else "q99 - q01"
        scales = stats.std if mode == "zscore" else stats.q99 - stats.q01
        warnings.warn(
            f"norm stats '{name}': dims {dims} are (near) constant ({scale_name} = "
            f"{[float(f'{scales[i]:.3g}') for i in dims]} < min_scale {min_scale}); their scale is floored to "
            f"{min_scale} so deviations cannot blow up (openpi would divide by {scale_name} + 1e-6)",
            UserWarning,
            stacklevel=3,
        )
    return dims


# ----------------------------------------------------------------------------------------------- files


def load_openpi_norm_stats(path: str | Path) -> dict[str, NormStats]:
    """Read openpi's `norm_stats.json` (`{"norm_stats": {"state": {...}, "actions": {...}}}`).

    `path` may be the file, a folder holding `norm_stats.json`, or an openpi checkpoint step folder with exactly one
    `assets/<asset_id>/norm_stats.json`.

    ```python
    >>> stats = load_openpi_norm_stats("tests/fixtures/openpi/pi0_small/ckpt/0")
    >>> sorted(stats), stats["state"].dim
    (['actions', 'state'], 8)

    ```
    """
    path = Path(path)
    if path.is_dir():
        direct = path / "norm_stats.json"
        found = [direct] if direct.is_file() else sorted(path.glob("assets/*/norm_stats.json"))
        if len(found) != 1:
            where = [str(p) for p in found] or "none"
            raise FileNotFoundError(
                f"expected one norm_stats.json in {path} (directly or under assets/<asset_id>/), found: {where}"
            )
        path = found[0]
    data = read_json_file(path)
    if not isinstance(data, dict) or not isinstance(data.get("norm_stats"), dict):
        raise ValueError(f"{path}: expected openpi's layout {{\"norm_stats\": {{\"state\": ..., \"actions\": ...}}}}")
    try:
        return {key: NormStats.from_dict(entry) for key, entry in data["norm_stats"].items()}
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def save_openpi_norm_stats(path: str | Path, stats: Mapping[str, NormStats]) -> Path:
    """Write `stats` as openpi's `norm_stats.json`; `path` is the file or a folder (then `<folder>/norm_stats.json`).

    Written to a temporary file first, so a failure leaves no half-written file behind. Returns the file's path.
    """
    path = Path(path)
    if path.suffix != ".json":
        path = path / "norm_stats.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"norm_stats": {key: value.to_dict() for key, value in stats.items()}}, indent=2)
    files.write_text_atomically(path, text)
    return path


# ----------------------------------------------------------------------------------------------- statistics


class RunningStats:
    """Streaming statistics of vectors (every leading axis of a batch is a batch axis), bounded memory.

    - mean and std: exact (Chan et al.'s parallel update in float64; std is the population std, as openpi's).
    - q01 / q99: exact (`numpy.quantile`, linear interpolation) while at most `max_exact_rows` vectors have been seen;
      past that, openpi's `RunningStats` estimate: a per-dim histogram of `num_bins` bins over [min, max], whose
      counts are moved onto new bins when the range grows (each old bin's count to the new bin holding its left
      edge), and the quantile is the left edge of the first bin where the cumulative count reaches q * count. The
      error is about one bin ((max - min) / num_bins) for one batch, and drifts low by up to a bin per range growth
      (the same numbers as openpi's `RunningStats` for the same batches).
    """

    def __init__(self, num_bins: int = NUM_QUANTILE_BINS, max_exact_rows: int = DEFAULT_MAX_EXACT_ROWS) -> None:
        self.num_bins = num_bins
        self.max_exact_rows = max_exact_rows
        self.count = 0
        self._mean: np.ndarray | None = None  # [D]
        self._m2: np.ndarray | None = None  # [D] sum of squared deviations
        self._min: np.ndarray | None = None
        self._max: np.ndarray | None = None
        self._hist: np.ndarray | None = None  # [D, num_bins]
        self._edges: np.ndarray | None = None  # [D, num_bins + 1]
        self._rows: list[np.ndarray] | None = []  # kept for exact quantiles until max_exact_rows is exceeded

    def update(self, batch: ArrayLike) -> None:
        values = _as_float_array(batch, "batch")
        values = values.reshape(-1, values.shape[-1]) if values.ndim > 1 else values[None]
        n, dim = values.shape
        if n == 0:
            return
        if self._mean is not None and dim != self._mean.size:
            raise ValueError(f"vectors of length {dim} after vectors of length {self._mean.size}")
        if not np.all(np.isfinite(values)):
            raise ValueError("cannot compute statistics of values containing NaN or inf")

        batch_mean = values.mean(axis=0)
        batch_m2 = ((values - batch_mean) ** 2).sum(axis=0)
        batch_min, batch_max = values.min(axis=0), values.max(axis=0)
        if self._mean is None:
            self._mean, self._m2, self._min, self._max = batch_mean, batch_m2, batch_min, batch_max
            self._edges = np.linspace(self._min - 1e-10, self._max + 1e-10, self.num_bins + 1, axis=-1)
            self._hist = np.zeros((dim, self.num_bins))
        else:
            total = self.count + n
            delta = batch_mean - self._mean
            self._mean = self._mean + delta * (n / total)
            self._m2 = self._m2 + batch_m2 + delta**2 * (self.count * n / total)
            grown = np.any(batch_min < self._min) or np.any(batch_max > self._max)
            self._min, self._max = np.minimum(self._min, batch_min), np.maximum(self._max, batch_max)
            if grown:
                self._rebin()
        self.count += n
        for d in range(dim):
            self._hist[d] += np.histogram(values[:, d], bins=self._edges[d])[0]
        if self._rows is not None:
            self._rows.append(values.copy())
            if self.count > self.max_exact_rows:
                self._rows = None

    def _rebin(self) -> None:
        new_edges = np.linspace(self._min - 1e-10, self._max + 1e-10, self.num_bins + 1, axis=-1)
        for d in range(self._hist.shape[0]):
            # each old bin's count goes to the new bin holding the old bin's left edge (openpi's redistribution)
            self._hist[d] = np.histogram(self._edges[d, :-1], bins=new_edges[d], weights=self._hist[d])[0]
        self._edges = new_edges

    @property
    def uses_exact_quantiles(self) -> bool:
        return self._rows is not None

    def quantiles(self, q: Sequence[float]) -> list[np.ndarray]:
        if self._rows is not None:
            rows = np.concatenate(self._rows, axis=0)
            return [np.quantile(rows, p, axis=0) for p in q]
        out = []
        cumulative = np.cumsum(self._hist, axis=1)  # [D, num_bins]
        for p in q:
            idx = [int(np.searchsorted(cumulative[d], p * self.count)) for d in range(cumulative.shape[0])]
            out.append(self._edges[np.arange(len(idx)), idx])
        return out

    def get_statistics(self) -> NormStats:
        if self.count < 2:
            raise ValueError(f"statistics need at least 2 vectors, got {self.count}")
        std = np.sqrt(np.maximum(self._m2 / self.count, 0.0))
        q01, q99 = self.quantiles([0.01, 0.99])
        return NormStats(mean=self._mean.copy(), std=std, q01=q01, q99=q99)


def _as_float_array(value: Any, name: str) -> np.ndarray:
    if is_torch_tensor(value):
        import torch

        value = value.detach().to("cpu", torch.float64).numpy()
    array = np.asarray(value)
    if array.dtype == object or not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise ValueError(f"{name}: expected a numeric array, got dtype {array.dtype}")
    if array.ndim == 0:
        raise ValueError(f"{name}: expected a vector or a batch of vectors, got a scalar")
    return array.astype(np.float64)


def compute_norm_stats(
    data: Iterable[Mapping[str, ArrayLike]] | Iterable[ArrayLike],
    keys: Sequence[str] = ("state", "actions"),
    *,
    delta_action_mask: Sequence[bool] | None = None,
    num_bins: int = NUM_QUANTILE_BINS,
    max_exact_rows: int = DEFAULT_MAX_EXACT_ROWS,
    progress: bool = False,
    total: int | None = None,
) -> dict[str, NormStats] | NormStats:
    """Statistics (mean, std, q01, q99) of a stream of samples, with bounded memory (a progress bar with `progress=True`).

    `data` yields either dicts (e.g. `{"state": [D] or [B, D], "actions": [H, D] or [B, H, D]}`, numpy or torch;
    every axis but the last is a batch axis) -> returns `{key: NormStats}` for `keys`; or plain arrays -> returns one
    `NormStats`. Mean/std are exact; quantiles as described in [`RunningStats`].

    With `delta_action_mask` (openpi's `DeltaActions`), the masked action dims have the sample's state subtracted
    before they are counted, so the action stats describe what the model is trained on (each dict then needs
    `state` [.., D] alongside `actions` [.., H, D]). Near-constant dims are reported with a warning.

    ```python
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> samples = [{"state": rng.normal(size=3), "actions": rng.normal(size=(4, 2))} for _ in range(100)]
    >>> stats = compute_norm_stats(samples, progress=False)
    >>> stats["state"].dim, stats["actions"].dim
    (3, 2)

    ```
    """
    if total is None and hasattr(data, "__len__"):
        total = len(data)  # type: ignore[arg-type]
    running: dict[str, RunningStats] = {}
    single = False
    from pi0_torch.utils.progress import tqdm

    for index, item in enumerate(tqdm(data, total=total, desc="norm stats", disable=not progress)):
        if isinstance(item, Mapping):
            if single:
                raise ValueError(f"sample {index}: a dict after plain arrays; pass one kind of sample")
            missing = [k for k in keys if k not in item]
            if missing:
                raise ValueError(f"sample {index}: missing keys {missing}; present: {sorted(item)}")
            values = {k: _as_float_array(item[k], f"sample {index} '{k}'") for k in keys}
            if delta_action_mask is not None and "actions" in values:
                if "state" not in item:
                    raise ValueError(f"sample {index}: delta_action_mask needs 'state' next to 'actions'")
                state = _as_float_array(item["state"], f"sample {index} 'state'")
                values["actions"] = apply_delta(values["actions"], state, delta_action_mask)
        else:
            if running and not single:
                raise ValueError(f"sample {index}: a plain array after dicts; pass one kind of sample")
            single = True
            values = {"": _as_float_array(item, f"sample {index}")}
        for key, value in values.items():
            running.setdefault(key, RunningStats(num_bins, max_exact_rows)).update(value)
    if not running:
        raise ValueError("compute_norm_stats got no samples")
    result = {key: stats.get_statistics() for key, stats in running.items()}
    for key, stats in result.items():
        flat = {mode: degenerate_dims(stats, mode) for mode in ("zscore", "quantile")}
        if flat["zscore"] or flat["quantile"]:
            warnings.warn(
                f"norm stats '{key or 'values'}': (near) constant dims (scale < {DEFAULT_MIN_SCALE}): "
                f"{flat['zscore']} by std, {flat['quantile']} by q99 - q01; normalization floors their scale at "
                f"min_scale (openpi would divide by ~1e-6 there)",
                UserWarning,
                stacklevel=2,
            )
    return result[""] if single else result


def apply_delta(actions: ArrayT, state: ArrayT, mask: Sequence[bool], *, inverse: bool = False) -> ArrayT:
    """openpi's `DeltaActions` (`inverse=False`) / `AbsoluteActions` (`inverse=True`).

    `actions` [..., H, Da], `state` [..., Ds] (raw, unnormalized, same leading axes); for every dim `i` with
    `mask[i]` True, `state[..., i]` is subtracted from (added to) `actions[..., :, i]`. `len(mask)` may be shorter
    than `Da` and `Ds` (the remaining dims are absolute). Returns a new array of the same type.
    """
    k = len(mask)
    if k > actions.shape[-1] or k > state.shape[-1]:
        raise ValueError(
            f"delta_action_mask has {k} entries but actions have {actions.shape[-1]} dims and state {state.shape[-1]}"
        )
    if is_torch_tensor(actions):
        import torch

        m = torch.as_tensor(list(mask), dtype=torch.bool, device=actions.device)
        shift = torch.where(m, torch.as_tensor(state, device=actions.device)[..., :k].to(actions.dtype), 0.0)
        out = actions.clone()
    else:
        m = np.asarray(mask, dtype=bool)
        shift = np.where(m, np.asarray(state)[..., :k], 0.0).astype(actions.dtype)
        out = actions.copy()
    shift = shift[..., None, :]  # [..., 1, k]: the same state for every action step
    out[..., :k] = out[..., :k] + shift if inverse else out[..., :k] - shift
    return out

