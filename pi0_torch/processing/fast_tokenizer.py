"""The FAST action tokenizer (Pertsch et al. 2025, "FAST: Efficient Action Tokenization for VLA Models").

An action chunk `[H, A]` becomes a few integer tokens:

1. DCT-II along time, orthonormal (`scipy.fft.dct(..., norm="ortho")`, here a float64 matrix product), per action
   dimension;
2. scale by `scale` and round to integers;
3. flatten frequency-major (all dims' lowest frequency first), shift by `-min_token` (negatives clip to 0) and write
   each coefficient as one character `chr(c)`;
4. byte-level BPE over that string (the `tokenizer.json` of a Hugging Face `tokenizers` model).

Decoding reverses it: BPE ids -> characters -> `ord(c) + min_token` -> `[H, A]` coefficients -> `/ scale` ->
inverse DCT. A sequence that does not decode to exactly `H * A` coefficients (a model can emit any ids) gives a
chunk of zeros and a logged warning, as openpi does (or, with `decode(mark_undecodable=True)`, a chunk of NaN, which a
policy withholds).

The folder layout is the public `physical-intelligence/fast` one (`processor_config.json` with `scale`,
`vocab_size`, `min_token`, `time_horizon`, `action_dim`; the BPE's `tokenizer.json` and `tokenizer_config.json`),
read without running its remote code, so a copy of the public tokenizer loads here and `save_pretrained` writes
a folder that tooling made for the public one reads.

```python
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> chunks = [np.cumsum(rng.normal(0, 0.1, (10, 3)), axis=0) for _ in range(200)]  # smooth [H=10, A=3] chunks
>>> tokenizer = FASTActionTokenizer.fit(chunks, scale=10, vocab_size=256)
>>> ids = tokenizer(chunks[0])
>>> len(ids), len(ids[0]) < 30  # one sequence, fewer tokens than the chunk's 30 values
(1, True)
>>> decoded = tokenizer.decode(ids, time_horizon=10, action_dim=3)
>>> decoded.shape, bool(np.abs(decoded[0] - chunks[0]).max() < 0.1)  # quantized with step 1 / scale in DCT space
((1, 10, 3), True)

```
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tokenizers import ByteLevelBPETokenizer
from tokenizers.trainers import BpeTrainer
from transformers import PreTrainedTokenizerFast

from pi0_torch.utils.files import atomic_output_dir
from pi0_torch.utils.validation import read_json_file

logger = logging.getLogger(__name__)

PROCESSOR_CONFIG_FILE = "processor_config.json"
BPE_FILE = "tokenizer.json"
PUBLIC_PROCESSOR_CLASS = "UniversalActionProcessor"  # the class name the public folder's config names


class FASTActionTokenizer:
    """Action chunks `[H, A]` <-> FAST token ids (see the module docstring for the algorithm).

    Args:
        bpe: the byte-level BPE over coefficient characters (a `transformers.PreTrainedTokenizerFast`).
        scale: DCT coefficients are multiplied by it before rounding (the quantization step is `1 / scale`).
        vocab_size: the BPE's vocabulary size (FAST ids are `0 .. vocab_size - 1`).
        min_token: the smallest rounded coefficient of the data the BPE was fitted on (characters are shifted by it).
        time_horizon, action_dim: the chunk shape `decode` uses when not given.
    """

    def __init__(
        self,
        bpe: PreTrainedTokenizerFast,
        scale: float = 10,
        vocab_size: int = 1024,
        min_token: int = 0,
        *,
        time_horizon: int | None = None,
        action_dim: int | None = None,
    ) -> None:
        if not scale > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        self.bpe = bpe
        self.scale = scale
        self.vocab_size = int(vocab_size)
        self.min_token = int(min_token)
        self.time_horizon = time_horizon
        self.action_dim = action_dim
        self.unencodable_chunks = 0  # chunks encoded to tokens that do not decode back to them (see __call__)

    # ------------------------------------------------------------------------------------------- files

    @classmethod
    def from_pretrained(cls, folder: str | Path) -> FASTActionTokenizer:
        """Read a FAST tokenizer folder (the public `physical-intelligence/fast` layout or `save_pretrained`'s).

        Only the settings and the BPE are read; no code from the folder runs. Raises `FileNotFoundError` /
        `ValueError` naming what is missing or wrong.
        """
        folder = Path(folder)
        config_path = folder / PROCESSOR_CONFIG_FILE
        if not config_path.is_file() or not (folder / BPE_FILE).is_file():
            raise FileNotFoundError(
                f"{folder} is not a FAST tokenizer folder: expected {PROCESSOR_CONFIG_FILE} and {BPE_FILE} "
                "(the layout of physical-intelligence/fast)"
            )
        settings = read_json_file(config_path)
        if not isinstance(settings, dict):
            raise ValueError(f"{config_path}: expected a JSON object of settings, got a JSON {type(settings).__name__}")
        missing = [key for key in ("scale", "vocab_size", "min_token") if key not in settings]
        if missing:
            raise ValueError(f"{config_path} lacks {missing}; has {sorted(settings)}")
        bpe = PreTrainedTokenizerFast.from_pretrained(str(folder), local_files_only=True)
        return cls(
            bpe,
            scale=settings["scale"],
            vocab_size=settings["vocab_size"],
            min_token=settings["min_token"],
            time_horizon=settings.get("time_horizon"),
            action_dim=settings.get("action_dim"),
        )

    def to_dict(self) -> dict[str, Any]:
        """The settings of `processor_config.json` (the public folder's keys)."""
        return {
            "action_dim": self.action_dim,
            "min_token": self.min_token,
            "processor_class": PUBLIC_PROCESSOR_CLASS,
            "scale": self.scale,
            "time_horizon": self.time_horizon,
            "vocab_size": self.vocab_size,
        }

    def save_pretrained(self, folder: str | Path) -> Path:
        """Write the folder (`processor_config.json` and the BPE's files), whole or not at all; returns it."""
        folder = Path(folder)
        with atomic_output_dir(folder, overwrite=True) as partial:
            self.bpe.save_pretrained(str(partial))
            (partial / PROCESSOR_CONFIG_FILE).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")
        return folder

    # ------------------------------------------------------------------------------------------- encode / decode

    def __call__(self, actions: Any) -> list[list[int]]:
        """FAST ids of one chunk `[H, A]` or a batch `[B, H, A]`: a list (one per chunk) of id lists.

        The DCT is computed in float64 whatever the chunks' dtype. The public tokenizer runs scipy's DCT in the
        chunks' precision; on float32 chunks the two round a coefficient differently only when it lies within
        float32 rounding of a tie (`k + 0.5` after scaling): about 4 coefficients in a million on random chunks,
        none in openpi's fixture."""
        chunks = np.asarray(actions)
        if chunks.dtype.kind not in "fiu":
            raise ValueError(f"actions: expected real numbers, got dtype {chunks.dtype}")
        if chunks.ndim == 2:
            chunks = chunks[None]
        if chunks.ndim != 3 or 0 in chunks.shape:
            raise ValueError(f"actions: expected a chunk [H, A] or a batch [B, H, A], got shape {np.shape(actions)}")
        if not np.all(np.isfinite(chunks)):
            raise ValueError("actions: contains NaN or inf")
        coefficients = np.around(dct(chunks, axis=1) * self.scale)  # [B, H, A]
        ids = []
        for index, chunk in enumerate(coefficients):
            text = _to_characters(chunk.flatten() - self.min_token)
            ids.append(self.bpe(text)["input_ids"])
            if chunk.min() < self.min_token or self.bpe.decode(ids[-1]) != text:
                self._warn_unencodable(index, chunk)
        return ids

    def _warn_unencodable(self, index: int, coefficients: np.ndarray) -> None:
        """Count a chunk whose tokens do not decode back to it (coefficients below `min_token`, or beyond the
        fitted alphabet), and log the first: training on it would teach tokens that decode to zeros or to another
        chunk."""
        self.unencodable_chunks += 1
        if self.unencodable_chunks == 1:
            logger.warning(
                "FAST: chunk %d has scaled DCT coefficients in [%d, %d], outside what this tokenizer encodes (it starts "
                "at min_token %d): its tokens decode to another chunk or to zeros. The actions lie outside the range the "
                "tokenizer was fitted to: refit it (--fast-tokenizer fit) or check the normalization. Further such "
                "chunks are counted in unencodable_chunks, not logged", index, int(coefficients.min()),
                int(coefficients.max()), self.min_token,
            )

    def decode(
        self, ids: Iterable[Sequence[int]], time_horizon: int | None = None, action_dim: int | None = None,
        mark_undecodable: bool = False,
    ) -> np.ndarray:
        """Action chunks `[B, H, A]` (float64) of id sequences; `H`, `A` default to the tokenizer's settings.

        A sequence that does not decode to `H * A` coefficients gives zeros and a logged warning (openpi's FAST
        behaviour: a model may emit an undecodable sequence; the robot then gets a zero chunk, not a crash), or
        with `mark_undecodable` a chunk of NaN, which tells it from a decoded chunk (a policy withholds it).
        """
        horizon = time_horizon if time_horizon is not None else self.time_horizon
        dim = action_dim if action_dim is not None else self.action_dim
        if horizon is None or dim is None:
            raise ValueError("decode needs time_horizon and action_dim (this tokenizer's settings have none)")
        fill, filled = (np.nan, "NaN (undecodable)") if mark_undecodable else (0.0, "zeros")
        chunks = []
        for sequence in ids:
            sequence = [int(i) for i in sequence]
            shown = sequence[:16] + (["..."] if len(sequence) > 16 else [])
            if any(not 0 <= i < self.vocab_size for i in sequence):
                logger.warning("FAST tokens %s are not all in [0, %d): returning a chunk of %s", shown, self.vocab_size,
                               filled)
                coefficients = np.full(horizon * dim, fill)
            else:
                text = self.bpe.decode(sequence)
                coefficients = np.array([ord(c) for c in text], dtype=np.float64) + self.min_token
                if coefficients.size != horizon * dim:
                    logger.warning(
                        "FAST tokens %s decode to %d coefficients, not %d x %d: returning a chunk of %s",
                        shown, coefficients.size, horizon, dim, filled,
                    )
                    coefficients = np.full(horizon * dim, fill)
            chunks.append(idct(coefficients.reshape(horizon, dim) / self.scale, axis=0))
        return np.stack(chunks) if chunks else np.zeros((0, horizon, dim))

    # ------------------------------------------------------------------------------------------- fitting

    @classmethod
    def fit(
        cls,
        chunks: Iterable[Any],
        scale: float = 10,
        vocab_size: int = 1024,
        *,
        time_horizon: int | None = None,
        action_dim: int | None = None,
    ) -> FASTActionTokenizer:
        """Fit a FAST tokenizer to action chunks (each `[H, A]`, normalized as the model will see them).

        The alphabet is every rounded DCT coefficient between the data's smallest and largest; the BPE merges
        frequent runs (pairs seen at least twice) until `vocab_size` tokens. Raises `ValueError` when `vocab_size`
        cannot hold the alphabet (raise it, or lower `scale`). `time_horizon`/`action_dim` default to the chunks'.
        """
        arrays = [np.asarray(chunk, dtype=np.float64) for chunk in chunks]
        if not arrays or any(a.ndim != 2 or a.shape != arrays[0].shape or 0 in a.shape for a in arrays):
            raise ValueError("chunks: expected a non-empty list of action chunks, all of one shape [H, A]")
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise ValueError("chunks: contain NaN or inf")
        rounded = [np.around(dct(a, axis=0).flatten() * scale) for a in arrays]
        low = int(min(r.min() for r in rounded))
        high = int(max(r.max() for r in rounded))
        if high - low > vocab_size:
            raise ValueError(
                f"vocab_size {vocab_size} cannot hold the {high - low + 1} coefficient values of these chunks at scale "
                f"{scale}; raise vocab_size or lower scale"
            )
        if high - low + 100 > vocab_size:
            logger.warning("the coefficient alphabet (%d values) is nearly the vocab size %d", high - low + 1, vocab_size)
        bpe = ByteLevelBPETokenizer()
        trainer = BpeTrainer(
            vocab_size=vocab_size,
            min_frequency=2,
            show_progress=False,
            special_tokens=[],
            initial_alphabet=[chr(i) for i in range(high - low + 1)],
            max_token_length=10_000,
        )
        # the inner tokenizer trains with our alphabet (ByteLevelBPETokenizer.train_from_iterator would replace it)
        bpe._tokenizer.train_from_iterator((_to_characters(r - low) for r in rounded), trainer=trainer)
        horizon, dim = arrays[0].shape
        return cls(
            PreTrainedTokenizerFast(tokenizer_object=bpe, clean_up_tokenization_spaces=False),
            scale=scale,
            vocab_size=vocab_size,
            min_token=low,
            time_horizon=time_horizon if time_horizon is not None else horizon,
            action_dim=action_dim if action_dim is not None else dim,
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(scale={self.scale}, vocab_size={self.vocab_size}, min_token={self.min_token}, "
            f"time_horizon={self.time_horizon}, action_dim={self.action_dim})"
        )


@functools.lru_cache(maxsize=32)
def _dct_matrix(length: int) -> np.ndarray:
    """The orthonormal DCT-II matrix `[length, length]` in float64: entry `(k, n)` is `s_k cos(pi (2n + 1) k / 2N)`,
    `s_0 = sqrt(1 / N)`, `s_k = sqrt(2 / N)`. It is orthogonal, so its transpose is the orthonormal DCT-III."""
    k = np.arange(length, dtype=np.float64)[:, None]
    n = np.arange(length, dtype=np.float64)[None, :]
    matrix = np.cos(np.pi * (2 * n + 1) * k / (2 * length)) * np.sqrt(2 / length)
    matrix[0] /= np.sqrt(2)
    matrix.setflags(write=False)
    return matrix


def dct(values: np.ndarray, axis: int) -> np.ndarray:
    """Orthonormal DCT-II of `values` along `axis`, in float64 (`scipy.fft.dct(values, axis=axis, norm="ortho")`).

    >>> np.abs(dct(np.array([1.0, 1.0, 1.0, 1.0]), axis=0)).round(12)  # a constant has only the lowest frequency
    array([2., 0., 0., 0.])
    """
    moved = np.moveaxis(np.asarray(values, dtype=np.float64), axis, -1)
    return np.moveaxis(moved @ _dct_matrix(moved.shape[-1]).T, -1, axis)


def idct(coefficients: np.ndarray, axis: int) -> np.ndarray:
    """Orthonormal DCT-III (the inverse of [`dct`]) along `axis`, in float64 (`scipy.fft.idct(..., norm="ortho")`).

    >>> values = np.array([[0.5, -1.0], [2.0, 0.25], [3.0, 1.0]])
    >>> bool(np.allclose(idct(dct(values, axis=0), axis=0), values, rtol=0, atol=1e-15))
    True
    """
    moved = np.moveaxis(np.asarray(coefficients, dtype=np.float64), axis, -1)
    return np.moveaxis(moved @ _dct_matrix(moved.shape[-1]), -1, axis)


def _to_characters(shifted: np.ndarray) -> str:
    """One character per (shifted, rounded) coefficient; negatives clip to 0."""
    return "".join(map(chr, np.maximum(shifted, 0).astype(int)))
