"""An exported policy's folder, as `pi0-torch export` writes it and `ExportedPolicy` reads it (no torch here).

```
export/
  deploy.json            what the graph takes and returns, how to build its inputs (below), versions and hashes
  model.onnx             the graph (ONNX), with model.onnx.data beside it when over 2 GB; or model.pt2 (AOTInductor)
  reference.npz          one input set and the graph's output for it, to check a runtime against
  tokenizer.model        the prompt's SentencePiece model
  processor_config.json  the processor's settings (cameras, prompt format, normalization, delta actions)
  norm_stats.json        the state / action statistics (openpi's layout)
  policy_settings.json   the recommended settings (noise scale, actions to execute per chunk), when the model had them
```

The graph is `generate_actions` for a fixed batch size, camera set, prompt length and step count, with the state
normalization and the action unnormalization folded in. Its inputs, in order (`deploy.json`'s `inputs`):

| name | dtype | shape | what |
|---|---|---|---|
| `images` | uint8 | `[B, cameras, H, W, 3]` | RGB frames resized with padding to the model's size (`resize`); zeros where absent |
| `image_masks` | bool | `[B, cameras]` | which cameras the sample shows |
| `input_ids` | int64 | `[B, L]` | the prompt's token ids, padded with `pad_id` |
| `attention_mask` | bool | `[B, L]` | which of them are the prompt's |
| `state` | float32 | `[B, state_dim]` | the robot's state in the checkpoint's units (after `value_conversion`, if any) |
| `noise` | float32 | `[B, horizon, action_dim]` | where the flow starts: standard normal times `noise_scale` |

Output `actions` float32 `[B, horizon, robot action dims]`: robot units (before `value_conversion`'s way back, if any).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

DEPLOY_FILE = "deploy.json"
REFERENCE_FILE = "reference.npz"
FORMAT_NAME = "pi0-torch-export"
FORMAT_VERSION = 1
FORMATS = {"onnx": "model.onnx", "pt2": "model.pt2"}
INPUT_NAMES = ("images", "image_masks", "input_ids", "attention_mask", "state", "noise")
OUTPUT_NAMES = ("actions",)
MIN_OPSET = 18  # RMSNorm's and RoPE's ops as exported (public ports patch them by hand below 18)
ONNX_PROTOBUF_LIMIT = 2 * 1024**3  # above it an ONNX model keeps its weights as external data
# An artifact's actions against the model's own on the same inputs (at export) and against `reference.npz` (when a
# runtime loads it), max |difference| / max |action|, by the weights' dtype: the engine's bounds
# (`pi0_torch.inference.checks.VERIFY_TOLERANCE`); an exporter's rewrite reorders float sums, nothing more
ACTION_TOLERANCE = {"float32": 1e-4, "bfloat16": 3e-2, "float16": 3e-2}


def action_deviation(got: np.ndarray, want: np.ndarray) -> float:
    """max |got - want| / max |want| (inf where `got` holds NaN or inf): what `ACTION_TOLERANCE` bounds."""
    if not np.isfinite(got).all():
        return float("inf")
    return float(np.abs(got - want).max() / max(float(np.abs(want).max()), 1e-12))


class ExportFolderError(ValueError):
    """A folder that is not a usable export: one line naming what is wrong and what to do."""


def file_sha256(path: Path, chunk: int = 16 * 1024**2) -> str:
    """The SHA-256 of a file, read in chunks (weights of several GB)."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while block := stream.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def read_deploy(directory: str | Path) -> dict[str, Any]:
    """`deploy.json` of an export folder, checked for what a runtime needs (every file it names present); raises
    [`ExportFolderError`] naming the problem."""
    directory = Path(directory)
    path = directory / DEPLOY_FILE
    if not directory.is_dir():
        raise ExportFolderError(f"no export folder at {directory} (pi0-torch export MODEL_DIR --output-dir DIR writes one)")
    if not path.is_file():
        raise ExportFolderError(f"{directory} holds no {DEPLOY_FILE}, so it is not an exported policy (pi0-torch export "
                                "MODEL_DIR --output-dir DIR writes one; a model folder loads with PI0Policy instead)")
    try:
        spec = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as error:
        raise ExportFolderError(f"{path}: not a readable JSON file ({str(error)[:200]})") from None
    if not isinstance(spec, dict) or spec.get("format") != FORMAT_NAME:
        raise ExportFolderError(f"{path}: not a pi0-torch export description (its 'format' is not {FORMAT_NAME!r})")
    if spec.get("format_version") != FORMAT_VERSION:
        raise ExportFolderError(f"{path}: export format version {spec.get('format_version')!r}; this pi0-torch reads "
                                f"version {FORMAT_VERSION} (export the model again with this version)")
    missing = [key for key in ("artifact", "inputs", "outputs", "model", "processor") if not isinstance(spec.get(key), (Mapping, list))]
    if missing:
        raise ExportFolderError(f"{path}: lacks {missing}; export the model again")
    artifact = spec["artifact"]
    if artifact.get("format") not in FORMATS:
        raise ExportFolderError(f"{path}: artifact format {artifact.get('format')!r}; expected one of {sorted(FORMATS)}")
    if [entry.get("name") for entry in spec["inputs"]] != list(INPUT_NAMES):
        raise ExportFolderError(f"{path}: inputs {[entry.get('name') for entry in spec['inputs']]}; expected {list(INPUT_NAMES)}")
    for name in (artifact.get("file"), *artifact.get("external_data", ()), "tokenizer.model", "processor_config.json"):
        if not isinstance(name, str) or Path(name).name != name or not (directory / name).is_file():
            raise ExportFolderError(f"{directory}: {name!r} is missing (named in {DEPLOY_FILE}); the folder is "
                                    "incomplete: copy or export it again")
    return spec


def check_artifact_hash(directory: Path, spec: Mapping[str, Any]) -> None:
    """The graph file's SHA-256 against the one `deploy.json` recorded at export (a truncated or swapped file)."""
    artifact = spec["artifact"]
    for name in (artifact["file"], *artifact.get("external_data", ())):
        recorded = artifact.get("sha256", {}).get(name)
        actual = file_sha256(directory / name)
        if recorded != actual:
            raise ExportFolderError(f"{directory / name}: its SHA-256 {actual[:16]}... differs from the "
                                    f"{str(recorded)[:16]}... recorded in {DEPLOY_FILE} at export: the file was changed "
                                    "or damaged (copy or export the folder again)")
