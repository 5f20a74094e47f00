"""What every conversion writes: a pi0-torch model folder (config, safetensors weights streamed tensor by tensor,
the processor files), the checks made before anything is written, and the [`ConversionResult`] it reports.

The openpi direction (`pi0_torch.conversion.convert_openpi`) and the LeRobot / transformers one
(`pi0_torch.conversion.convert_hf`) both produce tensors in our layout one at a time; [`ShardedSafetensorsWriter`]
puts each into its planned place in the output files (laid out from the config before any weight is read, sharded as
`save_pretrained` shards) and drops it, so memory stays near the largest single tensor.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import struct
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from pi0_torch.utils.progress import tqdm

from pi0_torch.conversion.orbax_reader import CheckpointError
from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.normalization import NormStats, load_openpi_norm_stats, save_openpi_norm_stats
from pi0_torch.processing.processing_pi0 import NORM_STATS_FILE, PI0Processor
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.processing.tokenization import TEST_TOKENIZER, TEST_TOKENIZER_VOCAB, PromptTokenizer, build_test_tokenizer
from pi0_torch.utils.files import OutputPathError, check_output_dir, check_separate

logger = logging.getLogger(__name__)

DTYPES: dict[str, torch.dtype] = {"float32": torch.float32, "bfloat16": torch.bfloat16}
DEFAULT_MAX_SHARD_BYTES = 5 * 10**9  # "5GB", as save_pretrained counts it
SINGLE_FILE = "model.safetensors"
INDEX_FILE = "model.safetensors.index.json"
_SAFETENSORS_DTYPES = {torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16"}
_WRITE_BLOCK = 64 << 20  # bytes of a tensor cast and written at once


class ConversionError(CheckpointError):
    """A conversion that cannot proceed (bad input, existing output, not enough disk). The message is one line."""


# ---------------------------------------------------------------------------------------------------------------------
# checks before anything is written, the plan, progress
# ---------------------------------------------------------------------------------------------------------------------


def check_output(input_path: str | os.PathLike[str], output_dir: Path, overwrite: bool) -> None:
    """Fail before reading anything: the output must not overlap the input, and may replace a non-empty folder
    only with `overwrite`."""
    try:
        check_separate(input_path, output_dir)
        check_output_dir(output_dir, overwrite)
    except OutputPathError as error:
        raise ConversionError(str(error)) from None


def checked_arguments(
    dtype: str, max_shard_bytes: int | str, input_path: str | os.PathLike[str], output_dir: str | os.PathLike[str], overwrite: bool
) -> tuple[torch.dtype, int, Path]:
    """The arguments every conversion takes, checked before anything is read: the torch dtype, the largest shard
    in bytes and the absolute output folder."""
    if dtype not in DTYPES:
        raise ConversionError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    try:
        shard_bytes = parse_size(max_shard_bytes)
    except ValueError as error:
        raise ConversionError(str(error)) from None
    output_dir = Path(output_dir).expanduser().absolute()
    check_output(input_path, output_dir, overwrite)
    return DTYPES[dtype], shard_bytes, output_dir


def _model_class(config: PI0Config | PI0FastConfig) -> type[PI0ForActionGeneration | PI0FastForActionGeneration]:
    return PI0FastForActionGeneration if isinstance(config, PI0FastConfig) else PI0ForActionGeneration


def planned_shapes(config: PI0Config | PI0FastConfig) -> dict[str, tuple[int, ...]]:
    """Every parameter the config's model (`PI0ForActionGeneration` / `PI0FastForActionGeneration`) has, with its
    shape, in state-dict order (nothing allocated)."""
    with torch.device("meta"):
        model = _model_class(config)(config)
    return {name: tuple(tensor.shape) for name, tensor in model.state_dict().items()}


def check_disk_space(output_dir: Path, needed: int) -> None:
    """Refuse an output whose `needed` bytes do not fit in the free space where it is written."""
    probe = next(p for p in (output_dir, *output_dir.parents) if p.exists())
    free = shutil.disk_usage(probe).free
    if free < needed:
        raise ConversionError(f"not enough free disk space for {output_dir}: need {needed / 1e9:.2f} GB, {free / 1e9:.2f} GB free")


def progress_bar(total: int, description: str, enabled: bool) -> tqdm:
    """A progress bar of `total` bytes on stderr (silent unless `enabled`)."""
    return tqdm(total=total, desc=description, unit="B", unit_scale=True, unit_divisor=1024, disable=not enabled, file=sys.stderr)


def _human(count: float) -> str:
    """1234567 -> '1.23 M' (decimal prefixes)."""
    for prefix, scale in (("T", 1e12), ("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if count >= scale:
            return f"{count / scale:.2f} {prefix}"
    return f"{count:.0f} "


def name_list(names: Iterable[str], limit: int = 12) -> str:
    """`names` for a message: the first `limit`, then how many more."""
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f" ... ({len(names) - limit} more)" if len(names) > limit else "")


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
            raise ConversionError(f"{len(self.missing)} parameters were never filled: {name_list(self.missing)}")
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


# ---------------------------------------------------------------------------------------------------------------------
# config and processor files, and the result
# ---------------------------------------------------------------------------------------------------------------------


def save_config(config: PI0Config | PI0FastConfig, dtype: torch.dtype, folder: Path) -> None:
    config.architectures = [_model_class(config).__name__]
    config.dtype = dtype
    config.save_pretrained(folder)


def read_norm_stats(path: Path) -> dict[str, NormStats]:
    try:
        stats = load_openpi_norm_stats(path)
    except (ValueError, OSError) as error:
        raise ConversionError(f"unusable norm stats {path}: {error}") from None
    missing = [key for key in ("state", "actions") if key not in stats]
    if missing:
        raise ConversionError(f"norm stats {path} lack {', '.join(missing)} (have {', '.join(sorted(stats)) or 'nothing'})")
    return stats


def check_tokenizer(tokenizer: str | Path | None, config: PI0Config | PI0FastConfig) -> Path | PromptTokenizer | None:
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


def build_processor(
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
    missing = processor_inputs_missing(config, norm_stats, tokenizer, fast_tokenizer)
    if missing:
        if processor_options:
            raise ConversionError(f"processor settings {sorted(processor_options)} need {' and '.join(missing)}")
        return None
    try:
        if fast:
            return PI0FastProcessor.from_config(config, tokenizer, fast_tokenizer, norm_stats, **(processor_options or {}))
        return PI0Processor.from_config(config, tokenizer=tokenizer, norm_stats=norm_stats, **(processor_options or {}))
    except (ValueError, OSError, TypeError) as error:
        given = TEST_TOKENIZER if isinstance(tokenizer, PromptTokenizer) else tokenizer  # (its source, not an object repr)
        raise ConversionError(f"cannot build the processor with --tokenizer {given}: {error}") from None


def processor_inputs_missing(
    config: PI0Config | PI0FastConfig, norm_stats: Any, tokenizer: Any, fast_tokenizer: Any = None
) -> list[str]:
    """What a processor still needs ("norm stats", "--tokenizer", π0-FAST's "--fast-tokenizer"); empty: nothing."""
    needed = {"norm stats": norm_stats, "--tokenizer": tokenizer}
    if isinstance(config, PI0FastConfig):
        needed["--fast-tokenizer"] = fast_tokenizer
    return [name for name, value in needed.items() if value is None]


def write_processor_files(
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
    processor_missing: list[str] = field(default_factory=list)  # what the processor lacked (empty: it was written)

    def summary(self) -> str:
        fast = isinstance(self.config, PI0FastConfig)
        kind = "π0-FAST" if fast else "π0.5" if self.config.pi05 else "π0"
        processor = "PI0FastProcessor" if fast else "PI0Processor"
        params = self.weight_bytes // torch.empty((), dtype=self.dtype).element_size()
        lines = [
            f"wrote {self.output_dir}: {kind}, {_human(params)} parameters, {_human(self.weight_bytes)}B of "
            f"{str(self.dtype).removeprefix('torch.')} weights in {len(self.weight_files)} file(s)",
            f"norm stats: {self.norm_stats or 'none found'}",
            "processor: " + (f"none: it needs {' and '.join(self.processor_missing)}"
                             + (" (--tokenizer: PaliGemma's SentencePiece file, or test)" if "--tokenizer" in self.processor_missing else "")
                             if self.processor_missing else f"written ({processor}.from_pretrained loads it)"),
        ]
        if self.dropped:
            lines.append(f"not converted (unused by the model): {name_list(self.dropped, 6)}")
        return "\n".join(lines)
