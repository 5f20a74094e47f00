"""openpi checkpoints (orbax, read without JAX) -> pi0-torch folders: [`convert_openpi_checkpoint`] (`pi0-torch
convert --from openpi`).

π0 vs π0.5 vs π0-FAST and every dimension come from the parameter tree (`pi0_torch.conversion.openpi_weights`), the norm
stats from the checkpoint's `assets/`; a LoRA fine-tune's adapters are merged into the weights. An openpi leaf is read
one layer at a time: a leaf stored as one big chunk is decompressed once, as a stream, and its layers kept in memory or
spilled to a scratch folder until they are written ([`_OpenpiLeafSource`]); every leaf must be used. The folder is
written by `pi0_torch.conversion.output_folder`.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pi0_torch.conversion.openpi_paligemma import openpi_lora_ranks
from pi0_torch.conversion.openpi_weights import check_openpi_shapes, config_from_openpi_shapes, is_openpi_fast_tree, iter_openpi_state_dict
from pi0_torch.conversion.orbax_reader import LeafInfo, OrbaxCheckpoint, first_line, streaming_reason
from pi0_torch.conversion.output_folder import (
    DEFAULT_MAX_SHARD_BYTES,
    ConversionError,
    ConversionResult,
    ShardedSafetensorsWriter,
    build_processor,
    processor_inputs_missing,
    check_disk_space,
    check_output,
    check_tokenizer,
    checked_arguments,
    name_list,
    planned_shapes,
    progress_bar,
    read_norm_stats,
    save_config,
    write_processor_files,
)
from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer
from pi0_torch.processing.processing_pi0_fast import FAST_TOKENIZER_DIR
from pi0_torch.utils.files import atomic_output_dir

logger = logging.getLogger(__name__)

_SMALL_LEAF_BYTES = 64 << 20  # a multi-layer chunk up to this size keeps its layers in memory, a bigger one spills them


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
    torch_dtype, max_shard_bytes, output_dir = checked_arguments(dtype, max_shard_bytes, checkpoint_dir, output_dir, overwrite)
    checkpoint = OrbaxCheckpoint(checkpoint_dir)
    check_output(checkpoint.step_dir, output_dir, overwrite)  # the assets beside params/ are input too
    if (reason := streaming_reason()) is not None:
        logger.warning(f"{reason}: each stored chunk is decoded whole, so memory peaks at about twice the largest one "
                       "(10 GB for a single-device float32 π0)")
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
    if lora_ranks := openpi_lora_ranks(shapes):
        logger.info("merging openpi's LoRA adapters into the weights they adapt: " + ", ".join(
            f"{('VLM', 'action expert')[expert]} {kind} rank {rank}" for (expert, kind), rank in sorted(lora_ranks.items())))
    norm_stats_path = find_norm_stats(checkpoint.step_dir, asset_id)
    norm_stats = read_norm_stats(norm_stats_path) if norm_stats_path else None
    if norm_stats is None:
        logger.warning(f"no assets/<asset_id>/norm_stats.json in {checkpoint.step_dir}: the output has no norm stats")
    if action_tokenizer is not None and not isinstance(config, PI0FastConfig):
        raise ConversionError(f"--fast-tokenizer is for π0-FAST checkpoints; {checkpoint.params_dir} holds a π0/π0.5 model")
    tokenizer = check_tokenizer(tokenizer, config)
    processor = build_processor(config, norm_stats, tokenizer, processor_options, action_tokenizer)
    plan = planned_shapes(config)
    itemsize = torch.empty((), dtype=torch_dtype).element_size()
    check_disk_space(output_dir, sum(math.prod(s) for s in plan.values()) * itemsize + _OpenpiLeafSource.spill_bytes(checkpoint))

    with atomic_output_dir(output_dir, overwrite) as folder:
        source = _OpenpiLeafSource(checkpoint, folder / ".scratch")
        try:
            with ShardedSafetensorsWriter(folder, plan, torch_dtype, max_shard_bytes) as writer, progress_bar(
                writer.total_bytes, f"converting {checkpoint.step_dir.parent.name}/{checkpoint.step_dir.name}", progress
            ) as bar:
                for name, tensor in iter_openpi_state_dict(source.read, config, lora_ranks):
                    bar.update(writer.write(name, tensor))
                    del tensor
        finally:
            source.close()
        unused = sorted(set(checkpoint.leaves) - source.used)
        if unused:
            raise ConversionError(f"checkpoint leaves not used by the conversion: {name_list(unused)}")
        save_config(config, torch_dtype, folder)
        write_processor_files(folder, processor, norm_stats, tokenizer)
        if processor is None and action_tokenizer is not None:
            action_tokenizer.save_pretrained(folder / FAST_TOKENIZER_DIR)
    return ConversionResult(output_dir, config, torch_dtype, [output_dir / n for n in writer.filenames], writer.total_bytes,
                            norm_stats_path, processor_missing=processor_inputs_missing(config, norm_stats, tokenizer, action_tokenizer))


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


def _load_fast_tokenizer(folder: str | os.PathLike[str] | None) -> FASTActionTokenizer | None:
    if folder is None:
        return None
    try:
        return FASTActionTokenizer.from_pretrained(Path(folder).expanduser())
    except (OSError, ValueError) as error:
        raise ConversionError(f"unusable FAST tokenizer {folder}: {first_line(error)}") from None


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
