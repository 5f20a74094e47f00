"""Read (and, for tests and benchmarks, write) orbax PyTree checkpoints without JAX.

openpi saves parameters with orbax: a `params/` folder holding `_METADATA` (the tree: one entry per leaf, keys in
order) and the arrays as zarr arrays inside an OCDBT key-value store (`manifest.ocdbt`, `d/...`,
`ocdbt.process_*/`). Each array lives under the key `".".join(tree keys)`. `tensorstore` opens that store
directly, so reading needs neither JAX nor orbax.

Leaf paths are reported the way openpi names parameters: tree keys joined by "/", without the top-level item key
(`params`) and without the `/value` suffix that nnx state adds (`PaliGemma/llm/layers/attn/q_einsum/w`).

```python
>>> from pi0_torch.conversion.orbax_reader import OrbaxCheckpoint
>>> ckpt = OrbaxCheckpoint("tests/fixtures/openpi/pi0_small/ckpt/0")
>>> ckpt.leaves["PaliGemma/llm/layers/attn/q_einsum/w"].shape
(3, 4, 64, 32)
>>> ckpt.read("PaliGemma/llm/layers/attn/q_einsum/w/value", layer=1).shape
(4, 64, 32)

```
"""

from __future__ import annotations

import ast
import functools
import json
import math
import os
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tensorstore as ts

from pi0_torch.conversion.openpi_paligemma import strip_value_suffix
from pi0_torch.utils.validation import first_line

try:
    import zstandard
except ImportError:  # optional: without it a chunk is decoded whole by tensorstore (peak memory: 2x the chunk)
    zstandard = None

METADATA_FILE = "_METADATA"
MAX_FLAT_KEY_CHARS = 2_000  # a leaf's path as a tuple repr: a few hundred characters in openpi's checkpoints
_STREAM_READ_BYTES = 16 << 20  # compressed bytes fetched per read when a chunk is decompressed as a stream
VALUE_SUFFIX = "value"
# orbax value types that hold an array (other entries, e.g. empty nodes, carry no data)
_ARRAY_VALUE_TYPES = frozenset({"jax.Array", "np.ndarray", "scalar"})


def streaming_reason() -> str | None:
    """Why zstd chunks are decoded whole by tensorstore here instead of decompressed as streams (None: they are
    streamed, see `OrbaxCheckpoint.iter_rows`)."""
    if zstandard is None:
        return "zstandard is not installed"
    if not _reads_byte_ranges():
        return "tensorstore reads byte ranges of a stored value from 0.1.81 on (Python 3.10's last is 0.1.78)"
    return None


@functools.lru_cache(maxsize=None)
def _reads_byte_ranges() -> bool:
    """Whether this tensorstore's `KvStore.read` takes a `byte_range` (asked once, of an in-memory store)."""
    try:
        ts.KvStore.open({"driver": "memory"}).result().read("probe", byte_range=slice(0, 0)).result()
    except TypeError:
        return False
    return True


class CheckpointError(ValueError):
    """A checkpoint folder that is missing, foreign, incomplete or corrupt. The message is one line."""


@dataclass(frozen=True)
class LeafInfo:
    """One array leaf of the checkpoint."""

    path: str  # openpi name: tree keys joined by "/", without the item key and the "/value" suffix
    key: str  # name of the array inside the store: the full tree keys joined by "."
    shape: tuple[int, ...]
    dtype: np.dtype
    chunks: tuple[int, ...]  # zarr chunk shape: slicing along an axis whose chunk is 1 reads only that slice

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def find_params_dir(path: str | os.PathLike[str]) -> Path:
    """The orbax item folder (the one holding `_METADATA`) for an openpi `<step>/params` folder or its `<step>`."""
    path = Path(path).expanduser()
    if not path.exists():
        raise CheckpointError(f"checkpoint folder {path} does not exist")
    if not path.is_dir():
        raise CheckpointError(f"{path} is a file; expected an openpi checkpoint folder (<step> or <step>/params)")
    for candidate in (path, path / "params"):
        if (candidate / METADATA_FILE).is_file():
            return candidate
    steps = sorted(p.name for p in path.iterdir() if (p / "params" / METADATA_FILE).is_file())
    if steps:
        raise CheckpointError(f"{path} is a training run with steps {', '.join(steps)}; pass one step folder, e.g. {path / steps[-1]}")
    raise CheckpointError(f"{path} is not an orbax checkpoint: no {METADATA_FILE} in it or in {path / 'params'}")


class OrbaxCheckpoint:
    """Array leaves of an orbax PyTree checkpoint, listed from its metadata and read one at a time.

    `path` is an openpi step folder (`<run>/<step>`), its `params` folder, or any orbax item folder.
    Construction reads only metadata; `read` decodes one leaf (or one slice of it along axis 0).
    Every problem (foreign folder, missing or truncated data) raises `CheckpointError` with one line.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.params_dir = find_params_dir(path)
        self.step_dir = self.params_dir.parent if self.params_dir.name == "params" else self.params_dir
        metadata = _load_metadata(self.params_dir)
        self._use_zarr3 = bool(metadata.get("use_zarr3", False))
        self._context = ts.Context()
        self._kvstore = self._kvstore_spec()
        self._kvstore_handle: ts.KvStore | None = None
        tree_keys = _array_leaf_keys(metadata, self.params_dir)
        self.leaves: dict[str, LeafInfo] = {}
        for keys in tree_keys:
            info = self._open_info(keys, _leaf_path(keys, tree_keys))
            self.leaves[info.path] = info
        if bool(metadata.get("store_array_data_equal_to_fill_value", False)):
            self._check_chunks_present()

    # -- listing -------------------------------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.leaves)

    def __iter__(self) -> Iterator[str]:
        return iter(self.leaves)

    def __contains__(self, path: object) -> bool:
        return isinstance(path, str) and _normalize(path) in self.leaves

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """`{leaf path: shape}` for every array leaf."""
        return {path: info.shape for path, info in self.leaves.items()}

    @property
    def nbytes(self) -> int:
        """Bytes of all leaves in their stored dtypes."""
        return sum(info.nbytes for info in self.leaves.values())

    def info(self, path: str) -> LeafInfo:
        """Metadata of one leaf; `path` may carry the `/value` suffix."""
        try:
            return self.leaves[_normalize(path)]
        except KeyError:
            raise CheckpointError(f"checkpoint {self.params_dir} has no leaf {path!r}") from None

    # -- reading -------------------------------------------------------------------------------------------------------

    def read(self, path: str, layer: int | slice | None = None) -> np.ndarray:
        """The array of one leaf in its stored dtype (bfloat16 leaves come back as `ml_dtypes.bfloat16`).

        With `layer` (an index or a slice along axis 0, the stacked-layer axis in openpi), only `array[layer]` is
        read; that decodes only the chunks holding it. A whole leaf is decompressed straight into the result when
        possible (see `iter_rows`), so reading it takes little more memory than the array itself.
        """
        info = self.info(path)
        if layer is None and info.shape:
            streamed = self._read_streaming(info)
            if streamed is not None:
                return streamed
        store = self._open(info.key)
        if layer is not None:
            rows = range(info.shape[0]) if info.shape else range(0)
            if isinstance(layer, int) and layer not in rows or isinstance(layer, slice) and not rows[layer]:
                raise IndexError(f"layer {layer} out of range for leaf {info.path} of shape {info.shape}")
            store = store[layer]
        try:
            return np.asarray(store.read().result())
        except ValueError as error:  # tensorstore reports unreadable data as ValueError
            raise CheckpointError(f"cannot read leaf {info.path} from {self.params_dir}: {first_line(error)}") from None

    def iter_rows(self, path: str, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """Yield `array[i]` for `start <= i < stop` along axis 0 (openpi's stacked-layer axis), in order.

        orbax stores an array saved from one device as a single zstd-compressed chunk; decoding it whole takes
        twice its size in memory (4.8 GB for π0's largest leaf). When the array is chunked along axis 0 only and
        compressed with zstd (what orbax writes), each chunk is decompressed as a stream instead, so only about one
        row is held at a time, where `streaming_reason` finds nothing against it (`zstandard` installed, a tensorstore
        that reads byte ranges). Otherwise the chunks are decoded by tensorstore.
        """
        info = self.info(path)
        stop = info.shape[0] if stop is None else stop
        if not info.shape or not 0 <= start < stop <= info.shape[0]:
            raise IndexError(f"rows [{start}, {stop}) out of range for leaf {info.path} of shape {info.shape}")
        rows_per_chunk, row_bytes = info.chunks[0], math.prod(info.shape[1:]) * info.dtype.itemsize
        for chunk in range(start // rows_per_chunk, (stop - 1) // rows_per_chunk + 1):
            first, last = max(start, chunk * rows_per_chunk), min(stop, (chunk + 1) * rows_per_chunk)
            source = self._chunk_source(info, chunk)
            if source is None:
                yield from self.read(info.path, slice(first, last))
                continue
            with self._decompressing(info, source) as reader:
                reader.seek((first - chunk * rows_per_chunk) * row_bytes)  # a forward seek decompresses and drops
                for _ in range(first, last):
                    row = np.empty(row_bytes, np.uint8)
                    _fill(reader, memoryview(row), info.path)
                    yield row.view(info.dtype).reshape(info.shape[1:])

    # -- internals -----------------------------------------------------------------------------------------------------

    def _read_streaming(self, info: LeafInfo) -> np.ndarray | None:
        """The whole leaf, each chunk decompressed straight into the result; None when not streamable."""
        sources = [self._chunk_source(info, chunk) for chunk in range(math.ceil(info.shape[0] / info.chunks[0]))]
        if any(source is None for source in sources):
            return None
        array = np.empty(info.shape, info.dtype)
        flat = memoryview(array.reshape(-1).view(np.uint8))
        chunk_bytes = math.prod(info.chunks) * info.dtype.itemsize
        for chunk, source in enumerate(sources):
            with self._decompressing(info, source) as reader:  # the last chunk may be padded: read what fits
                _fill(reader, flat[chunk * chunk_bytes : (chunk + 1) * chunk_bytes], info.path)
        return array

    def _chunk_source(self, info: LeafInfo, chunk: int) -> _KvStoreValueReader | None:
        """The stored bytes of chunk `chunk` along axis 0, when it can be decompressed as a zstd stream: zarr v2,
        zstd without filters, C order, little-endian, chunked along axis 0 only, chunk present (and nothing in
        `streaming_reason`)."""
        if streaming_reason() is not None or not info.shape or info.chunks[1:] != info.shape[1:] or info.dtype.byteorder not in ("<", "=", "|"):
            return None
        try:
            zarray = self._zarr_metadata(info.key)
            if zarray is None or (zarray.get("compressor") or {}).get("id") != "zstd" or zarray.get("filters") or zarray.get("order") != "C":
                return None
            separator = zarray.get("dimension_separator", ".")
            key = f"{info.key}/" + separator.join([str(chunk)] + ["0"] * (len(info.shape) - 1))
            source = _KvStoreValueReader(self._kvstore_store(), key)
            return source if source.exists() else None  # an absent chunk means "fill value": leave it to tensorstore
        except ValueError as error:
            raise CheckpointError(f"cannot read leaf {info.path} from {self.params_dir}: {first_line(error)}") from None

    @contextmanager
    def _decompressing(self, info: LeafInfo, source: _KvStoreValueReader) -> Iterator[Any]:
        """A zstd stream reader over `source`; read errors become one-line `CheckpointError`s."""
        try:
            with zstandard.ZstdDecompressor().stream_reader(source, read_size=_STREAM_READ_BYTES, closefd=False) as reader:
                yield reader
        except (ValueError, zstandard.ZstdError) as error:
            if isinstance(error, CheckpointError):
                raise
            raise CheckpointError(f"cannot read leaf {info.path} from {self.params_dir}: {first_line(error)}") from None

    def _zarr_metadata(self, key: str) -> dict | None:
        if self._use_zarr3:
            return None
        result = self._kvstore_store().read(f"{key}/.zarray").result()
        return json.loads(result.value) if result.state == "value" else None

    def _kvstore_store(self) -> ts.KvStore:
        if self._kvstore_handle is None:
            self._kvstore_handle = ts.KvStore.open(self._kvstore, context=self._context).result()
        return self._kvstore_handle

    def _kvstore_spec(self) -> dict:
        base = {"driver": "file", "path": str(self.params_dir.resolve()) + "/"}
        if (self.params_dir / "manifest.ocdbt").is_file():
            return {"driver": "ocdbt", "base": base}
        return base  # orbax without OCDBT: one zarr folder per array

    def _spec(self, key: str) -> dict:
        return {"driver": "zarr3" if self._use_zarr3 else "zarr", "kvstore": {**self._kvstore, "path": key + "/"}}

    def _open(self, key: str) -> ts.TensorStore:
        try:
            return ts.open(self._spec(key), open=True, read=True, context=self._context).result()
        except ValueError as error:
            raise CheckpointError(f"cannot open array {key!r} in {self.params_dir}: {first_line(error)}") from None

    def _open_info(self, keys: tuple[str, ...], path: str) -> LeafInfo:
        store = self._open(".".join(keys))
        chunks = store.chunk_layout.read_chunk.shape
        return LeafInfo(
            path=path,
            key=".".join(keys),
            shape=tuple(int(n) for n in store.shape),
            dtype=np.dtype(store.dtype.numpy_dtype),
            chunks=tuple(int(n) for n in chunks) if chunks is not None else tuple(int(n) for n in store.shape),
        )

    def _check_chunks_present(self) -> None:
        """orbax wrote every chunk (`store_array_data_equal_to_fill_value`): a missing one means lost data."""
        try:
            listed = self._kvstore_store().list().result()
        except ValueError as error:
            raise CheckpointError(f"cannot list the data of {self.params_dir}: {first_line(error)}") from None
        counts: dict[str, int] = {}
        for raw in listed:  # "<array key>/<chunk key>"; array keys hold no "/"
            key, _, chunk = raw.decode("utf-8", "replace").partition("/")
            if chunk and not chunk.startswith(".") and chunk != "zarr.json":
                counts[key] = counts.get(key, 0) + 1
        for info in self.leaves.values():
            expected = math.prod(math.ceil(n / c) for n, c in zip(info.shape, info.chunks)) if info.shape else 1
            if counts.get(info.key, 0) < expected:
                raise CheckpointError(
                    f"checkpoint {self.params_dir} is incomplete: leaf {info.path} has {counts.get(info.key, 0)} "
                    f"of {expected} data chunks"
                )


def _fill(reader: Any, view: memoryview, path: str) -> None:
    """Read exactly `len(view)` bytes from a stream reader into `view`."""
    filled = 0
    while filled < len(view):
        count = reader.readinto(view[filled:])
        if count == 0:
            raise CheckpointError(f"cannot read leaf {path}: its data ends early (truncated)")
        filled += count


class _KvStoreValueReader:
    """A read-only file over one key-value store entry, fetched in byte ranges (the source of a zstd stream)."""

    def __init__(self, store: ts.KvStore, key: str) -> None:
        self.store, self.key = store, key
        self._position, self._at_end = 0, False

    def exists(self) -> bool:
        return self.store.read(self.key, byte_range=slice(0, 0)).result().state == "value"

    def read(self, size: int = -1) -> bytes:
        if self._at_end or size == 0:
            return b""
        end = None if size < 0 else self._position + size
        try:
            value = self.store.read(self.key, byte_range=slice(self._position, end)).result().value
        except ValueError:  # the range runs past the end of the value: take what is left
            value = self.store.read(self.key, byte_range=slice(self._position, None)).result().value
            self._at_end = True
        self._position += len(value)
        self._at_end = self._at_end or not value or end is None
        return value


def _normalize(path: str) -> str:
    return strip_value_suffix(path.strip("/"))


def _load_metadata(params_dir: Path) -> dict:
    file = params_dir / METADATA_FILE
    try:
        metadata = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:  # (RecursionError: absurd nesting)
        raise CheckpointError(f"{file} is not a readable orbax metadata file: {first_line(error) or type(error).__name__}") from None
    if not isinstance(metadata, dict) or not isinstance(metadata.get("tree_metadata"), dict):
        raise CheckpointError(f"{file} has no 'tree_metadata': not an orbax PyTree checkpoint")
    return metadata


def _array_leaf_keys(metadata: dict, params_dir: Path) -> list[tuple[str, ...]]:
    """Tree keys of every array leaf, in metadata order."""
    leaves = []
    for flat_key, entry in metadata["tree_metadata"].items():
        value = entry.get("value_metadata", {}) if isinstance(entry, dict) else {}
        if not isinstance(value, dict) or value.get("value_type") not in _ARRAY_VALUE_TYPES or value.get("skip_deserialize", False):
            continue
        leaves.append(_leaf_keys(flat_key, entry.get("key_metadata"), params_dir / METADATA_FILE))
    if not leaves:
        raise CheckpointError(f"{params_dir / METADATA_FILE} lists no array leaves")
    return leaves


def _leaf_keys(flat_key: str, key_metadata: Any, file: Path) -> tuple[str, ...]:
    """The tree keys of one leaf: from its `key_metadata` (a list of `{"key": ...}`), or in older metadata from the
    flat key, the tuple's repr. Anything else (a repr that is no tuple literal, absurd nesting, wrong types) is a
    `CheckpointError` naming the file and the leaf."""
    try:
        if key_metadata:
            if not isinstance(key_metadata, list) or not all(isinstance(k, dict) and "key" in k for k in key_metadata):
                raise TypeError(f"key_metadata is not a list of {{'key': ...}} entries: {str(key_metadata)[:80]}")
            return tuple(str(k["key"]) for k in key_metadata)
        if not isinstance(flat_key, str) or len(flat_key) > MAX_FLAT_KEY_CHARS:
            raise ValueError(f"a flat key of {len(str(flat_key))} characters")
        keys = ast.literal_eval(flat_key)
        if not isinstance(keys, tuple):
            raise TypeError(f"the flat key is a {type(keys).__name__}, not a tuple of keys")
        return tuple(str(k) for k in keys)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError) as error:
        raise CheckpointError(f"{file}: the leaf {str(flat_key)[:60]!r} has no readable keys "
                              f"({first_line(error) or type(error).__name__}): not an orbax PyTree checkpoint") from None


def _leaf_path(keys: tuple[str, ...], all_keys: list[tuple[str, ...]]) -> str:
    """openpi name of a leaf: drop the item key shared by every leaf (`params`) and the nnx `value` suffix."""
    if all(len(k) > 1 and k[0] == all_keys[0][0] for k in all_keys):
        keys = keys[1:]
    if keys and keys[-1] == VALUE_SUFFIX and len(keys) > 1:
        keys = keys[:-1]
    return "/".join(keys)


# -- writing (tests and benchmarks: openpi-layout checkpoints without JAX) --------------------------------------------

ChunkFiller = Callable[[tuple[slice, ...]], np.ndarray]


def write_orbax_checkpoint(
    params_dir: str | os.PathLike[str],
    leaves: Mapping[str, np.ndarray | tuple[tuple[int, ...], np.dtype, ChunkFiller]],
    *,
    item_key: str = "params",
    value_suffix: bool = True,
    chunk_bytes: int | None = None,
) -> None:
    """Write `leaves` (openpi paths -> arrays) as an orbax OCDBT PyTree checkpoint the way openpi saves params.

    The layout matches what orbax 0.11 writes: `_METADATA` with one `tree_metadata` entry per leaf keyed by
    `(item_key, *path.split("/"), "value")` (without `"value"` when `value_suffix` is False), and zarr v2 arrays
    (zstd level 1) named by those keys joined with "." in an OCDBT store at the folder's root.

    A leaf is either an array, or `(shape, dtype, fill)` where `fill(index)` returns the data at `index` (a tuple
    of slices covering some rows of axis 0), so huge checkpoints can be generated a block of rows at a time. With
    `chunk_bytes`, arrays are chunked along axis 0 (as many whole layers per chunk as fit); otherwise each array is
    a single chunk, as orbax writes an array saved from one device. Each array is written in one transaction, so a
    chunk is encoded once however many row blocks fill it.
    """
    params_dir = Path(params_dir)
    params_dir.mkdir(parents=True, exist_ok=True)
    kvstore = {"driver": "ocdbt", "base": {"driver": "file", "path": str(params_dir.resolve()) + "/"}}
    context = ts.Context()
    tree_metadata = {}
    for path, leaf in leaves.items():
        keys = (item_key, *path.split("/"), *((VALUE_SUFFIX,) if value_suffix else ()))
        shape, dtype, fill = _as_generator(leaf)
        chunks = _chunk_shape(shape, dtype, chunk_bytes)
        store = ts.open(
            {
                "driver": "zarr",
                "kvstore": {**kvstore, "path": ".".join(keys) + "/"},
                "metadata": {
                    "shape": list(shape),
                    "chunks": list(chunks),
                    "dtype": _zarr_dtype(dtype),
                    "compressor": {"id": "zstd", "level": 1},
                    "fill_value": None,
                    "order": "C",
                    "dimension_separator": ".",
                },
            },
            create=True,
            context=context,
        ).result()
        with ts.Transaction() as transaction:
            target = store.with_transaction(transaction)
            for index in _row_blocks(shape, _block_rows(shape, dtype, chunks)):
                target[index].write(fill(index)).result()
        tree_metadata[str(keys)] = {
            "key_metadata": [{"key": k, "key_type": 2} for k in keys],
            "value_metadata": {"value_type": "jax.Array", "skip_deserialize": False, "write_shape": list(shape)},
        }
    metadata = {
        "tree_metadata": tree_metadata,
        "use_zarr3": False,
        "store_array_data_equal_to_fill_value": True,
        "custom_metadata": None,
    }
    (params_dir / METADATA_FILE).write_text(json.dumps(metadata))


def _as_generator(leaf: np.ndarray | tuple[tuple[int, ...], np.dtype, ChunkFiller]) -> tuple[tuple[int, ...], np.dtype, ChunkFiller]:
    if isinstance(leaf, tuple):
        shape, dtype, fill = leaf
        return tuple(shape), np.dtype(dtype), fill
    array = np.asarray(leaf)
    return array.shape, array.dtype, lambda index: array[index]


def _zarr_dtype(dtype: np.dtype) -> str:
    return "bfloat16" if dtype.name == "bfloat16" else dtype.str


def _chunk_shape(shape: tuple[int, ...], dtype: np.dtype, chunk_bytes: int | None) -> tuple[int, ...]:
    if not shape or chunk_bytes is None:
        return shape
    row_bytes = math.prod(shape[1:]) * dtype.itemsize
    return (max(1, min(shape[0], chunk_bytes // max(row_bytes, 1))), *shape[1:])


def _block_rows(shape: tuple[int, ...], dtype: np.dtype, chunks: tuple[int, ...]) -> int:
    """Rows of axis 0 generated at once: a chunk's worth when chunked, else blocks of about 64 MiB."""
    if not shape:
        return 1
    if chunks[0] < shape[0]:
        return chunks[0]
    return max(1, min(shape[0], (64 << 20) // max(math.prod(shape[1:]) * dtype.itemsize, 1)))


def _row_blocks(shape: tuple[int, ...], rows: int) -> Iterator[tuple[slice, ...]]:
    if not shape:
        yield ()
        return
    for start in range(0, shape[0], rows):
        yield (slice(start, min(start + rows, shape[0])), *(slice(0, n) for n in shape[1:]))
