"""Prompt formats and tokenization against openpi's PaligemmaTokenizer conventions and the fixtures' examples."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from tokenizers import Tokenizer, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

from pi0_torch.processing.tokenization import (
    PromptTokenizer,
    build_test_tokenizer,
    clean_prompt,
    discretize_state,
    format_pi05_prompt,
    load_tokenizer,
)

from conftest import FIXTURES


@pytest.fixture(scope="module")
def tokenizer() -> PromptTokenizer:
    return build_test_tokenizer()


def test_discretization_matches_openpi() -> None:
    with np.load(FIXTURES / "pi05_small" / "reference.npz") as reference:
        state, expected = reference["preproc/pi05_state_in"], reference["preproc/pi05_state_discretized"]
    bins = discretize_state(state)
    assert bins.dtype == np.int64
    np.testing.assert_array_equal(bins, expected)
    assert bins.min() == -1 and bins.max() == 255  # below -1 -> -1; at or above 1 - 2/256 -> 255


@pytest.mark.parametrize("raw_prompt", ["pick up the fork", "  pick_up the fork\n", "pick_up_the_fork"])
def test_pi05_prompt_matches_fixture_example(raw_prompt: str) -> None:
    meta = json.loads((FIXTURES / "pi05_small" / "meta.json").read_text())
    with np.load(FIXTURES / "pi05_small" / "reference.npz") as reference:
        state = reference["preproc/pi05_state_in"]
    assert format_pi05_prompt(raw_prompt, state) == meta["pi05_prompt_example"]
    assert meta["pi05_prompt_example"] == "Task: pick up the fork, State: 0 1 64 128 128 192 255 255 255 -1;\nAction: "


def test_clean_prompt_like_openpi() -> None:
    assert clean_prompt("  Open_the DRAWER\nslowly \n") == "Open the DRAWER slowly"  # no lowercasing
    assert clean_prompt("a\nb_c") == "a b c"


def test_pi0_tokens(tokenizer: PromptTokenizer) -> None:
    ids, mask = tokenizer.tokenize("pick_up the fork", max_len=48)
    expected = [tokenizer.bos_id, *tokenizer.encode("pick up the fork"), *tokenizer.encode("\n")]
    assert ids.dtype == np.int64 and mask.dtype == bool and ids.shape == mask.shape == (48,)
    assert ids[: len(expected)].tolist() == expected
    assert mask.tolist() == [True] * len(expected) + [False] * (48 - len(expected))
    assert np.all(ids[len(expected) :] == 0)  # PaliGemma pad id


def test_pi05_tokens(tokenizer: PromptTokenizer) -> None:
    state = np.array([-1.0, 0.0, 0.5, 2.0])
    ids, mask = tokenizer.tokenize("pick up the fork", max_len=200, normalized_state=state)
    expected = [tokenizer.bos_id, *tokenizer.encode("Task: pick up the fork, State: 0 128 192 255;\nAction: ")]
    assert ids[: len(expected)].tolist() == expected and int(mask.sum()) == len(expected)
    assert tokenizer.decode(ids[1 : len(expected)]) == "Task: pick up the fork, State: 0 128 192 255;\nAction: "


def test_long_prompt_warns_and_truncates(tokenizer: PromptTokenizer) -> None:
    long_prompt = " ".join(["pick up the red cup and place it on the shelf"] * 10)
    full = tokenizer.prompt_ids(long_prompt)
    with pytest.warns(UserWarning, match=rf"prompt: {len(full)} tokens exceed max_token_len 48 .*truncating"):
        ids, mask = tokenizer.tokenize(long_prompt, max_len=48)
    assert ids.tolist() == full[:48] and mask.all()
    with pytest.raises(ValueError, match=rf"prompt: {len(full)} tokens exceed max_token_len 48"):
        tokenizer.tokenize(long_prompt, max_len=48, truncation="error")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ids, mask = tokenizer.tokenize("pick up the fork", max_len=len(tokenizer.prompt_ids("pick up the fork")))
    assert mask.all()


@pytest.mark.parametrize(
    ("prompt", "message"),
    [("", "empty after cleaning"), (" _\n_ ", "empty after cleaning"), (3, "expected a string, got int"),
     ("pick \ud800up", r"not valid text: '\\ud800' at position 5 is half of a UTF-16 surrogate pair")],
)
def test_bad_prompts(tokenizer: PromptTokenizer, prompt: object, message: str) -> None:
    with pytest.raises(ValueError, match=f"^prompt: {message}"):
        tokenizer.tokenize(prompt, max_len=48)  # type: ignore[arg-type]


def test_test_tokenizer_is_paligemma_like_and_deterministic(tokenizer: PromptTokenizer) -> None:
    sp = tokenizer.backend
    assert (sp.pad_id(), sp.eos_id(), sp.bos_id(), sp.unk_id()) == (0, 1, 2, 3)
    assert tokenizer.kind == "sentencepiece" and tokenizer.vocab_size <= 512
    assert build_test_tokenizer().backend.serialized_model_proto() == sp.serialized_model_proto()
    text = "Task: Put the Zebra ✓ in the box, State: -1 0 255;\nAction: "  # unseen characters fall back to bytes
    ids = tokenizer.encode(text)
    assert sp.unk_id() not in ids and tokenizer.decode(ids) == text
    small = build_test_tokenizer(vocab_size=320)
    assert small.vocab_size <= 320 and small.decode(small.encode(text)) == text
    with pytest.raises(ValueError, match="vocab_size must be >= 320"):
        build_test_tokenizer(vocab_size=300)


def test_load_and_save_sentencepiece(tokenizer: PromptTokenizer, tmp_path) -> None:
    model_file = tmp_path / "paligemma_tokenizer.model"
    build_test_tokenizer(save_to=model_file)
    for source in (model_file, str(model_file), tokenizer.backend, tokenizer):
        loaded = load_tokenizer(source)
        assert loaded.encode("pick up the fork", add_bos=True) == tokenizer.encode("pick up the fork", add_bos=True)
    tokenizer.save(tmp_path / "saved")
    assert (tmp_path / "saved" / "tokenizer.model").is_file()
    for loaded in (load_tokenizer(tmp_path / "saved"), PromptTokenizer.load(tmp_path / "saved", "sentencepiece")):
        assert loaded.backend.serialized_model_proto() == tokenizer.backend.serialized_model_proto()


def _word_level_hf_tokenizer() -> PreTrainedTokenizerFast:
    words = ["<pad>", "<eos>", "<bos>", "<unk>", "pick", "up", "the", "fork", "\n"]
    backend = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.Whitespace()
    return PreTrainedTokenizerFast(
        tokenizer_object=backend, bos_token="<bos>", eos_token="<eos>", pad_token="<pad>", unk_token="<unk>"
    )


def test_transformers_tokenizer_backend(tmp_path) -> None:
    tokenizer = load_tokenizer(_word_level_hf_tokenizer())
    assert tokenizer.kind == "transformers" and (tokenizer.bos_id, tokenizer.pad_id) == (2, 0)
    ids, mask = tokenizer.tokenize("pick_up the fork", max_len=8)
    # bos added once by us (add_special_tokens=False on the transformers side); this vocabulary drops "\n"
    assert ids.tolist() == [2, 4, 5, 6, 7, 0, 0, 0] and mask.tolist() == [True] * 5 + [False] * 3
    tokenizer.save(tmp_path)
    reloaded = PromptTokenizer.load(tmp_path, "transformers")
    assert reloaded.kind == "transformers"
    assert np.array_equal(reloaded.tokenize("pick up the fork", max_len=8)[0], ids)
    assert load_tokenizer(tmp_path).kind == "transformers"


def test_load_tokenizer_errors(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="tokenizer not found"):
        load_tokenizer(tmp_path / "nope.model")
    bad = tmp_path / "bad.model"
    bad.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="is not a SentencePiece model"):
        load_tokenizer(bad)
    with pytest.raises(TypeError, match="cannot build a tokenizer from int"):
        load_tokenizer(3)  # type: ignore[arg-type]
    hf = _word_level_hf_tokenizer()
    hf.bos_token = None
    with pytest.raises(ValueError, match="no beginning-of-sequence token"):
        PromptTokenizer(hf)
