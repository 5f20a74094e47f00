"""π0-FAST against openpi's own outputs (`tests/fixtures/openpi/pi0_fast_small`, see its README): FAST ids and
decodes, prompt tokenization, float32 / bf16 loss and log-probs, prefix embeddings, attention mask, greedy decoding."""

from __future__ import annotations

import io
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import sentencepiece
import torch

from pi0_torch import PI0FastConfig, PI0FastForActionGeneration
from pi0_torch.conversion.openpi_weights import config_from_openpi_shapes, load_openpi_params
from pi0_torch.inference import checks, fast_decoding
from pi0_torch.inference.decoding_graphs import DecodingGraphs
from pi0_torch.inference.layer_pass import decoder_sampling_weights
from pi0_torch.kernels import ops
from pi0_torch.masks import prefix_lm_mask
from pi0_torch.models.modeling_pi0_fast import token_log_probs
from pi0_torch.processing.fast_tokenizer import FASTActionTokenizer, dct, idct
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0_fast import PI0FastProcessor
from pi0_torch.utils.op_count import AtenOpCounter

from conftest import FIXTURES, relative_error

FAST_DIR = FIXTURES / "pi0_fast_small"
TASK = dict(action_dim=8, action_horizon=10, max_token_len=96)  # what the fixture's openpi config set


class FastReference:
    """The π0-FAST fixture: openpi weights, inputs in our layout, openpi's outputs."""

    def __init__(self) -> None:
        self.params = dict(np.load(FAST_DIR / "params_flat.npz"))
        self.arrays = dict(np.load(FAST_DIR / "reference.npz"))
        self.config = config_from_openpi_shapes({k: v.shape for k, v in self.params.items()}, **TASK)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def model(self, dtype: torch.dtype = torch.float32) -> PI0FastForActionGeneration:
        model = PI0FastForActionGeneration(self.config).eval()
        load_openpi_params(model, self.params)
        return model.to(dtype)

    def inputs(self, kind: str) -> dict[str, torch.Tensor]:
        """`inputs/{train,infer}/*` with the images channels-first, cameras stacked in config order."""
        cameras = self.config.camera_names
        images = np.stack([self[f"inputs/images/{c}"] for c in cameras], axis=1)  # [B, C, H, W, 3]
        return dict(
            pixel_values=torch.from_numpy(images).permute(0, 1, 4, 2, 3).contiguous(),
            image_masks=torch.from_numpy(np.stack([self[f"inputs/image_masks/{c}"] for c in cameras], axis=1)),
            input_ids=torch.from_numpy(self[f"inputs/{kind}/tokens"]),
            attention_mask=torch.from_numpy(self[f"inputs/{kind}/token_mask"]),
            token_ar_mask=torch.from_numpy(self[f"inputs/{kind}/ar_mask"]),
        )


@pytest.fixture(scope="module")
def fast_reference() -> FastReference:
    return FastReference()


@pytest.fixture(scope="module")
def fast_tokenizer() -> FASTActionTokenizer:
    return FASTActionTokenizer.from_pretrained(FAST_DIR / "fast_tokenizer")


def fixture_fast_ids(reference: FastReference) -> list[list[int]]:
    return [[int(i) for i in row if i >= 0] for row in reference["tokenizer/fast_ids"]]


# ----------------------------------------------------------------------------------------------- tokenizers


def test_fast_ids_and_decode_match_openpi(fast_reference: FastReference, fast_tokenizer: FASTActionTokenizer) -> None:
    assert (fast_tokenizer.scale, fast_tokenizer.vocab_size, fast_tokenizer.min_token) == (10, 512, -31)
    ids = fixture_fast_ids(fast_reference)
    assert fast_tokenizer(fast_reference["inputs/actions"]) == ids
    assert [fast_tokenizer(chunk)[0] for chunk in fast_reference["inputs/actions"]] == ids  # [H, A] one at a time
    decoded = fast_tokenizer.decode(ids, time_horizon=10, action_dim=8)
    np.testing.assert_array_equal(decoded.astype(np.float32), fast_reference["tokenizer/extracted_actions"])


def test_undecodable_tokens_give_zeros_with_a_warning(fast_tokenizer: FASTActionTokenizer, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        chunks = fast_tokenizer.decode([[5, 6, 7], [-3], [512]], time_horizon=10, action_dim=8)
    assert chunks.shape == (3, 10, 8) and not chunks.any()
    assert sum("returning a chunk of zeros" in record.message for record in caplog.records) == 3
    with pytest.raises(ValueError, match="time_horizon and action_dim"):
        FASTActionTokenizer(fast_tokenizer.bpe).decode([[1]])


def test_fit_save_and_reload(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    chunks = [np.cumsum(rng.normal(0, 0.05, (12, 4)), axis=0) for _ in range(300)]
    tokenizer = FASTActionTokenizer.fit(chunks, scale=20, vocab_size=300)
    ids = tokenizer(np.stack(chunks[:5]))
    assert max(max(row) for row in ids) < 300 and np.mean([len(row) for row in ids]) < 12 * 4
    decoded = tokenizer.decode(ids)
    # rounding in the orthonormal DCT space: per-coefficient error <= 1 / (2 scale), so the chunk's L2 error too
    assert np.sqrt(((decoded - np.stack(chunks[:5])) ** 2).sum(axis=(1, 2))).max() <= np.sqrt(48) / 40 + 1e-9
    tokenizer.save_pretrained(tmp_path / "fast")
    assert sorted(p.name for p in (tmp_path / "fast").iterdir()) == [
        ".pi0-torch-manifest.json", "processor_config.json", "tokenizer.json", "tokenizer_config.json"]
    reloaded = FASTActionTokenizer.from_pretrained(tmp_path / "fast")
    assert reloaded(np.stack(chunks[:5])) == ids and (reloaded.time_horizon, reloaded.action_dim) == (12, 4)
    with pytest.raises(ValueError, match="vocab_size 8 cannot hold"):
        FASTActionTokenizer.fit(chunks, scale=20, vocab_size=8)
    with pytest.raises(FileNotFoundError, match="processor_config.json"):
        FASTActionTokenizer.from_pretrained(tmp_path)


def test_dct_is_scipys_orthonormal_dct() -> None:
    """FAST's DCT-II / DCT-III (a float64 matrix product) against scipy's, which openpi's FAST tokenizer uses:
    the same to 1e-12; the same FAST coefficients after scaling and rounding for float64 chunks; for float32 chunks
    (scipy computes in float32) a rounding differs only where the coefficient lies within float32 error of a tie."""
    scipy_fft = pytest.importorskip("scipy.fft")
    rng = np.random.default_rng(0)
    for shape, axis in (((10, 8), 0), ((3, 50, 32), 1), ((1, 1), 0), ((7, 5, 2), 2)):
        values = rng.normal(0, 3, shape)
        np.testing.assert_allclose(dct(values, axis), scipy_fft.dct(values, axis=axis, norm="ortho"), rtol=0, atol=1e-12)
        np.testing.assert_allclose(idct(values, axis), scipy_fft.idct(values, axis=axis, norm="ortho"), rtol=0, atol=1e-12)
    chunks = np.cumsum(rng.normal(0, 0.3, (2000, 10, 8)), axis=1)  # smooth, like action chunks
    for scale in (10, 100):
        assert np.array_equal(np.around(dct(chunks, 1) * scale), np.around(scipy_fft.dct(chunks, axis=1, norm="ortho") * scale))
        chunks32 = chunks.astype(np.float32)
        exact = dct(chunks32, 1) * scale
        differ = np.around(exact) != np.around(scipy_fft.dct(chunks32, axis=1, norm="ortho") * scale)
        distance_to_tie = np.abs(np.abs(exact - np.floor(exact)) - 0.5)
        assert differ.sum() <= 5 and (distance_to_tie[differ] < 1e-4).all()


def test_prompt_tokenization_matches_openpi(fast_reference: FastReference) -> None:
    processor = PI0FastProcessor.from_config(
        fast_reference.config, FAST_DIR / "tokenizer.model", FAST_DIR / "fast_tokenizer", norm_mode="none",
        state_dim=8, action_dim_robot=8,
    )
    state = fast_reference["inputs/state"]
    assert (np.abs(state) > 1).any()  # bins -1 and 255 are exercised
    names = {"input_ids": "tokens", "attention_mask": "token_mask", "token_ar_mask": "ar_mask", "token_loss_mask": "loss_mask"}
    for row, prompt in enumerate(fast_reference["tokenizer/prompts"]):
        for kind, actions in (("train", fast_reference["inputs/actions"][row]), ("infer", None)):
            ours = processor.tokenize(str(prompt), state[row], actions)
            for key, theirs in names.items():
                np.testing.assert_array_equal(ours[key], fast_reference[f"inputs/{kind}/{theirs}"][row], err_msg=f"{kind} {key}")


# ----------------------------------------------------------------------------------------------- model


def test_float32_parity(fast_reference: FastReference) -> None:
    model = fast_reference.model()
    train = fast_reference.inputs("train")
    loss_mask = torch.from_numpy(fast_reference["inputs/train/loss_mask"])
    with torch.no_grad():
        tokens, valid, flags = model.embed_inputs(**train)
        output = model(**train, token_loss_mask=loss_mask)
    mask, _ = prefix_lm_mask(valid, flags)
    np.testing.assert_array_equal(mask.numpy(), fast_reference["fp32/attn_mask"])
    assert relative_error(tokens, fast_reference["fp32/prefix_embeddings"]) < 1e-4  # measured 2.6e-5 (SigLIP in float32)
    assert relative_error(output.loss, fast_reference["fp32/loss"].mean()) < 1e-5
    target_logp = token_log_probs(output.logits, train["input_ids"][:, 1:])
    assert relative_error(target_logp, fast_reference["fp32/target_logp"]) < 1e-5
    infer = fast_reference.inputs("infer")
    steps = int(fast_reference["inputs/max_decoding_steps"])
    tokens = model.generate_tokens(**infer, max_new_tokens=steps)
    np.testing.assert_array_equal(tokens.numpy(), fast_reference["fp32/output_tokens"])  # row 1 has a masked camera


def test_bf16_inference_parity(fast_reference: FastReference) -> None:
    model = fast_reference.model(torch.bfloat16)
    train = fast_reference.inputs("train")
    loss_mask = torch.from_numpy(fast_reference["inputs/train/loss_mask"])
    with torch.no_grad():
        output = model(**train, token_loss_mask=loss_mask)
    assert output.logits.dtype == torch.bfloat16
    assert relative_error(output.loss, fast_reference["bf16_infer/loss"].mean()) < 1e-2  # measured 8.8e-4
    target_logp = token_log_probs(output.logits, train["input_ids"][:, 1:])[loss_mask[:, 1:]]
    assert relative_error(target_logp, fast_reference["bf16_infer/target_logp"][loss_mask[:, 1:].numpy()]) < 3e-2


def test_decoding_stops_when_every_row_emits_eos(fast_reference: FastReference, monkeypatch: pytest.MonkeyPatch) -> None:
    """openpi's rule: stop after the first step at which every row's new token is EOS; the rest stays 0."""
    model = fast_reference.model()
    infer = fast_reference.inputs("infer")
    vocab, eos = model.config.vocab_size, model.config.eos_token_id
    scripted = iter([[eos, 7], [9, eos], [eos, eos], [5, 5]])  # the rows' tokens, step by step

    def logits_for(step_tokens: list[int]) -> torch.Tensor:
        return torch.nn.functional.one_hot(torch.tensor(step_tokens), vocab).float()

    prepare = model.prepare_decoding
    monkeypatch.setattr(model, "prepare_decoding", lambda *args: (prepare(*args)[0], logits_for(next(scripted))))
    monkeypatch.setattr(model, "decode_step", lambda cache, token, step: logits_for(next(scripted)))
    tokens = model.generate_tokens(**infer, max_new_tokens=6)
    assert tokens.tolist() == [[eos, 9, eos, 0, 0, 0], [7, eos, eos, 0, 0, 0]]


def test_sampling_is_seeded_and_inputs_are_checked(fast_reference: FastReference) -> None:
    model = fast_reference.model()
    infer = fast_reference.inputs("infer")
    first, second = (
        model.generate_tokens(**infer, max_new_tokens=3, temperature=1.0, generator=torch.Generator().manual_seed(3))
        for _ in range(2)
    )
    assert torch.equal(first, second)
    with pytest.raises(ValueError, match="token_ar_mask must have shape"):
        model.generate_tokens(**{**infer, "token_ar_mask": infer["token_ar_mask"][:, :5]}, max_new_tokens=2)
    with pytest.raises(ValueError, match=r"pixel_values must lie in \[-1, 1\]"):
        model(**{**infer, "pixel_values": infer["pixel_values"] * 3})


def test_released_parameter_count() -> None:
    """openpi's gemma_2b (18 x 2048, mlp 16384, 8 heads of 256, 1 kv head, vocab 257152, LM head = embedding) +
    SigLIP So400m/14 (27 x 1152, mlp 4304) + its linear head to 2048."""
    with torch.device("meta"):
        model = PI0FastForActionGeneration(PI0FastConfig.from_preset("pi0_fast"))
    gemma_layer = 2048 * (8 * 256) + 2048 * (2 * 256) + (8 * 256) * 2048 + 3 * 2048 * 16_384 + 2 * 2048
    gemma = 257_152 * 2048 + 18 * gemma_layer + 2048
    siglip_layer = 4 * (1152 * 1152 + 1152) + 2 * 1152 * 4304 + 4304 + 1152 + 4 * 1152
    siglip = 14 * 14 * 3 * 1152 + 1152 + 256 * 1152 + 27 * siglip_layer + 2 * 1152 + 1152 * 2048 + 2048
    assert sum(p.numel() for p in model.parameters()) == gemma + siglip == 2_923_335_408


# ----------------------------------------------------------------------------------------------- processor


def atomic_tail_tokenizer(path: Path) -> Path:
    """A SentencePiece model like PaliGemma's (whitespace kept verbatim) whose ids 4..515 are atomic `<locNNNN>`
    pieces, as the ids PaliGemma gives FAST tokens are."""
    model = io.BytesIO()
    sentences = [f"Task: pick up the {c} block, State: {i} {i + 7};\nAction: |" for i, c in enumerate("abcdefghijklmnopqrst" * 8)]
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(sentences), model_writer=model, model_type="bpe", vocab_size=900, hard_vocab_limit=False,
        pad_id=0, eos_id=1, bos_id=2, unk_id=3, byte_fallback=True, split_digits=True, add_dummy_prefix=False,
        normalization_rule_name="identity", remove_extra_whitespaces=False, allow_whitespace_only_pieces=True,
        user_defined_symbols=[f"<loc{i:04d}>" for i in range(512)], num_threads=1, minloglevel=2,
    )
    path.write_bytes(model.getvalue())
    return path


def test_extract_actions_round_trips_through_the_prompt_text(tmp_path: Path, fast_reference: FastReference) -> None:
    """openpi's extract_actions: decode to text, cut between 'Action: ' and '|', encode again, map back to FAST ids."""
    tokenizer_path = atomic_tail_tokenizer(tmp_path / "tail.model")
    vocab = sentencepiece.SentencePieceProcessor(model_file=str(tokenizer_path)).get_piece_size()
    config = PI0FastConfig.from_preset("pi0_fast_small", fast_skip_tokens=vocab - 516)  # FAST ids -> ids 515..4
    processor = PI0FastProcessor.from_config(
        config, tokenizer_path, FAST_DIR / "fast_tokenizer", norm_mode="none", state_dim=8, action_dim_robot=8
    )
    actions = fast_reference["inputs/actions"]
    generated = []
    for row in range(2):
        tokens = processor.tokenize("pick up the block", fast_reference["inputs/state"][row], actions[row])
        postfix = tokens["input_ids"][tokens["token_ar_mask"]]  # what decoding emits, then zeros
        generated.append(np.pad(postfix, (0, 40 - len(postfix))))
    extracted = processor.extract_actions(np.stack(generated))
    np.testing.assert_array_equal(extracted, fast_reference["tokenizer/extracted_actions"])


def test_processor_inputs_save_and_reload(tmp_path: Path, fast_reference: FastReference) -> None:
    stats = {key: NormStats(mean=np.zeros(8), std=np.ones(8), q01=-2 * np.ones(8), q99=2 * np.ones(8)) for key in ("state", "actions")}
    processor = PI0FastProcessor.from_config(fast_reference.config, FAST_DIR / "tokenizer.model", FAST_DIR / "fast_tokenizer", stats)
    frame = np.zeros((120, 160, 3), np.uint8)
    state, actions = 2 * fast_reference["inputs/state"], 2 * fast_reference["inputs/actions"]  # quantile-normalized: / 2
    batch = processor(images={"base_0_rgb": [frame, frame], "wrist_0_rgb": [frame, None]}, prompt=list(fast_reference["tokenizer/prompts"]),
                      state=state, actions=actions)
    assert batch["pixel_values"].shape == (2, 3, 3, 224, 224)
    assert batch["image_masks"].all()  # openpi's π0-FAST transforms: absent cameras are black frames, not masked
    assert (batch["pixel_values"][1, 1:] == -1).all() and (batch["pixel_values"][0, 2] == -1).all()
    np.testing.assert_array_equal(batch["input_ids"].numpy(), fast_reference["inputs/train/tokens"])
    np.testing.assert_array_equal(batch["token_loss_mask"].numpy(), fast_reference["inputs/train/loss_mask"])
    processor.save_pretrained(tmp_path / "model")
    reloaded = PI0FastProcessor.from_pretrained(tmp_path / "model")
    inference = reloaded(images={"base_0_rgb": frame}, prompt=str(fast_reference["tokenizer/prompts"][0]), state=state[0])
    assert sorted(inference) == ["attention_mask", "image_masks", "input_ids", "pixel_values", "token_ar_mask"]
    np.testing.assert_array_equal(inference["input_ids"][0].numpy(), fast_reference["inputs/infer/tokens"][0])
    robot = reloaded.postprocess_actions(np.stack([fast_reference["tokenizer/extracted_actions"][0]]))
    np.testing.assert_allclose(robot[0], 2 * fast_reference["tokenizer/extracted_actions"][0], atol=1e-5)
    with pytest.raises(ValueError, match="prompt: empty"):
        processor(images={"base_0_rgb": frame}, prompt=" _ ", state=state[0])


def test_compiled_decoding_is_verified_against_eager_and_refused_when_it_differs(
    fast_reference: FastReference, caplog: pytest.LogCaptureFixture
) -> None:
    """After `compile_decoding`, the first `VERIFY_CALLS` calls also decode eagerly along the same tokens: a faithful
    compiled decoding stays on; one whose logits deviate (simulated: a step that scales them, as a broken CUDA graph
    would) is switched off with a warning, and that call returns the eager tokens."""
    model = fast_reference.model()
    infer = fast_reference.inputs("infer")
    expected = model.generate_tokens(**infer, max_new_tokens=4)
    model.compile_decoding(backend="eager")
    for _ in range(model.VERIFY_CALLS + 1):
        assert torch.equal(model.generate_tokens(**infer, max_new_tokens=4), expected)
    assert model.decoding_compiled and model._calls_to_verify == 0
    model.compile_decoding(backend="eager")
    compiled_step = model._compiled_decode_step
    model._compiled_decode_step = lambda *args: compiled_step(*args) * 3.0
    with caplog.at_level(logging.WARNING):
        tokens = model.generate_tokens(**infer, max_new_tokens=4)
    assert torch.equal(tokens, expected) and not model.decoding_compiled
    assert "compiled decoding was refused: its logits deviate from eager decoding by 2 of the largest" in caplog.text


def test_cuda_graph_decoding_is_refused_where_it_crashed(fast_reference: FastReference,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """On CUDA with torch < 2.12, `compile_decoding(mode="reduce-overhead")` crashed the process (SIGSEGV in
    inductor's CUDA-graph partition, torch 2.11 on an H200): it raises a `ValueError` naming that instead, compiling
    without CUDA graphs stays allowed, and elsewhere nothing is refused."""
    from torch.torch_version import TorchVersion

    model = fast_reference.model()
    assert model.decoding_graphs_reason() is None  # (the CPU)
    monkeypatch.setattr(type(model), "device", property(lambda self: torch.device("cuda")))
    monkeypatch.setattr(torch, "__version__", TorchVersion("2.11.0+cu130"))
    assert "crashes the process" in model.decoding_graphs_reason()
    with pytest.raises(ValueError, match=r"compile_decoding\(mode='reduce-overhead'\): .* crashes the process"):
        model.compile_decoding(mode="reduce-overhead")
    assert not model.decoding_compiled
    model.compile_decoding(backend="eager")
    assert model.decoding_compiled
    monkeypatch.setattr(torch, "__version__", TorchVersion("2.12.0+cu130"))
    assert model.decoding_graphs_reason() is None


def test_hand_captured_decoding_replays_eager_decoding_and_refuses_wrong_graphs(
    fast_reference: FastReference, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """`capture_decoding`: the prefill and the step of each input signature are recorded once; a call copies its
    inputs into the prefill's static inputs and replays it into the static cache, and every token replays the step
    on that cache (simulated here, as the CPU records nothing: `recorder.record` gives a "graph" whose replay runs the
    eager code again into the captured output, as a recorded graph rewrites the same memory). One capture serves two
    different observations with eager decoding's tokens; graphs whose first replays differ from the eager runs are
    refused with a warning naming the deviation, that call decodes eagerly, and the signature is not captured again.
    On the CPU `generate_tokens` itself stays eager."""
    model = fast_reference.model()
    infer = fast_reference.inputs("infer")
    swapped = {name: value.flip(0) for name, value in infer.items()}  # (other tokens per row)
    steps = 5
    expected = model.generate_tokens(**infer, max_new_tokens=steps)
    expected_swapped = model.generate_tokens(**swapped, max_new_tokens=steps)
    assert not torch.equal(expected, expected_swapped)

    class Replay:  # a "graph": its replay runs `run` again and writes the result where the capture run's went
        def __init__(self, run: Callable[[], torch.Tensor], output: torch.Tensor, scale: float) -> None:
            self.run, self.output, self.scale = run, output, scale

        def replay(self) -> None:
            self.output.copy_(self.run() * self.scale)

    recorded: list[float] = []

    def recording(scale: float) -> Callable[..., tuple[Replay, torch.Tensor, torch.Tensor]]:
        def record(run: Callable[[], torch.Tensor], *_: object) -> tuple[Replay, torch.Tensor, torch.Tensor]:
            recorded.append(scale)
            eager = run().clone()
            output = run()
            return Replay(run, output, scale), output, eager
        return record

    def decode(graphs: DecodingGraphs, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        with torch.no_grad():
            return model.decode(graphs.prepare, graphs.step, (*inputs.values(), steps, None), 0.0, None)[0]

    graphs = DecodingGraphs(model)
    monkeypatch.setattr(graphs.recorder, "record", recording(1.0))
    assert torch.equal(decode(graphs, infer), expected)
    assert torch.equal(decode(graphs, swapped), expected_swapped)  # (the second call's inputs copied in)
    assert recorded == [1.0, 1.0] and len(graphs.graphs) == 1 and not graphs.refused  # (a prefill and a step)
    captured = next(iter(graphs.graphs.values()))
    assert captured.cache.keys[0].shape[2] == model.decoding_slots(3, infer["input_ids"].shape[1], steps)

    wrong = DecodingGraphs(model)
    monkeypatch.setattr(wrong.recorder, "record", recording(3.0))
    with caplog.at_level(logging.WARNING):
        assert torch.equal(decode(wrong, infer), expected)
        assert torch.equal(decode(wrong, swapped), expected_swapped)
    assert recorded == [1.0, 1.0, 3.0, 3.0] and not wrong.graphs and len(wrong.refused) == 1
    assert caplog.text.count("were refused") == 1
    assert ("the CUDA graphs of π0-FAST's decoding (batch 2, 3 cameras, 96 prompt tokens, 5 new tokens) were refused: "
            "the prefill's first replay deviates from an eager run by 2 of the largest logit (bound 0.0001); it "
            "decodes eagerly from now on") in caplog.text

    model.capture_decoding()
    assert model.decoding_captured and torch.equal(model.generate_tokens(**infer, max_new_tokens=steps), expected)
    assert not model._decoding_graphs.graphs and not model._decoding_graphs.refused  # (the CPU: eager)
    model.compile_decoding(backend="eager", verify=False)  # one or the other
    assert model.decoding_compiled and not model.decoding_captured
    model.capture_decoding()
    assert model.decoding_captured and not model.decoding_compiled
    model._decoding_graphs.graphs["captured before"] = object()
    model.to(torch.bfloat16)  # (the graphs read the old tensors)
    assert model.decoding_captured and not model._decoding_graphs.graphs
    model.capture_decoding(disable=True)
    assert not model.decoding_captured


# ----------------------------------------------------------------------------------------------- decoding kernels

TRITON_REASON = ops.triton_reason(torch.device("cuda" if torch.cuda.is_available() else "cpu"))


@pytest.mark.skipif(TRITON_REASON is not None, reason=str(TRITON_REASON))
def test_fused_decoding_matches_openpi_and_the_modules(fast_reference: FastReference) -> None:
    """`decoding_kernels="triton"` (on the CPU in triton's interpreter): each decoded token's layers run the fused
    ops around the GEMMs, attention over its one range of slots with openpi's window (row 1 has a masked camera, whose
    tokens that window holds). Greedy decoding gives openpi's tokens; along the same (random) tokens the logits are the modules';
    compiled decoding traces the kernels as ops."""
    model = fast_reference.model()
    infer = fast_reference.inputs("infer")
    steps = int(fast_reference["inputs/max_decoding_steps"])
    model.decoding_kernels = "triton"
    assert model.decoding_kernels_reason(torch.device("cpu"), torch.float32) is None
    checks.decoding_ops_reason.cache_clear()
    tokens = model.generate_tokens(**infer, max_new_tokens=steps)
    cameras, text = infer["pixel_values"].shape[1], infer["input_ids"].shape[1]
    slots = model.decoding_slots(cameras, text, steps)  # (the call's own shapes were checked)
    assert checks.decoding_ops_reason.cache_info().currsize == 1
    assert checks.decoding_ops_reason(torch.device("cpu"), torch.float32, model.config.num_attention_heads,
                                                 model.config.head_dim, model.config.intermediate_size,
                                                 tokens.shape[0], slots) is None
    assert checks.decoding_ops_reason.cache_info().hits == 1
    with torch.no_grad():
        assert model.prepare_decoding(*infer.values(), steps)[0].keys[0].shape[2] == slots
    np.testing.assert_array_equal(tokens.numpy(), fast_reference["fp32/output_tokens"])

    count, layers = 5, model.config.num_hidden_layers
    arguments = (*infer.values(), count)
    forced = torch.randint(0, model.config.vocab_size, (tokens.shape[0], count), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        with AtenOpCounter() as counter:
            _, fused = model.decode(model.prepare_decoding, model.decode_step, (*arguments, decoder_sampling_weights(model.layers)),
                                    0.0, None, forced=forced)
        _, modules = model.decode(model.prepare_decoding, model.decode_step, (*arguments, None), 0.0, None, forced=forced)
    for op in ("rope_cache_write", "range_attention", "geglu"):
        assert counter.ops[op] == (count - 1) * layers, counter.ops
    assert counter.ops["addmm_"] == 2 * (count - 1) * layers and "_scaled_dot_product_attention_math" not in counter.ops
    for got, want in zip(fused, modules):
        assert relative_error(got, want) < 1e-5

    model.compile_decoding(backend="eager", verify=False)
    assert torch.equal(model.generate_tokens(**infer, max_new_tokens=3), tokens[:, :3])


def test_decoding_kernels_run_only_where_they_apply(monkeypatch: pytest.MonkeyPatch) -> None:
    """"auto" fuses only on CUDA in bf16 / fp16; "torch" never; "triton" refuses, naming why, a model it cannot run
    (grouped kv heads, LoRA), and so does building the fused layers for one; a kernel that differs from its reference
    on a device keeps decoding on the modules."""
    model = PI0FastForActionGeneration(PI0FastConfig.from_preset("pi0_fast_small")).eval()
    cpu = torch.device("cpu")
    assert "run on CUDA in bf16 / fp16" in model.decoding_kernels_reason(cpu, torch.float32)
    model.decoding_kernels = "torch"
    assert model.decoding_kernels_reason(cpu, torch.float32) == "decoding_kernels is 'torch'"
    with pytest.raises(ValueError, match=r"decoding_kernels must be one of \('auto', 'torch', 'triton'\), got 'cuda'"):
        model.decoding_kernels = "cuda"
    grouped = PI0FastForActionGeneration(PI0FastConfig.from_preset("pi0_fast_small", num_key_value_heads=2)).eval()
    grouped.decoding_kernels = "triton"
    with pytest.raises(ValueError, match="decoding_kernels='triton' cannot run: the fused attention folds the query heads onto one kv head"):
        grouped.decoding_kernels_reason(cpu, torch.float32)
    hooked = PI0FastForActionGeneration(PI0FastConfig.from_preset("pi0_fast_small")).eval()
    hooked.decoding_kernels = "triton"
    hooked.layers[1].block.o_proj.register_forward_hook(lambda module, args, output: output)
    with pytest.raises(ValueError, match="a layer's projections are not plain weights"):
        hooked.decoding_kernels_reason(cpu, torch.float32)
    buffers = [torch.zeros(1, 1, 8, hooked.config.head_dim) for _ in hooked.layers]  # (never read)
    with pytest.raises(ValueError, match="a layer's projections are not plain weights"):  # (no None weight at a token)
        fast_decoding.DecodingLayers.build(decoder_sampling_weights(hooked.layers), hooked.layers, buffers, buffers)
    if TRITON_REASON is not None:
        return
    from pi0_torch.kernels import triton_kernels

    checks.decoding_ops_reason.cache_clear()
    broken = triton_kernels.range_attention
    monkeypatch.setattr(triton_kernels, "range_attention", lambda *args: broken(*args) * 1.5)
    reason = checks.decoding_ops_reason(cpu, torch.float32, 2, 32, 128, 3, 600)
    assert reason.startswith("the fused kernel range_attention differs from its torch reference"), reason
    checks.decoding_ops_reason.cache_clear()
