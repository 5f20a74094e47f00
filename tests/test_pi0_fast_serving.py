"""Serving π0-FAST: `PI0Policy.from_pretrained` of a π0-FAST folder gives `PI0FastPolicy`, which the policy server
serves to openpi's own client (the helpers of `test_serving.py`). A chunk whose tokens decode to no action chunk is
never served as one (issue 38.6): it is withheld like a non-finite chunk, naming the cause."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import sentencepiece
import torch
import websockets.sync.client

from conftest import HANG_S
from pi0_torch import PI0FastProcessor
from pi0_torch.conversion.convert import convert_openpi_checkpoint
from pi0_torch.runtime.action_safety import UnsafeActionsError
from pi0_torch.runtime.observation_formats import ObservationFormat
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.policy_fast import PI0FastPolicy
from pi0_torch.runtime.serving import pack_message, unpack_message

from test_pi0_fast import FAST_DIR, FastReference, atomic_tail_tokenizer
from test_serving import client_python, run_client, running_server  # noqa: F401  (client_python is a fixture)

WITHHELD = ("the action chunk holds 80 NaN/inf values and was withheld; cause: the generated tokens decode to no "
            "action chunk (the logged warning shows them)")
FRAME = np.zeros((96, 128, 3), np.uint8)
OBSERVATION = {"images": {"base_0_rgb": FRAME, "wrist_0_rgb": FRAME}, "state": np.zeros(8), "prompt": "pick"}


@pytest.fixture(scope="module")
def fast_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """openpi's π0-FAST fixture converted with its tokenizers (state and actions: 8 dims, quantile stats)."""
    output = tmp_path_factory.mktemp("fast") / "pi0_fast"
    convert_openpi_checkpoint(
        FAST_DIR / "ckpt" / "0", output, tokenizer=FAST_DIR / "tokenizer.model", fast_tokenizer=FAST_DIR / "fast_tokenizer",
        max_token_len=96, progress=False,
    )
    return output


class Scripted:
    """A π0-FAST policy whose model emits scripted tokens (the model still runs on what the processor made), with a
    prompt tokenizer whose FAST range is atomic, as PaliGemma's is, so the text round trip keeps them. Each chunk
    takes the next row of `script`, or `action` (the fixture's chunk: "Action: ...|<eos>") once it is empty."""

    def __init__(self, fast_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        loaded = PI0Policy.from_pretrained(fast_model_dir, device="cpu")
        tokenizer = atomic_tail_tokenizer(tmp_path / "tail.model")
        skip = sentencepiece.SentencePieceProcessor(model_file=str(tokenizer)).get_piece_size() - 516
        self.processor = PI0FastProcessor.from_config(loaded.model.config, tokenizer, FAST_DIR / "fast_tokenizer",
                                                      fast_model_dir, fast_skip_tokens=skip)
        self.policy = PI0FastPolicy(loaded.model, self.processor, num_steps=40)
        reference = FastReference()
        tokens = self.processor.tokenize("pick", reference["inputs/state"][0], reference["inputs/actions"][0])
        self.action = tokens["input_ids"][tokens["token_ar_mask"]]
        # the fixture's quantized chunk is in model space; the processor unnormalizes it with the checkpoint's stats
        self.expected = self.processor.postprocess_actions(reference["tokenizer/extracted_actions"][:1])[0]
        self.script: list[np.ndarray] = []
        generate = self.policy.model.generate_tokens

        def scripted_generate(**inputs: torch.Tensor) -> torch.Tensor:
            assert generate(**inputs).shape == (len(inputs["input_ids"]), 40)
            rows = [self.script.pop(0) if self.script else self.action for _ in inputs["input_ids"]]
            return torch.from_numpy(np.stack([np.pad(row, (0, 50 - len(row))) for row in rows]))

        monkeypatch.setattr(self.policy.model, "generate_tokens", scripted_generate)


@pytest.fixture
def scripted(fast_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Scripted]:
    yield Scripted(fast_model_dir, tmp_path, monkeypatch)


def test_policy_turns_decoded_tokens_into_robot_actions(fast_model_dir: Path, scripted: Scripted) -> None:
    """The chunk a policy returns is the decoded FAST chunk, unnormalized."""
    loaded = PI0Policy.from_pretrained(fast_model_dir, device="cpu")
    assert isinstance(loaded, PI0FastPolicy) and loaded.metadata["model_type"] == "pi0_fast"
    assert loaded.num_steps == loaded.model.config.max_decoding_steps
    with pytest.raises(ValueError, match="noise_scale applies to flow-matching .* is a π0-FAST model"):
        PI0Policy.from_pretrained(fast_model_dir, device="cpu", noise_scale=0.25)
    np.testing.assert_allclose(scripted.policy.infer(OBSERVATION)["actions"], scripted.expected, rtol=1e-6, atol=1e-6)


def test_cuda_graphs_of_a_fast_policy(fast_model_dir: Path, monkeypatch: pytest.MonkeyPatch,
                                      caplog: pytest.LogCaptureFixture) -> None:
    """`cuda_graph=True` replays each decoded token as a hand-captured CUDA graph (`capture_decoding`) and needs CUDA
    (`serve` passes it by default on cuda); `compile=True` where inductor's graphs of the decoding step crashed
    (torch < 2.12 on CUDA; stood in here) replays the hand-captured graphs instead, with a warning."""
    with pytest.raises(ValueError, match="cuda_graph needs a CUDA device; this policy runs on cpu"):
        PI0Policy.from_pretrained(fast_model_dir, device="cpu", cuda_graph=True)
    loaded = PI0Policy.from_pretrained(fast_model_dir, device="cpu")
    assert not loaded.captured and not loaded.compiled
    reason = "π0-FAST's compiled decoding replayed as CUDA graphs crashes the process with torch 2.11.0"
    monkeypatch.setattr(loaded.model, "decoding_graphs_reason", lambda: reason)
    with caplog.at_level(logging.WARNING):
        policy = PI0FastPolicy(loaded.model, loaded.processor, compile=True)
    assert policy.captured and not policy.compiled
    assert f"compile=True: decoding replays hand-captured CUDA graphs instead: {reason}" in caplog.text


def test_a_chunk_whose_tokens_do_not_decode_is_withheld(scripted: Scripted, caplog: pytest.LogCaptureFixture) -> None:
    """Every way tokens fail to be a chunk (no "Action: ", FAST ids that are not a whole chunk, ids outside FAST's
    vocabulary) is withheld naming the cause, never returned as zeros unnormalized into a plausible row; in a batch,
    only the chunk that did not decode."""
    cases = {
        "no 'Action: '": np.zeros(4, np.int64),
        "a partial chunk": scripted.action[:-6],  # "Action: " and the first FAST tokens, no "|"
        "not FAST ids": np.asarray(scripted.processor.tokenizer.encode("Action: pick up|")),  # text, not FAST ids
    }
    for case, row in cases.items():
        scripted.script.append(row)
        with caplog.at_level(logging.WARNING), pytest.raises(UnsafeActionsError) as withheld:
            scripted.policy.infer(OBSERVATION)
        assert str(withheld.value) == WITHHELD, case
    assert caplog.text.count("returning a chunk of NaN (undecodable)") == len(cases)
    scripted.script.extend([scripted.action, np.zeros(4, np.int64)])
    with pytest.raises(UnsafeActionsError) as withheld:
        scripted.policy.infer_prepared([scripted.policy.prepare(OBSERVATION)] * 2)
    served, refused = withheld.value.outcomes
    np.testing.assert_allclose(served["actions"], scripted.expected, rtol=1e-6, atol=1e-6)
    assert str(refused) == f"observation 1 of a batch of 2: {WITHHELD}"


def test_a_served_chunk_that_does_not_decode_gets_no_actions(scripted: Scripted, caplog: pytest.LogCaptureFixture) -> None:
    """Over the server: the warm-up that decodes no chunk says so in the log, the request whose tokens do not decode
    gets `no actions: ...` with the cause, and the next one its actions."""
    scripted.script.extend([np.zeros(4, np.int64), np.zeros(4, np.int64)])  # the warm-up's chunk, the first request's
    with caplog.at_level(logging.WARNING), running_server(scripted.policy) as port:
        with websockets.sync.client.connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
            unpack_message(ws.recv(timeout=HANG_S))
            ws.send(pack_message(OBSERVATION))
            assert ws.recv(timeout=HANG_S) == f"no actions: {WITHHELD}"
            ws.send(pack_message(OBSERVATION))
            actions = unpack_message(ws.recv(timeout=HANG_S))["actions"]
    np.testing.assert_allclose(actions, scripted.expected, rtol=1e-6, atol=1e-6)
    assert "warm-up: the tokens generated for the blank observation decode to no action chunk (1 of 1 chunks)" in caplog.text


def test_openpi_client_is_served_pi0_fast(scripted: Scripted, client_python: Path, tmp_path: Path) -> None:  # noqa: F811
    with running_server(scripted.policy, obs_format=ObservationFormat.from_preset("libero_fast")) as port:
        result = run_client(client_python, tmp_path, mode="infer", port=port, layout="libero")
    meta = result["metadata"]
    assert meta["model_type"] == "pi0_fast" and meta["camera_names"] == ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
    assert (meta["state_dim"], meta["action_dim"], meta["action_horizon"]) == (8, 8, 10)
    reply = result["replies"][0]
    assert reply["shape"] == [10, 8] and reply["dtype"] == "float32" and reply["finite"]
    np.testing.assert_allclose(np.asarray(reply["actions"], np.float32), scripted.expected, rtol=1e-6, atol=1e-6)
