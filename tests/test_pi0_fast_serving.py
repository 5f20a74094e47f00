"""Serving π0-FAST: `PI0Policy.from_pretrained` of a π0-FAST folder gives `PI0FastPolicy`, which the policy server
serves to openpi's own client (the helpers of `test_serving.py`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sentencepiece
import torch

from pi0_torch import PI0FastProcessor
from pi0_torch.conversion.convert import convert_openpi_checkpoint
from pi0_torch.runtime.observation_formats import ObservationFormat
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.policy_fast import PI0FastPolicy

from test_pi0_fast import FAST_DIR, FastReference, atomic_tail_tokenizer
from test_serving import client_python, run_client, running_server  # noqa: F401  (client_python is a fixture)


@pytest.fixture(scope="module")
def fast_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """openpi's π0-FAST fixture converted with its tokenizers (state and actions: 8 dims, quantile stats)."""
    output = tmp_path_factory.mktemp("fast") / "pi0_fast"
    convert_openpi_checkpoint(
        FAST_DIR / "ckpt" / "0", output, tokenizer=FAST_DIR / "tokenizer.model", fast_tokenizer=FAST_DIR / "fast_tokenizer",
        max_token_len=96, progress=False,
    )
    return output


def test_policy_turns_decoded_tokens_into_robot_actions(fast_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The chunk a policy returns is the decoded FAST chunk, unnormalized: script the tokens the model emits (with a
    prompt tokenizer whose FAST range is atomic, as PaliGemma's is, so the text round trip keeps them)."""
    loaded = PI0Policy.from_pretrained(fast_model_dir, device="cpu")
    assert isinstance(loaded, PI0FastPolicy) and loaded.metadata["model_type"] == "pi0_fast"
    assert loaded.num_steps == loaded.model.config.max_decoding_steps
    with pytest.raises(ValueError, match="noise_scale applies to flow-matching .* is a π0-FAST model"):
        PI0Policy.from_pretrained(fast_model_dir, device="cpu", noise_scale=0.25)
    tokenizer = atomic_tail_tokenizer(tmp_path / "tail.model")
    skip = sentencepiece.SentencePieceProcessor(model_file=str(tokenizer)).get_piece_size() - 516
    processor = PI0FastProcessor.from_config(loaded.model.config, tokenizer, FAST_DIR / "fast_tokenizer", fast_model_dir, fast_skip_tokens=skip)
    policy = PI0FastPolicy(loaded.model, processor, num_steps=40)
    reference = FastReference()
    tokens = processor.tokenize("pick", reference["inputs/state"][0], reference["inputs/actions"][0])
    emitted = torch.from_numpy(np.pad(tokens["input_ids"][tokens["token_ar_mask"]], (0, 10)))[None]  # "Action: ...|<eos>", zeros
    real_generate = policy.model.generate_tokens

    def scripted_generate(**inputs: torch.Tensor) -> torch.Tensor:
        assert real_generate(**inputs).shape == (1, 40)  # the model runs on what the processor made
        return emitted

    monkeypatch.setattr(policy.model, "generate_tokens", scripted_generate)
    frame = np.zeros((96, 128, 3), np.uint8)
    actions = policy.infer({"images": {"base_0_rgb": frame, "wrist_0_rgb": frame}, "state": np.zeros(8), "prompt": "pick"})["actions"]
    # the fixture's quantized chunk is in model space; the processor unnormalizes it with the checkpoint's stats
    expected = processor.postprocess_actions(reference["tokenizer/extracted_actions"][:1])[0]
    np.testing.assert_allclose(actions, expected, rtol=1e-6, atol=1e-6)


def test_openpi_client_is_served_pi0_fast(fast_model_dir: Path, client_python: Path, tmp_path: Path) -> None:  # noqa: F811
    policy = PI0Policy.from_pretrained(fast_model_dir, device="cpu", num_steps=6)
    with running_server(policy, obs_format=ObservationFormat.from_preset("libero_fast")) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port, layout="libero")
    meta = result["metadata"]
    assert meta["model_type"] == "pi0_fast" and meta["camera_names"] == ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
    assert (meta["state_dim"], meta["action_dim"], meta["action_horizon"]) == (8, 8, 10)
    reply = result["replies"][0]
    assert reply["shape"] == [10, 8] and reply["dtype"] == "float32" and reply["finite"]
    # the same observation in process gives the same chunk (the client script's first LIBERO observation)
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    wrist = rng.integers(0, 256, (3, 64, 64), dtype=np.uint8)
    state = rng.standard_normal(8).astype(np.float32)
    local = policy.infer({"images": {"base_0_rgb": base, "wrist_0_rgb": wrist}, "state": state, "prompt": "pick up the fork"})
    np.testing.assert_array_equal(np.asarray(reply["actions"], np.float32), local["actions"])
