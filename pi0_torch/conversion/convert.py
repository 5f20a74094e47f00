"""Convert openpi, LeRobot and transformers π0 / π0.5 checkpoints into pi0-torch folders (and π0 back to transformers).

`pi0-torch convert --from openpi|lerobot|transformers --input SRC --output-dir DST` writes a folder that
`PI0ForActionGeneration.from_pretrained(DST)` loads: `config.json`, safetensors weights (`model.safetensors`, or
`model-0000i-of-0000N.safetensors` shards plus `model.safetensors.index.json` above `--max-shard-size`, as
`save_pretrained` does), and the processor files: openpi's `norm_stats.json` (from `assets/<asset_id>/` of an openpi
checkpoint), plus `processor_config.json` and the tokenizer when `--tokenizer` is given, so that
`PI0Processor.from_pretrained(DST)` works too.

How it stays safe on a 12 GB checkpoint:
- streaming: the output layout (every tensor's name, shape and byte range in its shard) is planned from the config
  before any weight is read; each tensor is written into its place as soon as it is produced and then dropped. An
  openpi leaf is read one layer at a time (a leaf stored as one big chunk is decompressed once, as a stream, and
  spilled per layer to a scratch folder), so memory stays near the largest single tensor (π0's 2.1 GB float32 text
  embedding), not the model;
- validation first: every leaf must be used and every parameter filled, with the shapes the inferred config
  needs; leftovers are reported by name before anything is written;
- atomic output: everything goes into a hidden partial folder next to DST that is renamed into place at the end;
  any failure removes it, and a partial folder left by a killed run is removed by the next run
  (`pi0_torch.utils.files`). An existing non-empty DST is replaced only with `overwrite=True` and only when
  pi0-torch wrote all of it, and never when it is, contains or lies inside the input.

```python
>>> import tempfile
>>> from pi0_torch import PI0ForActionGeneration
>>> from pi0_torch.conversion.convert import convert_openpi_checkpoint
>>> result = convert_openpi_checkpoint("tests/fixtures/openpi/pi0_small/ckpt/0", tempfile.mkdtemp() + "/pi0", progress=False)
>>> sorted(p.name for p in result.output_dir.iterdir())  # and the manifest of the files pi0-torch wrote
['.pi0-torch-manifest.json', 'config.json', 'model.safetensors', 'norm_stats.json']
>>> PI0ForActionGeneration.from_pretrained(result.output_dir).config.pi05
False

```
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import shutil
import struct
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open
from tqdm.auto import tqdm

from pi0_torch.cli import bool_mask
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.normalization import NormStats, load_openpi_norm_stats, save_openpi_norm_stats
from pi0_torch.conversion.download import CACHE_ENV, PUBLISHED_CHECKPOINTS, checkpoint_url, fetch_openpi_checkpoint
from pi0_torch.conversion.openpi_weights import check_openpi_shapes, config_from_openpi_shapes, is_openpi_fast_tree, iter_openpi_state_dict
from pi0_torch.conversion.orbax_reader import CheckpointError, LeafInfo, OrbaxCheckpoint, first_line
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.processing_pi0 import NORM_STATS_FILE, PI0Processor
from pi0_torch.processing.processing_pi0_fast import FAST_TOKENIZER_DIR, PI0FastProcessor
from pi0_torch.processing.robot_spaces import CONVERSIONS
from pi0_torch.processing.tokenization import TEST_TOKENIZER, TEST_TOKENIZER_VOCAB, PromptTokenizer, build_test_tokenizer
from pi0_torch.utils.files import OutputPathError, atomic_output_dir, check_output_dir, check_separate

logger = logging.getLogger(__name__)

SOURCES = ("openpi", "lerobot", "transformers")
DTYPES: dict[str, torch.dtype] = {"float32": torch.float32, "bfloat16": torch.bfloat16}
DEFAULT_MAX_SHARD_BYTES = 5 * 10**9  # "5GB", as save_pretrained counts it
CONFIG_FILE = "config.json"
SINGLE_FILE = "model.safetensors"
INDEX_FILE = "model.safetensors.index.json"
_SAFETENSORS_DTYPES = {torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16"}
_WRITE_BLOCK = 64 << 20  # bytes of a tensor cast and written at once
_SMALL_LEAF_BYTES = 64 << 20  # a multi-layer chunk up to this size keeps its layers in memory, a bigger one spills them


class ConversionError(CheckpointError):
    """A conversion that cannot proceed (bad input, existing output, not enough disk). The message is one line."""


# ---------------------------------------------------------------------------------------------------------------------
# streaming safetensors writer
# ---------------------------------------------------------------------------------------------------------------------


def parse_size(size: int | str) -> int:
    """Bytes from `5000000`, `"5GB"` (10**9), `"500MiB"` (2**20) ..., as `save_pretrained(max_shard_size=...)`."""
    if isinstance(size, int):
        return size
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]?)(i?)B?\s*", size, flags=re.IGNORECASE)
    if not match:
        raise ValueError(f"cannot parse size {size!r}; use e.g. 5GB, 500MB, 2GiB or a number of bytes")
    number, unit, binary = match.groups()
    exponent = "KMGT".find(unit.upper()) + 1 if unit else 0
    return int(float(number) * (1024 if binary else 1000) ** exponent)


@dataclass(frozen=True)
class _Slot:
    file: int  # index into the writer's files
    offset: int  # absolute byte offset of the tensor's data in that file
    shape: tuple[int, ...]


class ShardedSafetensorsWriter:
    """Writes a planned state dict into safetensors files tensor by tensor, in any order, without holding it.

    `shapes` (name -> shape, in save order) fixes the layout up front: tensors are grouped into shards of at most
    `max_shard_bytes` (a tensor larger than that gets its own shard), each file's header is written and the file
    sized, and `write` puts a tensor's bytes at its offset. `close` checks that every tensor was written and writes
    `model.safetensors.index.json` when there are several shards. Files are named as `save_pretrained` names them.
    """

    def __init__(
        self, folder: Path, shapes: Mapping[str, tuple[int, ...]], dtype: torch.dtype, max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES
    ) -> None:
        if dtype not in _SAFETENSORS_DTYPES:
            raise ValueError(f"unsupported dtype {dtype}; expected one of {list(_SAFETENSORS_DTYPES)}")
        self.dtype = dtype
        itemsize = torch.empty((), dtype=dtype).element_size()
        groups: list[list[str]] = []
        group_bytes = 0
        for name, shape in shapes.items():
            nbytes = math.prod(shape) * itemsize
            if not groups or (group_bytes + nbytes > max_shard_bytes and groups[-1]):
                groups.append([])
                group_bytes = 0
            groups[-1].append(name)
            group_bytes += nbytes
        count = len(groups)
        self.filenames = [SINGLE_FILE] if count == 1 else [f"model-{i + 1:05d}-of-{count:05d}.safetensors" for i in range(count)]
        self.folder = folder
        self.total_bytes = 0
        self._slots: dict[str, _Slot] = {}
        self._fds: list[int] = []
        self._written: set[str] = set()
        try:
            for index, names in enumerate(groups):
                header: dict[str, Any] = {"__metadata__": {"format": "pt"}}
                begin = 0
                for name in names:
                    end = begin + math.prod(shapes[name]) * itemsize
                    header[name] = {"dtype": _SAFETENSORS_DTYPES[dtype], "shape": list(shapes[name]), "data_offsets": [begin, end]}
                    begin = end
                encoded = json.dumps(header, separators=(",", ":")).encode()
                encoded += b" " * (-len(encoded) % 8)  # safetensors pads the header to 8 bytes with spaces
                data_start = 8 + len(encoded)
                fd = os.open(folder / self.filenames[index], os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
                self._fds.append(fd)
                os.write(fd, struct.pack("<Q", len(encoded)) + encoded)
                os.ftruncate(fd, data_start + begin)
                for name in names:
                    self._slots[name] = _Slot(index, data_start + header[name]["data_offsets"][0], tuple(shapes[name]))
                self.total_bytes += begin
        except BaseException:
            self._close_files()
            raise

    def __enter__(self) -> ShardedSafetensorsWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, *rest: Any) -> None:
        if kind is None:
            self.close()
        else:
            self._close_files()

    @property
    def missing(self) -> list[str]:
        return [name for name in self._slots if name not in self._written]

    def write(self, name: str, tensor: torch.Tensor) -> int:
        """Write one planned tensor (cast to the writer's dtype); returns the bytes written."""
        slot = self._slots.get(name)
        if slot is None:
            raise ConversionError(f"tensor {name} is not a parameter of the model")
        if name in self._written:
            raise ConversionError(f"tensor {name} was produced twice")
        if tuple(tensor.shape) != slot.shape:
            raise ConversionError(f"tensor {name} has shape {tuple(tensor.shape)}, the model needs {slot.shape}")
        flat = tensor.detach().reshape(-1)
        step = _WRITE_BLOCK // flat.element_size()
        offset = slot.offset
        for begin in range(0, flat.numel(), step):  # cast block by block: no full-size copy of a big tensor
            block = memoryview(flat[begin : begin + step].to(device="cpu", dtype=self.dtype).contiguous().view(torch.uint8).numpy())
            done = 0
            while done < len(block):
                done += os.pwrite(self._fds[slot.file], block[done:], offset + done)
            offset += done
        self._written.add(name)
        return offset - slot.offset

    def close(self) -> list[Path]:
        """Check that every tensor was written, close the files, write the index; returns the weight files."""
        self._close_files()
        if self.missing:
            raise ConversionError(f"{len(self.missing)} parameters were never filled: {_names(self.missing)}")
        if len(self.filenames) > 1:
            index = {
                "metadata": {"total_size": self.total_bytes},
                "weight_map": {name: self.filenames[slot.file] for name, slot in sorted(self._slots.items())},
            }
            (self.folder / INDEX_FILE).write_text(json.dumps(index, indent=2) + "\n")
        return [self.folder / name for name in self.filenames]

    def _close_files(self) -> None:
        while self._fds:
            os.close(self._fds.pop())


def _human(count: float) -> str:
    """1234567 -> '1.23 M' (decimal prefixes)."""
    for prefix, scale in (("T", 1e12), ("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if count >= scale:
            return f"{count / scale:.2f} {prefix}"
    return f"{count:.0f} "


def _names(names: Iterable[str], limit: int = 12) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f" ... ({len(names) - limit} more)" if len(names) > limit else "")


def _model_class(config: PI0Config | PI0FastConfig) -> type[PI0ForActionGeneration | PI0FastForActionGeneration]:
    return PI0FastForActionGeneration if isinstance(config, PI0FastConfig) else PI0ForActionGeneration


def planned_shapes(config: PI0Config | PI0FastConfig) -> dict[str, tuple[int, ...]]:
    """Every parameter the config's model (`PI0ForActionGeneration` / `PI0FastForActionGeneration`) has, with its
    shape, in state-dict order (nothing allocated)."""
    with torch.device("meta"):
        model = _model_class(config)(config)
    return {name: tuple(tensor.shape) for name, tensor in model.state_dict().items()}


def _check_disk_space(output_dir: Path, needed: int) -> None:
    probe = next(p for p in (output_dir, *output_dir.parents) if p.exists())
    free = shutil.disk_usage(probe).free
    if free < needed:
        raise ConversionError(f"not enough free disk space for {output_dir}: need {needed / 1e9:.2f} GB, {free / 1e9:.2f} GB free")


def _progress(total: int, description: str, enabled: bool) -> tqdm:
    return tqdm(total=total, desc=description, unit="B", unit_scale=True, unit_divisor=1024, disable=not enabled, file=sys.stderr)


# ---------------------------------------------------------------------------------------------------------------------
# processor files
# ---------------------------------------------------------------------------------------------------------------------


def find_norm_stats(step_dir: Path, asset_id: str | None = None) -> Path | None:
    """`<step>/assets/<asset_id>/norm_stats.json`; the only one when `asset_id` is None. None when there are none."""
    found = sorted((step_dir / "assets").glob("*/norm_stats.json"))
    choices = [p.parent.name for p in found]
    if asset_id is not None:
        path = step_dir / "assets" / asset_id / "norm_stats.json"
        if not path.is_file():
            raise ConversionError(f"no norm stats for asset id {asset_id!r} in {step_dir / 'assets'}; choices: {', '.join(choices) or 'none'}")
        return path
    if len(found) > 1:
        raise ConversionError(f"{step_dir / 'assets'} has norm stats for several asset ids; pick one with --asset-id: {', '.join(choices)}")
    return found[0] if found else None


def _read_norm_stats(path: Path) -> dict[str, NormStats]:
    try:
        stats = load_openpi_norm_stats(path)
    except (ValueError, OSError) as error:
        raise ConversionError(f"unusable norm stats {path}: {error}") from None
    missing = [key for key in ("state", "actions") if key not in stats]
    if missing:
        raise ConversionError(f"norm stats {path} lack {', '.join(missing)} (have {', '.join(sorted(stats)) or 'nothing'})")
    return stats


def _build_processor(
    config: PI0Config | PI0FastConfig,
    norm_stats: Mapping[str, NormStats] | None,
    tokenizer: str | Path | None,
    processor_options: Mapping[str, Any] | None,
    fast_tokenizer: FASTActionTokenizer | None = None,
) -> PI0Processor | None:
    """The output's processor when there are a tokenizer and norm stats (and for π0-FAST its FAST tokenizer), built
    before any weight is written so that a bad setting fails fast. `processor_options` (`delta_action_mask`,
    `value_conversion`) need all of them."""
    fast = isinstance(config, PI0FastConfig)
    if tokenizer is None or norm_stats is None or (fast and fast_tokenizer is None):
        if processor_options:
            needed = "--tokenizer, --fast-tokenizer" if fast else "--tokenizer"
            raise ConversionError(f"processor settings {sorted(processor_options)} need {needed} and norm stats")
        return None
    try:
        if fast:
            return PI0FastProcessor.from_config(config, tokenizer, fast_tokenizer, norm_stats, **(processor_options or {}))
        return PI0Processor.from_config(config, tokenizer=tokenizer, norm_stats=norm_stats, **(processor_options or {}))
    except (ValueError, OSError, TypeError) as error:
        raise ConversionError(f"cannot build the processor with tokenizer {tokenizer}: {error}") from None


def _write_processor_files(
    folder: Path, processor: PI0Processor | None, norm_stats: Mapping[str, NormStats] | None, tokenizer: str | Path | None
) -> None:
    """The processor (settings, tokenizer, norm_stats.json) when there is one, else norm_stats.json when known."""
    if processor is not None:
        processor.save_pretrained(folder)
        return
    if norm_stats is not None:
        save_openpi_norm_stats(folder / NORM_STATS_FILE, norm_stats)
    if tokenizer is not None:
        logger.warning("no norm stats: the tokenizer alone does not make a processor; it was not copied")
    elif norm_stats is not None:
        logger.warning(
            "no --tokenizer given: wrote norm_stats.json only; build the processor with "
            "PI0Processor.from_config(config, tokenizer=<paligemma_tokenizer.model>, norm_stats=<output folder>)"
        )


def lerobot_norm_stats(folder: Path) -> tuple[Path, dict[str, NormStats]] | None:
    """Norm stats from a LeRobot policy folder (`policy_preprocessor_step_*_normalizer_processor.safetensors`, keys
    `observation.state.{mean,std,q01,q99}` and `action.{...}`), in openpi's form; None when the folder has none."""
    found = sorted(folder.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    if not found:
        return None
    if len(found) > 1:
        raise ConversionError(f"{folder} has several LeRobot normalizer files ({', '.join(p.name for p in found)}); pass --norm-stats")
    try:
        with safe_open(found[0], framework="np") as handle:
            values = {key: handle.get_tensor(key) for key in handle.keys()}
    except Exception as error:  # safetensors raises its own SafetensorError on malformed files
        raise ConversionError(f"cannot read {found[0]}: {first_line(error)}") from None
    stats = {}
    for ours, theirs in (("state", "observation.state"), ("actions", "action")):
        entry = {name: values.get(f"{theirs}.{name}") for name in ("mean", "std", "q01", "q99")}
        try:
            stats[ours] = NormStats.from_dict({k: None if v is None else v.reshape(-1) for k, v in entry.items()})
        except ValueError as error:
            raise ConversionError(f"{found[0]}: unusable {theirs} statistics: {error}") from None
    return found[0], stats


def _check_tokenizer(tokenizer: str | Path | None, config: PI0Config | PI0FastConfig) -> Path | PromptTokenizer | None:
    """The prompt tokenizer to save with the processor: a SentencePiece file, or for `test` (`TEST_TOKENIZER`) a
    small one trained here, offline (as `pi0-torch train --tokenizer test`; for trials and tests, not for real
    checkpoints, whose embeddings expect PaliGemma's)."""
    if tokenizer is None:
        return None
    if str(tokenizer) == TEST_TOKENIZER:
        return build_test_tokenizer(vocab_size=min(TEST_TOKENIZER_VOCAB, config.vocab_size))
    path = Path(tokenizer).expanduser()
    if not path.exists():
        raise ConversionError(f"tokenizer {path} does not exist")
    return path


def _save_config(config: PI0Config | PI0FastConfig, dtype: torch.dtype, folder: Path) -> None:
    config.architectures = [_model_class(config).__name__]
    config.dtype = dtype
    config.save_pretrained(folder)


@dataclass
class ConversionResult:
    """What a conversion wrote."""

    output_dir: Path
    config: PI0Config | PI0FastConfig
    dtype: torch.dtype
    weight_files: list[Path]
    weight_bytes: int
    norm_stats: Path | None = None
    dropped: list[str] = field(default_factory=list)  # source tensors deliberately not converted
    processor: bool = False  # whether the processor files (tokenizer, norm stats, settings) were written

    def summary(self) -> str:
        kind = "π0-FAST" if isinstance(self.config, PI0FastConfig) else "π0.5" if self.config.pi05 else "π0"
        params = self.weight_bytes // torch.empty((), dtype=self.dtype).element_size()
        lines = [
            f"wrote {self.output_dir}: {kind}, {_human(params)} parameters, {_human(self.weight_bytes)}B of "
            f"{str(self.dtype).removeprefix('torch.')} weights in {len(self.weight_files)} file(s)",
            f"norm stats: {self.norm_stats or 'none found'}",
            "processor: " + ("written (PI0Processor.from_pretrained loads it)" if self.processor else
                             "none (it needs norm stats and --tokenizer: PaliGemma's SentencePiece file, or test)"),
        ]
        if self.dropped:
            lines.append(f"not converted (unused by the model): {_names(self.dropped, 6)}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------------------------
# openpi
# ---------------------------------------------------------------------------------------------------------------------


class _OpenpiLeafSource:
    """`read(path, layer)` for `iter_openpi_state_dict`: float32 arrays, one layer at a time, with usage tracking.

    A stacked leaf chunked one layer per chunk is sliced straight from the store. When a chunk holds several layers
    (orbax writes an array saved from one device as a single chunk), reading layer by layer would decode that chunk
    again for each of its layers, so the chunk is decoded once, as a stream (`OrbaxCheckpoint.iter_rows`), and its
    layers are kept until they are asked for: in memory when the chunk is small, else spilled to files in
    `scratch`. Each layer is handed out once and then dropped, so memory stays near one layer and scratch space
    shrinks as the conversion proceeds.
    """

    def __init__(self, checkpoint: OrbaxCheckpoint, scratch: Path) -> None:
        self.checkpoint = checkpoint
        self.scratch = scratch
        self.used: set[str] = set()
        self._pending: dict[tuple[str, int], np.ndarray | Path] = {}  # decoded layers not handed out yet

    @staticmethod
    def spill_bytes(checkpoint: OrbaxCheckpoint) -> int:
        """Upper bound of the scratch space the spilled layers need."""
        return sum(info.nbytes for info in checkpoint.leaves.values() if info.shape and info.chunks[0] > 1 and _chunk_bytes(info) > _SMALL_LEAF_BYTES)

    def read(self, path: str, layer: int | None) -> np.ndarray:
        info = self.checkpoint.info(path)
        self.used.add(info.path)
        if layer is None or info.chunks[0] == 1:
            return _as_float32(self.checkpoint.read(path, layer), info.path)
        if (info.path, layer) not in self._pending:
            self._decode_chunk(info, layer)
        pending = self._pending.pop((info.path, layer))
        if isinstance(pending, Path):
            array = np.fromfile(pending, dtype=info.dtype).reshape(info.shape[1:])
            pending.unlink()
            return _as_float32(array, info.path)
        return _as_float32(pending, info.path)

    def _decode_chunk(self, info: LeafInfo, layer: int) -> None:
        start = layer - layer % info.chunks[0]
        spill = _chunk_bytes(info) > _SMALL_LEAF_BYTES
        if spill:
            self.scratch.mkdir(exist_ok=True)
        rows = self.checkpoint.iter_rows(info.path, start, min(start + info.chunks[0], info.shape[0]))
        for index, row in enumerate(rows, start):  # streamed: about one row in memory at a time
            if spill:
                file = self.scratch / f"{info.key}.{index}.bin"
                row.tofile(file)
                self._pending[info.path, index] = file
            else:
                self._pending[info.path, index] = row.copy()  # not a view: the chunk can be freed

    def close(self) -> None:
        self._pending.clear()
        shutil.rmtree(self.scratch, ignore_errors=True)


def _chunk_bytes(info: LeafInfo) -> int:
    return math.prod(info.chunks) * info.dtype.itemsize


def _as_float32(array: np.ndarray, name: str) -> np.ndarray:
    """Floating leaves as float32 (bfloat16 -> float32 is exact; torch cannot take numpy's bfloat16)."""
    if array.dtype == np.float32:
        return array
    if array.dtype.kind != "f" and array.dtype.name != "bfloat16":
        raise ConversionError(f"leaf {name} has dtype {array.dtype}; expected floating-point weights")
    return array.astype(np.float32)


def convert_openpi_checkpoint(
    checkpoint_dir: str | os.PathLike[str],
    output_dir: str | os.PathLike[str],
    *,
    dtype: str = "float32",
    asset_id: str | None = None,
    tokenizer: str | os.PathLike[str] | None = None,
    processor_options: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    max_shard_bytes: int | str = DEFAULT_MAX_SHARD_BYTES,
    progress: bool = False,
    fast_tokenizer: str | os.PathLike[str] | None = None,
    **config_overrides: Any,
) -> ConversionResult:
    """Convert an openpi checkpoint (`<run>/<step>` or its `params` folder) into a pi0-torch folder.

    π0 vs π0.5 vs π0-FAST and every dimension are inferred from the parameter tree; `config_overrides` set what the
    weights do not store (`action_horizon`, `max_token_len`, `camera_names`, `num_inference_steps`; for π0-FAST also
    `action_dim`, which otherwise comes from the FAST tokenizer's settings, like the horizon, then openpi's
    defaults). Norm stats come from `<step>/assets/<asset_id>/norm_stats.json` (`asset_id` may be omitted when there
    is one). `processor_options` go to the processor (e.g. openpi's ALOHA configs: `delta_action_mask` for the joints
    and `value_conversion="aloha"`). A π0-FAST checkpoint takes its FAST tokenizer folder (`fast_tokenizer`,
    written to `fast_tokenizer/` in the output). Raises `CheckpointError` (one line; nothing is written) for any
    problem with the input or the output location.
    """
    torch_dtype, max_shard_bytes, output_dir = _common_arguments(dtype, max_shard_bytes, checkpoint_dir, output_dir, overwrite)
    checkpoint = OrbaxCheckpoint(checkpoint_dir)
    _check_output(checkpoint.step_dir, output_dir, overwrite)  # the assets beside params/ are input too
    shapes = checkpoint.shapes()
    action_tokenizer = _load_fast_tokenizer(fast_tokenizer)
    if is_openpi_fast_tree(shapes) and action_tokenizer is not None:
        for name, value in (("action_horizon", action_tokenizer.time_horizon), ("action_dim", action_tokenizer.action_dim)):
            if value is not None:
                config_overrides.setdefault(name, value)
    try:
        config = config_from_openpi_shapes(shapes, **config_overrides)
        check_openpi_shapes(shapes, config)
    except KeyError as error:
        raise ConversionError(f"{checkpoint.params_dir} is not a π0/π0.5 parameter tree: missing leaf {error}") from None
    except ValueError as error:
        raise ConversionError(f"{checkpoint.params_dir}: {error}") from None
    norm_stats_path = find_norm_stats(checkpoint.step_dir, asset_id)
    norm_stats = _read_norm_stats(norm_stats_path) if norm_stats_path else None
    if norm_stats is None:
        logger.warning(f"no assets/<asset_id>/norm_stats.json in {checkpoint.step_dir}: the output has no norm stats")
    if action_tokenizer is not None and not isinstance(config, PI0FastConfig):
        raise ConversionError(f"--fast-tokenizer is for π0-FAST checkpoints; {checkpoint.params_dir} holds a π0/π0.5 model")
    tokenizer = _check_tokenizer(tokenizer, config)
    processor = _build_processor(config, norm_stats, tokenizer, processor_options, action_tokenizer)
    plan = planned_shapes(config)
    itemsize = torch.empty((), dtype=torch_dtype).element_size()
    _check_disk_space(output_dir, sum(math.prod(s) for s in plan.values()) * itemsize + _OpenpiLeafSource.spill_bytes(checkpoint))

    with atomic_output_dir(output_dir, overwrite) as folder:
        source = _OpenpiLeafSource(checkpoint, folder / ".scratch")
        try:
            with ShardedSafetensorsWriter(folder, plan, torch_dtype, max_shard_bytes) as writer, _progress(
                writer.total_bytes, f"converting {checkpoint.step_dir.parent.name}/{checkpoint.step_dir.name}", progress
            ) as bar:
                for name, tensor in iter_openpi_state_dict(source.read, config):
                    bar.update(writer.write(name, tensor))
                    del tensor
        finally:
            source.close()
        unused = sorted(set(checkpoint.leaves) - source.used)
        if unused:
            raise ConversionError(f"checkpoint leaves not used by the conversion: {_names(unused)}")
        _save_config(config, torch_dtype, folder)
        _write_processor_files(folder, processor, norm_stats, tokenizer)
        if processor is None and action_tokenizer is not None:
            action_tokenizer.save_pretrained(folder / FAST_TOKENIZER_DIR)
    return ConversionResult(output_dir, config, torch_dtype, [output_dir / n for n in writer.filenames], writer.total_bytes,
                            norm_stats_path, processor=processor is not None)


def _load_fast_tokenizer(folder: str | os.PathLike[str] | None) -> FASTActionTokenizer | None:
    if folder is None:
        return None
    try:
        return FASTActionTokenizer.from_pretrained(Path(folder).expanduser())
    except (OSError, ValueError) as error:
        raise ConversionError(f"unusable FAST tokenizer {folder}: {first_line(error)}") from None


def _check_output(input_path: str | os.PathLike[str], output_dir: Path, overwrite: bool) -> None:
    """Fail before reading anything: the output must not overlap the input, and may replace a non-empty folder
    only with `overwrite`."""
    try:
        check_separate(input_path, output_dir)
        check_output_dir(output_dir, overwrite)
    except OutputPathError as error:
        raise ConversionError(str(error)) from None


def _common_arguments(
    dtype: str, max_shard_bytes: int | str, input_path: str | os.PathLike[str], output_dir: str | os.PathLike[str], overwrite: bool
) -> tuple[torch.dtype, int, Path]:
    if dtype not in DTYPES:
        raise ConversionError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    try:
        shard_bytes = parse_size(max_shard_bytes)
    except ValueError as error:
        raise ConversionError(str(error)) from None
    output_dir = Path(output_dir).expanduser().absolute()
    _check_output(input_path, output_dir, overwrite)
    return DTYPES[dtype], shard_bytes, output_dir


# ---------------------------------------------------------------------------------------------------------------------
# LeRobot / transformers PI0 (PyTorch, Hugging Face layout) <-> ours
# ---------------------------------------------------------------------------------------------------------------------

# One Gemma decoder layer in the Hugging Face layout -> (our name inside `layers.{i}.{vlm|expert}`, part, parts).
# q/k/v and gate/up are separate there and fused (concatenated along the output rows, in this order) here.
_HF_LAYER: dict[str, tuple[str, int, int]] = {
    "self_attn.q_proj.weight": ("qkv_proj.weight", 0, 3),
    "self_attn.k_proj.weight": ("qkv_proj.weight", 1, 3),
    "self_attn.v_proj.weight": ("qkv_proj.weight", 2, 3),
    "self_attn.o_proj.weight": ("o_proj.weight", 0, 1),
    "mlp.gate_proj.weight": ("gate_up_proj.weight", 0, 2),
    "mlp.up_proj.weight": ("gate_up_proj.weight", 1, 2),
    "mlp.down_proj.weight": ("down_proj.weight", 0, 1),
    "input_layernorm.weight": ("attn_norm.weight", 0, 1),
    "post_attention_layernorm.weight": ("mlp_norm.weight", 0, 1),
    # π0.5 adaRMS (openpi's PyTorch Gemma, used by LeRobot): Linear cond -> [scale | shift | gate]
    "input_layernorm.dense.weight": ("attn_norm.modulation.weight", 0, 1),
    "input_layernorm.dense.bias": ("attn_norm.modulation.bias", 0, 1),
    "post_attention_layernorm.dense.weight": ("mlp_norm.modulation.weight", 0, 1),
    "post_attention_layernorm.dense.bias": ("mlp_norm.modulation.bias", 0, 1),
}
_HEADS = ("state_proj", "action_in_proj", "action_time_mlp_in", "action_time_mlp_out", "action_out_proj", "time_mlp_in", "time_mlp_out")

# Key prefixes: LeRobot wraps everything in `model.`; openpi's PyTorch port and transformers' saved files use
# `paligemma_with_expert.{paligemma,gemma_expert}`; transformers' modules are `model.vlm` / `model.dit`.
_VLM = r"(?:model\.)?(?:paligemma_with_expert\.paligemma\.(?:model\.)?|vlm\.)"
_EXPERT = r"(?:model\.)?(?:paligemma_with_expert\.gemma_expert\.(?:model\.)?|dit\.)"
_LM = r"language_model\.(?:model\.)?"


@dataclass(frozen=True)
class _Target:
    name: str  # our parameter
    part: int  # position among the fused parts
    parts: int


_DROP_TIED_EMBEDDING = "tied LM head (copy of the text embedding)"
_HF_RULES: list[tuple[re.Pattern[str], Callable[[re.Match[str]], _Target | str]]] = [
    (re.compile(_VLM + r"vision_tower\.(?:vision_model\.)?(.+)"), lambda m: _Target(f"vision_tower.{m[1]}", 0, 1)),
    (re.compile(_VLM + r"multi_modal_projector\.linear\.(weight|bias)"), lambda m: _Target(f"image_projection.{m[1]}", 0, 1)),
    (re.compile(_VLM + _LM + r"embed_tokens\.weight"), lambda m: _Target("embed_tokens.weight", 0, 1)),
    (re.compile(_VLM + r"(?:language_model\.)?lm_head\.weight"), lambda m: _DROP_TIED_EMBEDDING),
    (re.compile(_VLM + _LM + r"layers\.(\d+)\.(.+)"), lambda m: _layer_target(int(m[1]), "vlm", m[2])),
    (re.compile(_VLM + _LM + r"norm\.weight"), lambda m: _Target("vlm_final_norm.weight", 0, 1)),
    (re.compile(_EXPERT + r"(?:embed_tokens|lm_head)\.weight"), lambda m: "unused action-expert embedding / LM head"),
    (re.compile(_EXPERT + r"layers\.(\d+)\.(.+)"), lambda m: _layer_target(int(m[1]), "expert", m[2])),
    (re.compile(_EXPERT + r"norm\.weight"), lambda m: _Target("expert_final_norm.weight", 0, 1)),
    (re.compile(_EXPERT + r"norm\.dense\.(weight|bias)"), lambda m: _Target(f"expert_final_norm.modulation.{m[1]}", 0, 1)),
    (re.compile(r"(?:model\.)?(?:embed_action_time\.)?(" + "|".join(_HEADS) + r")\.(weight|bias)"), lambda m: _Target(f"{m[1]}.{m[2]}", 0, 1)),
    (re.compile(r"(?:normalize_inputs|normalize_targets|unnormalize_outputs)\..+"), lambda m: "LeRobot normalization buffer"),
]


def _layer_target(layer: int, expert: str, rest: str) -> _Target | str:
    if rest not in _HF_LAYER:
        return ""
    name, part, parts = _HF_LAYER[rest]
    return _Target(f"layers.{layer}.{expert}.{name}", part, parts)


def _hf_key_target(key: str) -> _Target | str:
    """Where a LeRobot / transformers tensor goes: a `_Target`, a reason to drop it, or "" when unknown."""
    for pattern, target in _HF_RULES:
        match = pattern.fullmatch(key)
        if match:
            return target(match)
    return ""


def _safetensors_files(folder: Path) -> list[Path]:
    """The weight files of a Hugging Face-style folder: those of `model.safetensors.index.json`, or `model.safetensors`."""
    index = folder / INDEX_FILE
    if index.is_file():
        try:
            weight_map = json.loads(index.read_text())["weight_map"]
        except (ValueError, KeyError, TypeError) as error:
            raise ConversionError(f"unreadable {index}: {error}") from None
        files = [folder / name for name in sorted(set(weight_map.values()))]
    else:
        files = [folder / SINGLE_FILE]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise ConversionError(f"{folder} has no safetensors weights: missing {', '.join(missing)}")
    return files


@dataclass
class _HFWeights:
    """The tensors of a Hugging Face-layout π0 folder, grouped by the parameter of ours they make up."""

    folder: Path
    files: dict[str, Path]  # source key -> file
    shapes: dict[str, tuple[int, ...]]  # source key -> shape
    sources: dict[str, list[str | None]]  # our name -> source keys in part order
    dropped: list[str]

    @classmethod
    def scan(cls, folder: Path) -> _HFWeights:
        files: dict[str, Path] = {}
        shapes: dict[str, tuple[int, ...]] = {}
        for path in _safetensors_files(folder):
            try:
                with safe_open(path, framework="pt") as handle:
                    for key in handle.keys():
                        files[key] = path
                        shapes[key] = tuple(handle.get_slice(key).get_shape())
            except Exception as error:  # safetensors raises its own SafetensorError on malformed files
                raise ConversionError(f"cannot read {path}: {first_line(error)}") from None
        sources: dict[str, list[str | None]] = {}
        dropped, unknown, tied = [], [], []
        for key in files:
            target = _hf_key_target(key)
            if isinstance(target, _Target):
                parts = sources.setdefault(target.name, [None] * target.parts)
                if parts[target.part] is not None:
                    raise ConversionError(f"{folder}: both {parts[target.part]} and {key} map to {target.name}")
                parts[target.part] = key
            elif target == _DROP_TIED_EMBEDDING:
                tied.append(key)
            elif target:
                dropped.append(key)
            else:
                unknown.append(key)
        if unknown:
            raise ConversionError(f"{folder}: tensors not part of a π0/π0.5 model: {_names(sorted(unknown))}")
        if "embed_tokens.weight" not in sources and tied:  # hub files keep only the tied LM head
            sources["embed_tokens.weight"] = [tied.pop()]
        dropped += tied
        incomplete = [f"{name} (lacks part {parts.index(None)})" for name, parts in sources.items() if None in parts]
        if incomplete:
            raise ConversionError(f"{folder}: incomplete fused parameters: {_names(sorted(incomplete))}")
        return cls(folder, files, shapes, sources, sorted(dropped))

    def fused_shape(self, name: str) -> tuple[int, ...]:
        shapes = [self.shapes[key] for key in self.sources[name] if key is not None]
        return (sum(s[0] for s in shapes), *shapes[0][1:])

    def tensor(self, name: str, handles: Mapping[Path, Any]) -> torch.Tensor:
        parts = [handles[self.files[key]].get_tensor(key) for key in self.sources[name] if key is not None]
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=0)


# Released Gemma variants, as LeRobot names them in its config (heads, kv heads, head dim).
_GEMMA_VARIANTS = {"gemma_2b": (8, 1, 256), "gemma_300m": (8, 1, 256)}
_SIGLIP_HEADS = {1152: 16}  # So400m/14


def _hf_config_hints(folder: Path) -> dict[str, Any]:
    """PI0Config fields that the weights do not determine, from a transformers or LeRobot `config.json`."""
    path = folder / CONFIG_FILE
    if not path.is_file():
        return {}
    try:
        raw = json.loads(path.read_text())
    except ValueError as error:
        raise ConversionError(f"unreadable {path}: {error}") from None
    hints: dict[str, Any] = {}
    if isinstance(raw.get("vlm_config"), dict):  # transformers PI0Config
        text, vision, dit = raw["vlm_config"].get("text_config", {}), raw["vlm_config"].get("vision_config", {}), raw.get("dit_config", {})
        for ours, theirs in (("num_attention_heads", "num_attention_heads"), ("num_key_value_heads", "num_key_value_heads"), ("head_dim", "head_dim")):
            if theirs in text:
                hints[ours] = text[theirs]
                if theirs in dit and dit[theirs] != text[theirs]:
                    raise ConversionError(f"{path}: the action expert's {theirs} ({dit[theirs]}) differs from the VLM's ({text[theirs]}); π0 shares them")
        if "num_attention_heads" in vision:
            hints["vision_num_heads"] = vision["num_attention_heads"]
        if "rms_norm_eps" in text:
            hints["rms_norm_eps"] = text["rms_norm_eps"]
        theta = (text.get("rope_parameters") or {}).get("rope_theta", text.get("rope_theta"))
        if theta is not None:
            hints["rope_theta"] = theta
    else:  # LeRobot policy config
        variant = _GEMMA_VARIANTS.get(raw.get("paligemma_variant", ""))
        if variant:
            hints.update(zip(("num_attention_heads", "num_key_value_heads", "head_dim"), variant))
        if "tokenizer_max_length" in raw:
            hints["max_token_len"] = raw["tokenizer_max_length"]
    renames = {
        "chunk_size": "action_horizon",
        "num_inference_steps": "num_inference_steps",
        "num_steps": "num_inference_steps",
        "time_sampling_beta_alpha": "time_beta_alpha",
        "time_sampling_beta_beta": "time_beta_beta",
        "time_sampling_scale": "time_scale",
        "time_sampling_offset": "time_offset",
        "min_period": "time_min_period",
        "max_period": "time_max_period",
    }
    hints.update({ours: raw[theirs] for theirs, ours in renames.items() if raw.get(theirs) is not None})
    return hints


def _config_from_hf(weights: _HFWeights, hints: Mapping[str, Any], overrides: Mapping[str, Any]) -> PI0Config:
    def shape(name: str) -> tuple[int, ...]:
        if name not in weights.sources:
            raise ConversionError(f"{weights.folder}: not a π0/π0.5 checkpoint, no tensor for {name}")
        return weights.fused_shape(name)

    def count(pattern: str) -> int:
        return 1 + max((int(m[1]) for name in weights.sources if (m := re.fullmatch(pattern, name))), default=-1)

    settings = {**hints, **overrides}
    width, _, patch, _ = shape("vision_tower.embeddings.patch_embedding.weight")
    q_rows = weights.shapes[weights.sources["layers.0.vlm.qkv_proj.weight"][0]][0] if "layers.0.vlm.qkv_proj.weight" in weights.sources else 0
    k_rows = weights.shapes[weights.sources["layers.0.vlm.qkv_proj.weight"][1]][0] if q_rows else 0
    kv_heads = settings.get("num_key_value_heads", 1)
    head_dim = settings.get("head_dim", k_rows // kv_heads if k_rows else 0)
    vision_heads = settings.get("vision_num_heads", _SIGLIP_HEADS.get(width))
    if vision_heads is None:
        raise ConversionError(f"{weights.folder}: cannot tell the SigLIP head count of width {width} from the weights; pass vision_num_heads")
    vocab, vlm_width = shape("embed_tokens.weight")
    inferred = dict(
        pi05="time_mlp_in.weight" in weights.sources,
        image_size=math.isqrt(shape("vision_tower.embeddings.position_embedding.weight")[0]) * patch,
        patch_size=patch,
        vision_hidden_size=width,
        vision_intermediate_size=shape("vision_tower.encoder.layers.0.mlp.fc1.weight")[0],
        vision_num_layers=count(r"vision_tower\.encoder\.layers\.(\d+)\.layer_norm1\.weight"),
        vision_num_heads=vision_heads,
        vlm_hidden_size=vlm_width,
        vlm_intermediate_size=shape("layers.0.vlm.gate_up_proj.weight")[0] // 2,
        expert_hidden_size=shape("layers.0.expert.o_proj.weight")[0],
        expert_intermediate_size=shape("layers.0.expert.gate_up_proj.weight")[0] // 2,
        num_hidden_layers=count(r"layers\.(\d+)\.vlm\.o_proj\.weight"),
        num_attention_heads=q_rows // head_dim if head_dim else 0,
        num_key_value_heads=kv_heads,
        head_dim=head_dim,
        vocab_size=vocab,
        action_dim=shape("action_in_proj.weight")[1],
    )
    try:
        return PI0Config(**{**inferred, **settings})
    except (ValueError, TypeError, ZeroDivisionError) as error:
        raise ConversionError(f"{weights.folder}: cannot build a config from these weights: {error}") from None


def convert_hf_checkpoint(
    input_dir: str | os.PathLike[str],
    output_dir: str | os.PathLike[str],
    *,
    dtype: str = "float32",
    tokenizer: str | os.PathLike[str] | None = None,
    norm_stats: str | os.PathLike[str] | None = None,
    processor_options: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    max_shard_bytes: int | str = DEFAULT_MAX_SHARD_BYTES,
    progress: bool = False,
    **config_overrides: Any,
) -> ConversionResult:
    """Import a LeRobot (`lerobot/pi0_base`-style) or transformers `PI0ForConditionalGeneration` folder.

    Keys of either layout (LeRobot's `model.paligemma_with_expert...`, openpi's PyTorch port, transformers' saved
    and in-memory names) are recognised; q/k/v and gate/up are fused into our layout; the unused action-expert
    embedding / LM head, the VLM's tied LM head (when the embedding is also present) and LeRobot normalization
    buffers are dropped (listed in the result). Head counts and the action horizon come from the folder's
    `config.json` where the weights cannot tell them; `config_overrides` win over both. Norm stats for the processor
    files come from `norm_stats` (an openpi `norm_stats.json`, file or folder) or else from a LeRobot folder's
    `policy_preprocessor_step_*_normalizer_processor.safetensors`.
    """
    torch_dtype, max_shard_bytes, output_dir = _common_arguments(dtype, max_shard_bytes, input_dir, output_dir, overwrite)
    folder = Path(input_dir).expanduser()
    if not folder.is_dir():
        raise ConversionError(f"input folder {folder} does not exist")
    weights = _HFWeights.scan(folder)
    config = _config_from_hf(weights, _hf_config_hints(folder), config_overrides)
    plan = planned_shapes(config)
    have = {name: weights.fused_shape(name) for name in weights.sources}
    missing = sorted(set(plan) - set(have))
    unexpected = sorted(set(have) - set(plan))
    misshaped = sorted(f"{n} {have[n]} (expected {plan[n]})" for n in set(plan) & set(have) if have[n] != plan[n])
    problems = [f"{kind}: {_names(names)}" for kind, names in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", misshaped)) if names]
    if problems:
        raise ConversionError(f"{folder} does not match the inferred {'π0.5' if config.pi05 else 'π0'} config; " + "; ".join(problems))
    if norm_stats is not None:
        stats_path: Path | None = Path(norm_stats).expanduser()
        stats = _read_norm_stats(stats_path)
    else:
        stats_path, stats = lerobot_norm_stats(folder) or (None, None)
    tokenizer = _check_tokenizer(tokenizer, config)
    processor = _build_processor(config, stats, tokenizer, processor_options)
    itemsize = torch.empty((), dtype=torch_dtype).element_size()
    _check_disk_space(output_dir, sum(math.prod(s) for s in plan.values()) * itemsize)

    with atomic_output_dir(output_dir, overwrite) as out:
        handles: dict[Path, Any] = {}
        try:
            for path in set(weights.files.values()):
                handles[path] = safe_open(path, framework="pt")
            with ShardedSafetensorsWriter(out, plan, torch_dtype, max_shard_bytes) as writer, _progress(
                writer.total_bytes, f"converting {folder.name}", progress
            ) as bar:
                for name in plan:
                    tensor = weights.tensor(name, handles)
                    if not tensor.is_floating_point():
                        raise ConversionError(f"{folder}: tensor for {name} has dtype {tensor.dtype}; expected floating-point weights")
                    bar.update(writer.write(name, tensor))
                    del tensor
        finally:
            handles.clear()
        _save_config(config, torch_dtype, out)
        _write_processor_files(out, processor, stats, tokenizer)
    return ConversionResult(output_dir, config, torch_dtype, [output_dir / n for n in writer.filenames], writer.total_bytes,
                            stats_path, weights.dropped, processor=processor is not None)


def _hf_export_names(name: str, config: PI0Config) -> list[tuple[str, int, int]]:
    """transformers `PI0ForConditionalGeneration` parameters (and row ranges) that our parameter `name` becomes."""
    if name.startswith("vision_tower."):
        return [(f"model.vlm.{name}", 0, -1)]
    if name.startswith("image_projection."):
        return [(f"model.vlm.multi_modal_projector.linear.{name.rsplit('.', 1)[1]}", 0, -1)]
    if name == "embed_tokens.weight":
        return [("model.vlm.language_model.embed_tokens.weight", 0, -1)]
    if name == "vlm_final_norm.weight":
        return [("model.vlm.language_model.norm.weight", 0, -1)]
    if name == "expert_final_norm.weight":
        return [("model.dit.norm.weight", 0, -1)]
    if name.split(".", 1)[0] in _HEADS:
        return [(name if name.startswith("action_out_proj") else f"embed_action_time.{name}", 0, -1)]
    match = re.fullmatch(r"layers\.(\d+)\.(vlm|expert)\.(.+)", name)
    if not match:
        raise ConversionError(f"no transformers PI0 counterpart for {name}")
    layer, expert, ours = match.groups()
    prefix = f"model.vlm.language_model.layers.{layer}." if expert == "vlm" else f"model.dit.layers.{layer}."
    width = config.vlm_intermediate_size if expert == "vlm" else config.expert_intermediate_size
    q_rows, kv_rows = config.num_attention_heads * config.head_dim, config.num_key_value_heads * config.head_dim
    rows = {"qkv_proj.weight": [q_rows, kv_rows, kv_rows], "gate_up_proj.weight": [width, width]}.get(ours, [-1])
    theirs = sorted((part, key) for key, (target, part, _) in _HF_LAYER.items() if target == ours)
    if not theirs:
        raise ConversionError(f"no transformers PI0 counterpart for {name}")
    starts = np.cumsum([0, *rows[:-1]]).tolist()
    return [(prefix + key, start, start + count if count > 0 else -1) for (part, key), start, count in zip(theirs, starts, rows)]


def _transformers_config(config: PI0Config) -> Any:
    from transformers import PI0Config as HFPI0Config

    gemma = dict(num_attention_heads=config.num_attention_heads, num_key_value_heads=config.num_key_value_heads,
                 head_dim=config.head_dim, num_hidden_layers=config.num_hidden_layers, rms_norm_eps=config.rms_norm_eps,
                 rope_parameters={"rope_theta": config.rope_theta, "rope_type": "default"})
    return HFPI0Config(
        vlm_config=dict(
            text_config=dict(model_type="gemma", hidden_size=config.vlm_hidden_size, intermediate_size=config.vlm_intermediate_size,
                             vocab_size=config.vocab_size, **gemma),
            vision_config=dict(model_type="siglip_vision_model", hidden_size=config.vision_hidden_size,
                               intermediate_size=config.vision_intermediate_size, num_hidden_layers=config.vision_num_layers,
                               num_attention_heads=config.vision_num_heads, patch_size=config.patch_size,
                               image_size=config.image_size, vision_use_head=False),
            projection_dim=config.vlm_hidden_size,
            image_token_id=config.vocab_size,
        ),
        dit_config=dict(hidden_size=config.expert_hidden_size, intermediate_size=config.expert_intermediate_size, **gemma),
        chunk_size=config.action_horizon,
        max_state_dim=config.action_dim,
        max_action_dim=config.action_dim,
        num_inference_steps=config.num_inference_steps,
        time_sampling_beta_alpha=config.time_beta_alpha,
        time_sampling_beta_beta=config.time_beta_beta,
        time_sampling_scale=config.time_scale,
        time_sampling_offset=config.time_offset,
        min_period=config.time_min_period,
        max_period=config.time_max_period,
    )


def export_to_transformers(
    model_dir: str | os.PathLike[str], output_dir: str | os.PathLike[str], *, dtype: str | None = None, overwrite: bool = False
) -> Path:
    """Write a pi0-torch π0 folder as a transformers `PI0ForConditionalGeneration` folder (weights + config.json).

    For side-by-side comparisons with `transformers.PI0ForConditionalGeneration.from_pretrained(output_dir)`. q/k/v
    and gate/up are split; transformers' action expert carries an embedding table the model never reads, written as
    zeros. π0.5 has no transformers counterpart. The whole model passes through memory once (transformers writes
    the files). `dtype` defaults to the stored dtype.
    """
    from transformers import PI0ForConditionalGeneration

    source = Path(model_dir).expanduser()
    output = Path(output_dir).expanduser().absolute()
    _check_output(source, output, overwrite)
    try:
        config = PI0Config.from_pretrained(source)
    except (OSError, ValueError) as error:
        raise ConversionError(f"{source} is not a pi0-torch model folder: {first_line(error)}") from None
    if config.pi05:
        raise ConversionError("transformers' PI0ForConditionalGeneration has no π0.5 (adaRMS) variant; only π0 exports")
    files = _safetensors_files(source)
    hf_config = _transformers_config(config)
    state: dict[str, torch.Tensor] = {}
    for path in files:
        with safe_open(path, framework="pt") as handle:
            for name in handle.keys():
                tensor = handle.get_tensor(name)
                if dtype is not None:
                    tensor = tensor.to(DTYPES[dtype])
                for target, start, end in _hf_export_names(name, config):
                    state[target] = tensor if (start, end) == (0, -1) else tensor[start:end].clone()
    reference = next(iter(state.values()))
    state["model.dit.embed_tokens.weight"] = torch.zeros(config.vocab_size, config.expert_hidden_size, dtype=reference.dtype)
    with torch.device("meta"):
        model = PI0ForConditionalGeneration(hf_config)
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as error:
        raise ConversionError(f"{source} does not fill transformers' PI0: {first_line(error)}") from None
    with atomic_output_dir(output, overwrite) as folder:
        model.save_pretrained(folder)
    return output


def transformers_pi0_inputs(inputs: Mapping[str, torch.Tensor], config: PI0Config) -> dict[str, torch.Tensor]:
    """Our model inputs -> the same observation for transformers' `PI0ForConditionalGeneration` (as exported by
    `export_to_transformers`): image placeholder tokens before the text and one combined attention mask.

    transformers' processor would drop a missing camera's tokens; here every camera keeps its tokens, masked when
    missing (as openpi does), and `pixel_attention_mask` is all True so each camera's features land on its own
    tokens. Masked tokens do not advance positions, so both layouts give the same result.
    """
    batch, cameras = inputs["image_masks"].shape
    image_tokens = cameras * config.tokens_per_image
    image_token_id = config.vocab_size  # what `export_to_transformers` configures
    return dict(
        pixel_values=inputs["pixel_values"],
        pixel_attention_mask=torch.ones(batch, cameras, dtype=torch.bool, device=inputs["image_masks"].device),
        input_ids=torch.cat([inputs["input_ids"].new_full((batch, image_tokens), image_token_id), inputs["input_ids"]], dim=1),
        attention_mask=torch.cat(
            [inputs["image_masks"].repeat_interleave(config.tokens_per_image, dim=1), inputs["attention_mask"].bool()], dim=1
        ).long(),
        state=inputs["state"],
    )


# ---------------------------------------------------------------------------------------------------------------------
# command line: `pi0-torch convert`
# ---------------------------------------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--from", dest="source", choices=[*SOURCES, "pi0-torch"],
                        help="input format (pi0-torch only with --to transformers; default with --checkpoint: openpi)")
    parser.add_argument("--to", dest="target", default="pi0-torch", choices=["pi0-torch", "transformers"],
                        help="output format (default: pi0-torch; transformers = PI0ForConditionalGeneration, π0 only)")
    parser.add_argument("--input", help="openpi <run>/<step> or <step>/params folder (or gs://... to download it), or a safetensors model folder")
    parser.add_argument("--checkpoint", choices=list(PUBLISHED_CHECKPOINTS), metavar="NAME",
                        help=f"download one of openpi's published checkpoints (with its asset id and processor settings) into "
                        f"${CACHE_ENV} (default ~/.cache/pi0_torch) and convert it: {', '.join(PUBLISHED_CHECKPOINTS)}")
    parser.add_argument("--output-dir", required=True, help="folder to create (must be absent or empty unless --overwrite)")
    parser.add_argument("--dtype", choices=list(DTYPES), default=None, help="weight dtype of the output (default: float32; export: as stored)")
    parser.add_argument("--asset-id", help="openpi: which assets/<asset_id>/norm_stats.json to use (needed when there are several)")
    parser.add_argument("--norm-stats", help="lerobot/transformers: an openpi norm_stats.json for the processor files (default for a LeRobot "
                        "folder: its policy_preprocessor_step_*_normalizer_processor.safetensors)")
    parser.add_argument("--tokenizer", help="PaliGemma SentencePiece model (e.g. paligemma_tokenizer.model) to save with the "
                        "processor, or test: a small tokenizer trained offline (trials and tests only, as train --tokenizer test)")
    parser.add_argument("--fast-tokenizer", help="openpi π0-FAST: the FAST action tokenizer folder (physical-intelligence/fast "
                        "layout), saved in the output's fast_tokenizer/")
    parser.add_argument("--action-horizon", type=int, help="actions per chunk (not stored in the weights; π0-FAST DROID / "
                        "LIBERO: 10; default: the FAST tokenizer's time_horizon, else the model's default)")
    parser.add_argument("--action-dim", type=int, help="π0-FAST: action dims a FAST chunk decodes to (DROID 8, LIBERO 7; "
                        "default: the FAST tokenizer's action_dim, else 32)")
    parser.add_argument("--max-token-len", type=int, help="prompt length in tokens (π0-FAST LIBERO: 180; default: the model's)")
    parser.add_argument("--delta-action-mask", type=bool_mask, metavar="1,1,...,0", help="processor: action dims the "
                        "checkpoint predicts relative to the state (openpi's DeltaActions; ALOHA: 1,1,1,1,1,1,0,1,1,1,1,1,1,0)")
    parser.add_argument("--value-conversion", choices=sorted(CONVERSIONS), help="processor: the robot's value "
                        "conversion the checkpoint was trained with (aloha: openpi's adapt_to_pi)")
    parser.add_argument("--max-shard-size", default="5GB", help="largest weight file before sharding (default: 5GB)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    try:
        if args.target == "transformers":
            if args.source != "pi0-torch":
                raise ConversionError("--to transformers exports a pi0-torch folder: convert first, then use --from pi0-torch")
            print(f"wrote {export_to_transformers(args.input, args.output_dir, dtype=args.dtype, overwrite=args.overwrite)}")
            return 0
        options = {"delta_action_mask": args.delta_action_mask, "value_conversion": args.value_conversion}
        overrides: dict[str, Any] = {}
        if args.checkpoint or (args.input or "").startswith("gs://"):
            if args.checkpoint and args.input or (args.source or "openpi") != "openpi":
                raise ConversionError("--checkpoint NAME and gs:// inputs are openpi checkpoints: give one of them, with --from openpi or no --from")
            check_output_dir(Path(args.output_dir).expanduser(), args.overwrite)  # before a download of many GB
            fetched = fetch_openpi_checkpoint(args.input or checkpoint_url(args.checkpoint), asset_id=args.asset_id,
                                              tokenizer=args.tokenizer, fast_tokenizer=args.fast_tokenizer,
                                              progress=not args.no_progress)
            args.source, args.input, args.asset_id, args.tokenizer = "openpi", fetched.folder, fetched.asset_id, fetched.tokenizer
            args.fast_tokenizer = fetched.fast_tokenizer
            options = {**fetched.processor_options, **{k: v for k, v in options.items() if v is not None}}
            overrides = fetched.config_overrides
        if args.source is None or args.input is None:
            raise ConversionError("give --from and --input (or --checkpoint NAME for openpi's published checkpoints)")
        common = dict(dtype=args.dtype or "float32", tokenizer=args.tokenizer, overwrite=args.overwrite,
                      max_shard_bytes=args.max_shard_size, progress=not args.no_progress,
                      processor_options={k: v for k, v in options.items() if v is not None})
        overrides.update({name: getattr(args, name) for name in ("action_horizon", "action_dim", "max_token_len")
                          if getattr(args, name) is not None})  # the flags win over a published checkpoint's settings
        if args.source == "openpi":
            if args.norm_stats:
                raise ConversionError("--norm-stats is for lerobot/transformers inputs; openpi's come from assets/ (--asset-id)")
            result = convert_openpi_checkpoint(args.input, args.output_dir, asset_id=args.asset_id, fast_tokenizer=args.fast_tokenizer,
                                               **common, **overrides)
        elif args.source in ("lerobot", "transformers"):
            if args.asset_id:
                raise ConversionError("--asset-id selects openpi assets; for lerobot/transformers use --norm-stats")
            if args.fast_tokenizer:
                raise ConversionError("--fast-tokenizer is for openpi π0-FAST checkpoints")
            result = convert_hf_checkpoint(args.input, args.output_dir, norm_stats=args.norm_stats, **common, **overrides)
        else:
            raise ConversionError("--from pi0-torch needs --to transformers")
    except (CheckpointError, OutputPathError, OSError) as error:
        print(f"error: {first_line(error)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("error: interrupted; nothing was written", file=sys.stderr)
        return 130
    print(result.summary())
    return 0
