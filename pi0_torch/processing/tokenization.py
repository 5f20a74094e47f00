"""Prompt tokenization for π0 and π0.5 (openpi's `PaligemmaTokenizer`), over SentencePiece or transformers tokenizers.

- Cleaning: `prompt.strip()`, then `_` and newlines become spaces (no lowercasing, as openpi's PaligemmaTokenizer).
- π0: `[bos] + encode(text) + encode("\\n")` (the newline is its own "start of answer" piece).
- π0.5 (discrete state): `[bos] + encode(f"Task: {text}, State: {bins};\\nAction: ")` where `bins` are the
  normalized, unpadded state digitized into 256 bins over [-1, 1] (`np.digitize(s, linspace(-1, 1, 257)[:-1]) - 1`:
  -1 for values below -1, 255 for values at or above 1 - 2/256), joined by spaces.
- Then right-padded with the pad id (0 for PaliGemma) to `max_len` with mask False, or truncated to `max_len` with a
  warning (`truncation="warn"`, openpi's behaviour) or a `ValueError` (`truncation="error"`).

The real tokenizer is PaliGemma's SentencePiece model (`paligemma_tokenizer.model`: vocab 257,152, pad 0, eos 1,
bos 2). [`build_test_tokenizer`] trains a small SentencePiece model with the same special ids on the fly, for tests
and demos where the real file is not available.

```python
>>> tok = build_test_tokenizer()
>>> ids, mask = tok.tokenize("pick_up the fork\\n", max_len=16)
>>> int(ids[0]) == tok.bos_id, int(mask.sum()) == len(tok.encode("pick up the fork")) + 2, ids.shape
(True, True, (16,))
>>> format_pi05_prompt("pick up the fork", [-1.0, 0.0, 1.5])
'Task: pick up the fork, State: 0 128 255;\\nAction: '

```
"""

from __future__ import annotations

import io
import itertools
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Union

import numpy as np
import sentencepiece

from pi0_torch.utils.optional import is_transformers_tokenizer

if TYPE_CHECKING:  # (imported where used: the processing code runs without transformers, `pi0_torch.utils.optional`)
    from transformers import PreTrainedTokenizerBase

SENTENCEPIECE_FILE = "tokenizer.model"
NUM_STATE_BINS = 256
MIN_TEST_VOCAB = 320
TEST_TOKENIZER = "test"  # what `pi0-torch train` / `convert --tokenizer` accept for [`build_test_tokenizer`]
TEST_TOKENIZER_VOCAB = 512  # its vocabulary there (at most the model's)
Truncation = Literal["warn", "error"]
TokenizerSource = Union["PromptTokenizer", sentencepiece.SentencePieceProcessor, "PreTrainedTokenizerBase", str, Path]


def clean_prompt(prompt: str) -> str:
    """openpi's cleaning: strip surrounding whitespace, then `_` and newlines -> spaces."""
    return prompt.strip().replace("_", " ").replace("\n", " ")


def discretize_state(normalized_state: Any) -> np.ndarray:
    """Bins (int64, -1..255) of a normalized state vector, as openpi's π0.5 prompt uses them."""
    state = np.asarray(normalized_state, dtype=np.float64)
    if state.ndim != 1:
        raise ValueError(f"state to discretize must be 1-D, got shape {state.shape}")
    edges = np.linspace(-1.0, 1.0, NUM_STATE_BINS + 1)[:-1]
    return (np.digitize(state, bins=edges) - 1).astype(np.int64)


def format_pi05_prompt(text: str, normalized_state: Any) -> str:
    """`"Task: {clean text}, State: {bins};\\nAction: "` (openpi's π0.5 discrete-state prompt)."""
    bins = " ".join(str(int(b)) for b in discretize_state(normalized_state))
    return f"Task: {clean_prompt(text)}, State: {bins};\nAction: "


class PromptTokenizer:
    """Text -> token ids for π0 / π0.5 prompts, over a SentencePiece model or a `transformers` tokenizer.

    Build it with [`load_tokenizer`] (a `.model` file, a folder, a SentencePiece processor or a transformers
    tokenizer) or [`build_test_tokenizer`]. A transformers tokenizer is used with `add_special_tokens=False` and its
    `bos_token_id` prepended, so both backends give the same ids for the same vocabulary.
    """

    def __init__(self, backend: sentencepiece.SentencePieceProcessor | PreTrainedTokenizerBase) -> None:
        if isinstance(backend, sentencepiece.SentencePieceProcessor):
            self.kind = "sentencepiece"
            bos, pad, eos = backend.bos_id(), backend.pad_id(), backend.eos_id()
            self.vocab_size = int(backend.get_piece_size())
        elif is_transformers_tokenizer(backend):
            self.kind = "transformers"
            bos, pad, eos = backend.bos_token_id, backend.pad_token_id, backend.eos_token_id
            self.vocab_size = len(backend)
        else:
            raise TypeError(
                f"tokenizer must be a sentencepiece.SentencePieceProcessor or a transformers tokenizer, got "
                f"{type(backend).__name__}"
            )
        if bos is None or bos < 0:
            raise ValueError("the tokenizer has no beginning-of-sequence token; π0 prompts start with one")
        self.backend = backend
        self.bos_id = int(bos)
        self.pad_id = int(pad) if pad is not None and pad >= 0 else 0  # openpi pads with 0
        self.eos_id = int(eos) if eos is not None and eos >= 0 else None  # ends π0-FAST's action postfix

    def encode(self, text: str, add_bos: bool = False) -> list[int]:
        if self.kind == "sentencepiece":
            ids = list(self.backend.encode(text))
        else:
            ids = list(self.backend.encode(text, add_special_tokens=False))
        return [self.bos_id, *ids] if add_bos else ids

    def decode(self, ids: Iterable[int]) -> str:
        ids = [int(i) for i in ids]
        if self.kind == "sentencepiece":
            return self.backend.decode(ids)
        return self.backend.decode(ids, skip_special_tokens=False)

    def prompt_ids(self, prompt: str, normalized_state: Any | None = None) -> list[int]:
        """Unpadded ids: π0 format when `normalized_state` is None, π0.5 discrete-state format otherwise.

        Raises `ValueError` when the cleaned prompt is empty.
        """
        if not isinstance(prompt, str):
            raise ValueError(f"prompt: expected a string, got {type(prompt).__name__}")
        try:
            prompt.encode("utf-8")
        except UnicodeEncodeError as error:  # a lone surrogate ("\ud800abc"): the tokenizers fail on it with no reason
            raise ValueError(f"prompt: not valid text: {prompt[error.start:error.end]!r} at position {error.start} "
                             "is half of a UTF-16 surrogate pair (a decoding error upstream?)") from None
        text = clean_prompt(prompt)
        if not text.strip():
            raise ValueError(f"prompt: empty after cleaning (got {prompt!r}); give the task instruction")
        if normalized_state is None:
            return self.encode(text, add_bos=True) + self.encode("\n")
        return self.encode(format_pi05_prompt(text, normalized_state), add_bos=True)

    def tokenize(
        self, prompt: str, max_len: int, normalized_state: Any | None = None, truncation: Truncation = "warn"
    ) -> tuple[np.ndarray, np.ndarray]:
        """`(ids int64 [max_len], mask bool [max_len])` padded/truncated as described in the module docstring."""
        ids = self.prompt_ids(prompt, normalized_state)
        if len(ids) > max_len:
            message = (
                f"prompt: {len(ids)} tokens exceed max_token_len {max_len} "
                f"({'π0.5 prompt with the state' if normalized_state is not None else 'π0 prompt'}: "
                f"{clean_prompt(prompt)[:60]!r}...)"
            )
            if truncation == "error":
                raise ValueError(message + "; shorten it or raise max_token_len")
            if truncation != "warn":
                raise ValueError(f"truncation must be 'warn' or 'error', got {truncation!r}")
            warnings.warn(message + "; truncating (the model sees only the first max_token_len tokens)", stacklevel=3)
            ids = ids[:max_len]
        valid = len(ids)
        tokens = np.full(max_len, self.pad_id, np.int64)
        tokens[:valid] = ids
        mask = np.zeros(max_len, bool)
        mask[:valid] = True
        return tokens, mask

    def save(self, directory: str | Path) -> None:
        """Write the tokenizer into `directory` (`tokenizer.model`, or the transformers tokenizer's own files)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        if self.kind == "sentencepiece":
            (directory / SENTENCEPIECE_FILE).write_bytes(self.backend.serialized_model_proto())
        else:
            self.backend.save_pretrained(str(directory))

    @classmethod
    def load(cls, directory: str | Path, kind: str) -> PromptTokenizer:
        """Read what [`save`] wrote (`kind` is `"sentencepiece"` or `"transformers"`)."""
        directory = Path(directory)
        if kind == "sentencepiece":
            return cls(_load_sentencepiece(directory / SENTENCEPIECE_FILE))
        if kind == "transformers":
            return cls(_load_transformers(directory))
        raise ValueError(f"unknown tokenizer kind {kind!r}; expected 'sentencepiece' or 'transformers'")


def _load_sentencepiece(path: Path) -> sentencepiece.SentencePieceProcessor:
    if not path.is_file():
        raise FileNotFoundError(f"SentencePiece model not found: {path}")
    processor = sentencepiece.SentencePieceProcessor()
    try:
        processor.LoadFromSerializedProto(path.read_bytes())
    except RuntimeError as error:
        raise ValueError(f"{path} is not a SentencePiece model: {error}") from None
    return processor


def _load_transformers(directory: Path) -> PreTrainedTokenizerBase:
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(str(directory), local_files_only=True)


def load_tokenizer(source: TokenizerSource) -> PromptTokenizer:
    """A [`PromptTokenizer`] from: itself; a `SentencePieceProcessor`; a transformers tokenizer; a path to a
    SentencePiece `.model` file (e.g. PaliGemma's `paligemma_tokenizer.model`); or a local folder holding
    `tokenizer.model` or a saved transformers tokenizer. Nothing is downloaded.
    """
    if isinstance(source, PromptTokenizer):
        return source
    if isinstance(source, sentencepiece.SentencePieceProcessor) or is_transformers_tokenizer(source):
        return PromptTokenizer(source)
    if not isinstance(source, (str, Path)):
        raise TypeError(f"cannot build a tokenizer from {type(source).__name__}")
    path = Path(source)
    if path.is_file():
        return PromptTokenizer(_load_sentencepiece(path))
    if path.is_dir():
        if (path / SENTENCEPIECE_FILE).is_file() and not (path / "tokenizer_config.json").is_file():
            return PromptTokenizer(_load_sentencepiece(path / SENTENCEPIECE_FILE))
        return PromptTokenizer(_load_transformers(path))
    raise FileNotFoundError(f"tokenizer not found: {path} (expected a SentencePiece .model file or a local folder)")


# ----------------------------------------------------------------------------------------------- test tokenizer

_VERBS = ("pick up", "put", "place", "move", "push", "open", "close", "grasp", "lift", "turn", "stack", "fold")
_OBJECTS = ("the fork", "the red cup", "a blue block", "the bowl", "the drawer", "the towel", "the green sponge",
            "the plate", "the bottle", "a spoon", "the lid", "the yellow box")
_PLACES = ("on the table", "in the sink", "into the basket", "next to the plate", "on the shelf", "to the left",
           "to the right", "under the cloth")


def _training_sentences(extra: Iterable[str]) -> list[str]:
    sentences = [f"{v} {o} {p}" for v, o, p in itertools.product(_VERBS, _OBJECTS, _PLACES)]
    # π0.5 prompt pieces with every state bin, so digits, ';', ':' and newlines are in the vocabulary
    bins = [str(b) for b in range(-1, NUM_STATE_BINS)]
    for i, sentence in enumerate(sentences[:: max(1, len(sentences) // 64)]):
        state = " ".join(bins[(i * 7 + j * 13) % len(bins)] for j in range(8))
        sentences.append(f"Task: {sentence}, State: {state};\nAction: ")
    sentences.extend(f"{sentence}\n" for sentence in sentences[:32])
    return sentences + list(extra)


def build_test_tokenizer(
    vocab_size: int = 512, extra_sentences: Iterable[str] = (), save_to: str | Path | None = None
) -> PromptTokenizer:
    """Train a small SentencePiece BPE tokenizer on robot-instruction text, in about a second, with no downloads.

    Special ids follow PaliGemma (pad 0, eos 1, bos 2, unk 3); unseen characters fall back to bytes, digits are split
    and whitespace is kept verbatim like Gemma's tokenizer. The vocabulary has at most `vocab_size` pieces (keep it
    <= the model's `vocab_size`; at least 320, the byte and character pieces). Training is deterministic. `save_to`
    optionally writes the `.model` file there.
    """
    if vocab_size < MIN_TEST_VOCAB:
        raise ValueError(
            f"vocab_size must be >= {MIN_TEST_VOCAB} (256 byte pieces + characters + specials), got {vocab_size}"
        )
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(_training_sentences(extra_sentences)),
        model_writer=model,
        model_type="bpe",
        vocab_size=vocab_size,
        hard_vocab_limit=False,
        pad_id=0,
        eos_id=1,
        bos_id=2,
        unk_id=3,
        byte_fallback=True,
        split_digits=True,
        normalization_rule_name="identity",
        remove_extra_whitespaces=False,
        add_dummy_prefix=False,
        allow_whitespace_only_pieces=True,
        user_defined_symbols=["\n"],
        num_threads=1,
        minloglevel=2,
    )
    processor = sentencepiece.SentencePieceProcessor()
    processor.LoadFromSerializedProto(model.getvalue())
    if save_to is not None:
        Path(save_to).parent.mkdir(parents=True, exist_ok=True)
        Path(save_to).write_bytes(model.getvalue())
    return PromptTokenizer(processor)
