"""CUDA checks: the openpi fixtures on the GPU, and the compiled sampling captured as a CUDA graph.

Marked `gpu`: skipped without CUDA and left out of `make test`; run them with `make test-gpu` on a GPU machine.
"""

from __future__ import annotations

import pytest
import torch

from conftest import OpenpiReference, relative_error
from test_parity import BF16_TOLERANCE

pytestmark = pytest.mark.gpu
CUDA = torch.device("cuda")


@pytest.fixture(autouse=True)
def exact_cuda_float32():
    """No TF32 (cuDNN allows it by default for SigLIP's patch convolution): float32 means float32."""
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


def on_cuda(ref: OpenpiReference, dtype: torch.dtype) -> tuple[torch.nn.Module, dict[str, torch.Tensor], torch.Tensor]:
    inputs = {name: value.to(CUDA) for name, value in ref.model_inputs().items()}
    return ref.model(dtype).to(CUDA), inputs, ref.tensor("inputs/sample_noise").to(CUDA)


@torch.no_grad()
def test_float32_actions_and_loss_match_openpi_on_cuda(reference: OpenpiReference) -> None:
    model, inputs, noise = on_cuda(reference, torch.float32)
    actions = model.generate_actions(**inputs, noise=noise)
    time, loss_noise, target = (reference.tensor(k).to(CUDA) for k in ("inputs/loss_time", "inputs/loss_noise", "inputs/actions"))
    velocity = model(**inputs, actions=target, noise=loss_noise, time=time).velocity
    assert relative_error(actions, reference["fp32/actions"]) <= 1e-4
    assert relative_error(velocity, reference["fp32/loss_path/v_t"]) <= 1e-4


@torch.no_grad()
def test_bf16_actions_match_openpi_bf16_on_cuda(reference: OpenpiReference) -> None:
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    actions = model.generate_actions(**inputs, noise=noise)
    assert actions.dtype == torch.float32
    assert relative_error(actions, reference["bf16_infer/actions"]) <= BF16_TOLERANCE


@torch.no_grad()
def test_cuda_graph_sampling_matches_eager_and_keeps_earlier_outputs(reference: OpenpiReference) -> None:
    """`compile_sampling(mode="reduce-overhead")`: the whole sampling replayed as one CUDA graph."""
    model, inputs, noise = on_cuda(reference, torch.float32)
    eager = [model.generate_actions(**inputs, noise=noise * scale) for scale in (1.0, 0.5)]
    model.compile_sampling(mode="reduce-overhead")
    replays = [model.generate_actions(**inputs, noise=noise * scale) for scale in (1.0, 0.5, 1.0, 0.5)]
    for got, want in zip(replays, eager + eager):  # every earlier output survived the later replays
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)
