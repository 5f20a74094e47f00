"""The orbax checkpoint reader against checkpoints written by openpi's own JAX code (tests/fixtures/openpi)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import ml_dtypes
import numpy as np
import pytest
import tensorstore as ts

from pi0_torch.conversion import orbax_reader
from pi0_torch.conversion.orbax_reader import CheckpointError, OrbaxCheckpoint, find_params_dir, write_orbax_checkpoint

from conftest import FIXTURES, VARIANTS


def params_flat(variant: str) -> dict[str, np.ndarray]:
    return dict(np.load(FIXTURES / variant / "params_flat.npz"))


def writable_copy(source: Path, target: Path) -> Path:
    """Copy a (read-only) fixture checkpoint so a test can damage it."""
    shutil.copytree(source, target, copy_function=shutil.copyfile)
    for folder, _, _ in os.walk(target):
        os.chmod(folder, 0o755)
    return target


def store_keys(params_dir: Path) -> list[bytes]:
    kvstore = {"driver": "ocdbt", "base": {"driver": "file", "path": str(params_dir.resolve()) + "/"}}
    return sorted(ts.KvStore.open(kvstore).result().list().result())


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(("where", "streaming"), [("step", True), ("params", False), ("params", "old tensorstore")],
                         ids=["step-zstd-stream", "params-tensorstore", "params-old-tensorstore"])
def test_every_leaf_equals_params_flat(variant: str, where: str, streaming: bool | str, monkeypatch: pytest.MonkeyPatch) -> None:
    if streaming is True and orbax_reader.streaming_reason() is not None:
        pytest.skip(f"{orbax_reader.streaming_reason()}: chunks are decoded by tensorstore")
    if streaming is False:
        monkeypatch.setattr(orbax_reader, "zstandard", None)
    if streaming == "old tensorstore":  # (one without byte ranges: the chunks are decoded by tensorstore, not streamed)
        monkeypatch.setattr(orbax_reader, "_reads_byte_ranges", lambda: False)
        assert "0.1.81" in orbax_reader.streaming_reason()
    step = FIXTURES / variant / "ckpt" / "0"
    checkpoint = OrbaxCheckpoint(step if where == "step" else step / "params")
    expected = params_flat(variant)
    assert checkpoint.params_dir == step / "params" and checkpoint.step_dir == step
    assert set(checkpoint) == set(expected)  # "params/" item key and "/value" suffix stripped
    for path, array in expected.items():
        info = checkpoint.info(path)
        assert (info.shape, info.dtype) == (array.shape, array.dtype), path
        assert info.key == "params." + path.replace("/", ".") + ".value"  # openpi training layout: nnx ".value"
        read = checkpoint.read(path)
        assert read.dtype == array.dtype and np.array_equal(read, array), path
        assert np.array_equal(checkpoint.read(path + "/value"), array), path
        if array.ndim > 1:
            assert np.array_equal(checkpoint.read(path, layer=array.shape[0] - 1), array[-1]), path
    assert checkpoint.nbytes == sum(a.nbytes for a in expected.values())


@pytest.mark.parametrize("variant", VARIANTS)
def test_writer_reproduces_orbax_layout(variant: str, tmp_path: Path) -> None:
    """The test/benchmark writer writes byte-for-byte the metadata and keys orbax wrote for the same tree."""
    original = FIXTURES / variant / "ckpt" / "0" / "params"
    write_orbax_checkpoint(tmp_path / "params", params_flat(variant))
    assert json.loads((tmp_path / "params" / "_METADATA").read_text()) == json.loads((original / "_METADATA").read_text())
    assert store_keys(tmp_path / "params") == store_keys(original)
    ours, theirs = OrbaxCheckpoint(tmp_path), OrbaxCheckpoint(original)
    assert ours.leaves == theirs.leaves  # same keys, shapes, dtypes and chunks


def test_released_layout_without_value_suffix(tmp_path: Path) -> None:
    """Released checkpoints store a pure dict (no "/value") and may be bfloat16 and chunked per layer."""
    arrays = {k: v.astype(ml_dtypes.bfloat16) for k, v in params_flat("pi0_small").items()}
    write_orbax_checkpoint(tmp_path / "params", arrays, value_suffix=False, chunk_bytes=20_000)
    checkpoint = OrbaxCheckpoint(tmp_path / "params")
    assert set(checkpoint) == set(arrays)
    gating = checkpoint.info("PaliGemma/llm/layers/mlp/gating_einsum")
    assert gating.key == "params.PaliGemma.llm.layers.mlp.gating_einsum" and gating.chunks[0] == 1
    for path, array in arrays.items():
        read = checkpoint.read(path)
        assert read.dtype == ml_dtypes.bfloat16 and np.array_equal(read.view(np.uint16), array.view(np.uint16)), path
    assert np.array_equal(checkpoint.read("PaliGemma/llm/layers/mlp/gating_einsum/value", 2).view(np.uint16), arrays["PaliGemma/llm/layers/mlp/gating_einsum"][2].view(np.uint16))


@pytest.mark.parametrize("streaming", [True, False], ids=["zstd-stream", "tensorstore"])
@pytest.mark.parametrize("chunk_bytes", [None, 70_000], ids=["one-chunk", "two-layer-chunks"])
def test_iter_rows(chunk_bytes: int | None, streaming: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    if streaming and orbax_reader.streaming_reason() is not None:
        pytest.skip(f"{orbax_reader.streaming_reason()}: chunks are decoded by tensorstore")
    if not streaming:
        monkeypatch.setattr(orbax_reader, "zstandard", None)
    arrays = {k: v.astype(ml_dtypes.bfloat16) for k, v in params_flat("pi05_small").items()}
    write_orbax_checkpoint(tmp_path / "params", arrays, chunk_bytes=chunk_bytes)
    checkpoint = OrbaxCheckpoint(tmp_path / "params")
    if streaming:  # whole leaves and row ranges never go through tensorstore's zarr decoding
        monkeypatch.setattr(checkpoint, "_open", lambda key: pytest.fail(f"{key} decoded by tensorstore"))
    for path, array in arrays.items():
        assert np.array_equal(checkpoint.read(path).view(np.uint16), array.view(np.uint16)), path
        if array.shape[0] < 3:
            continue
        rows = list(checkpoint.iter_rows(path, 1))
        assert len(rows) == array.shape[0] - 1, path
        assert all(np.array_equal(row.view(np.uint16), array[1 + i].view(np.uint16)) for i, row in enumerate(rows)), path
    with pytest.raises(IndexError, match="out of range"):
        next(checkpoint.iter_rows("PaliGemma/llm/layers/mlp/linear", 2, 5))


def test_iter_rows_streams_a_truncated_chunk_into_one_error(tmp_path: Path) -> None:
    step = writable_copy(FIXTURES / "pi0_small" / "ckpt" / "0", tmp_path / "0")
    data = max((step / "params").rglob("d/*"), key=lambda p: p.stat().st_size)
    with open(data, "r+b") as handle:
        handle.truncate(data.stat().st_size // 2)
    checkpoint = OrbaxCheckpoint(step)
    failures = []
    for path, info in checkpoint.leaves.items():
        if len(info.shape) > 1 and info.shape[0] > 1:
            try:
                list(checkpoint.iter_rows(path))
            except CheckpointError as error:
                failures.append(str(error))
    assert failures and all(message.startswith("cannot read leaf") and "\n" not in message for message in failures)


def test_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="does not exist"):
        OrbaxCheckpoint(tmp_path / "absent")
    (tmp_path / "file.txt").write_text("hello")
    with pytest.raises(CheckpointError, match="is a file"):
        OrbaxCheckpoint(tmp_path / "file.txt")
    with pytest.raises(CheckpointError, match="not an orbax checkpoint: no _METADATA"):
        OrbaxCheckpoint(tmp_path)
    run = tmp_path / "run"
    writable_copy(FIXTURES / "pi0_small" / "ckpt" / "0", run / "1000")
    with pytest.raises(CheckpointError, match=r"training run with steps 1000; pass one step folder"):
        find_params_dir(run)
    (run / "1000" / "params" / "_METADATA").write_text("{not json")
    with pytest.raises(CheckpointError, match="not a readable orbax metadata file"):
        OrbaxCheckpoint(run / "1000")
    (run / "1000" / "params" / "_METADATA").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(CheckpointError, match="no 'tree_metadata'"):
        OrbaxCheckpoint(run / "1000")


def test_truncated_data_file(tmp_path: Path) -> None:
    step = writable_copy(FIXTURES / "pi0_small" / "ckpt" / "0", tmp_path / "0")
    data = max((step / "params").rglob("d/*"), key=lambda p: p.stat().st_size)
    with open(data, "r+b") as handle:
        handle.truncate(data.stat().st_size // 2)
    checkpoint = OrbaxCheckpoint(step)  # metadata is intact
    failures = []
    for path in checkpoint:
        try:
            checkpoint.read(path)
        except CheckpointError as error:
            failures.append(str(error))
    assert failures and all(message.startswith("cannot read leaf") and "\n" not in message for message in failures)


def test_missing_chunk_and_missing_array(tmp_path: Path) -> None:
    step = writable_copy(FIXTURES / "pi0_small" / "ckpt" / "0", tmp_path / "0")
    kvstore = ts.KvStore.open({"driver": "ocdbt", "base": {"driver": "file", "path": str(step / "params") + "/"}}).result()
    kvstore.delete_range(ts.KvStore.KeyRange("params.PaliGemma.img.head.bias.value/0", "params.PaliGemma.img.head.bias.value/1")).result()
    with pytest.raises(CheckpointError, match=r"incomplete: leaf PaliGemma/img/head/bias has 0 of 1 data chunks"):
        OrbaxCheckpoint(step)
    kvstore.delete_range(ts.KvStore.KeyRange("params.PaliGemma.img.head.bias.value/", "params.PaliGemma.img.head.bias.value0")).result()
    with pytest.raises(CheckpointError, match=r"cannot open array 'params\.PaliGemma\.img\.head\.bias\.value'"):
        OrbaxCheckpoint(step)


def test_unknown_leaf_and_layer_range() -> None:
    checkpoint = OrbaxCheckpoint(FIXTURES / "pi0_small" / "ckpt" / "0")
    with pytest.raises(CheckpointError, match="has no leaf 'PaliGemma/nope'"):
        checkpoint.read("PaliGemma/nope")
    with pytest.raises(IndexError, match="layer 3 out of range"):
        checkpoint.read("PaliGemma/llm/layers/mlp/linear", layer=3)


@pytest.mark.parametrize("corrupt, message", [
    (lambda meta, key: meta["tree_metadata"].update({"not a literal": {**meta["tree_metadata"].pop(key), "key_metadata": None}}),
     "the leaf 'not a literal' has no readable keys"),
    (lambda meta, key: meta["tree_metadata"].update({"(" * 5000 + ")" * 5000: {**meta["tree_metadata"].pop(key), "key_metadata": None}}),
     "has no readable keys \\(a flat key of 10000 characters\\)"),
    (lambda meta, key: meta["tree_metadata"][key].update(key_metadata=[1, 2]), "key_metadata is not a list"),
    (lambda meta, key: meta["tree_metadata"].update({"['params', 'a']": {**meta["tree_metadata"].pop(key), "key_metadata": None}}),
     "the flat key is a list, not a tuple of keys"),
])
def test_malformed_metadata_is_one_line_naming_the_file(tmp_path: Path, corrupt, message: str) -> None:
    """Issue 38.15: malformed `_METADATA` files (a literal that is not one, 5,000 nested parentheses, wrong types) gave
    tracebacks; each is a `CheckpointError` naming the file and the leaf."""
    write_orbax_checkpoint(tmp_path / "params", {"a/b": np.zeros((2, 2), np.float32)})
    file = tmp_path / "params" / "_METADATA"
    metadata = json.loads(file.read_text())
    corrupt(metadata, next(iter(metadata["tree_metadata"])))
    file.write_text(json.dumps(metadata))
    with pytest.raises(CheckpointError, match=f"_METADATA: .*{message}") as refused:
        OrbaxCheckpoint(tmp_path / "params")
    assert "\n" not in str(refused.value)
    file.write_text("[" * 100_000 + "]" * 100_000)  # (nesting json cannot parse)
    with pytest.raises(CheckpointError, match="not a readable orbax metadata file"):
        OrbaxCheckpoint(tmp_path / "params")
