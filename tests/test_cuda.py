"""CUDA checks: the openpi fixtures on the GPU, the sampling as hand-captured CUDA graphs (with and without compiled
layers), FlashAttention's varlen kernel against SDPA, and π0-FAST's decoding with the fused kernels.

Marked `gpu`: skipped without CUDA and left out of `make test`; run them with `make test-gpu` on a GPU machine.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from conftest import OpenpiReference, relative_error, tiny_policy
from test_parity import BF16_TOLERANCE
from test_pi0_fast import FastReference

from pi0_torch.runtime.policy import PI0Policy

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


def relative(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got - want).abs().max() / want.abs().max())


@pytest.mark.parametrize("dtype, tolerance", [(torch.float32, 1e-5), (torch.bfloat16, 2e-2)])
def test_cuda_graph_sampling_matches_eager_and_keeps_earlier_outputs(reference: OpenpiReference, dtype: torch.dtype, tolerance: float) -> None:
    """`capture_sampling`: the sampling replayed as one hand-captured CUDA graph gives eager's actions (to bf16
    rounding: the graph's prefix slots are bucketed), and every output survives later replays."""
    model, inputs, noise = on_cuda(reference, dtype)
    eager = [model.generate_actions(**inputs, noise=noise * scale) for scale in (1.0, 0.5)]
    model.capture_sampling()
    replays = [model.generate_actions(**inputs, noise=noise * scale) for scale in (1.0, 0.5, 1.0, 0.5)]
    assert len(model._graphs.graphs) == 1
    for got, want in zip(replays, eager + eager):
        assert relative(got, want) <= tolerance
    if dtype == torch.bfloat16:
        assert relative_error(replays[0], reference["bf16_infer/actions"]) <= BF16_TOLERANCE


def test_cuda_graph_captures_both_real_time_chunking_methods(reference: OpenpiReference) -> None:
    """Real-time chunking: "conditioning" replays a graph of its own, which another previous chunk replays too;
    "guidance" samples eagerly by default. `capture_sampling(guidance=True)` tries its graph: verified at capture, it
    either replays eager's actions or is refused (a warning) and samples eagerly. Either way the actions are eager's;
    the test prints which happened on this GPU."""
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    model.config = copy.deepcopy(model.config)  # (the fixture's config is shared)
    model.config.rtc_max_delay = 4
    previous = [torch.randn_like(noise), torch.randn_like(noise)]
    rtc = dict(noise=noise, inference_delay=3, execution_horizon=5)
    eager = {(method, index): model.generate_actions(**inputs, **rtc, previous_actions=chunk, rtc_method=method)
             for method in ("conditioning", "guidance") for index, chunk in enumerate(previous)}
    model.capture_sampling()
    for index, chunk in enumerate(previous):
        conditioned = model.generate_actions(**inputs, **rtc, previous_actions=chunk, rtc_method="conditioning")
        assert relative(conditioned, eager["conditioning", index]) <= 2e-2
        torch.testing.assert_close(conditioned[:, :3], chunk[:, 5:8])  # the committed actions, unchanged
        guided = model.generate_actions(**inputs, **rtc, previous_actions=chunk, rtc_method="guidance")
        assert relative(guided, eager["guidance", index]) <= 2e-2
    assert len(model._graphs.graphs) == 1 and not model.replays_graphs("guidance")
    model.capture_sampling(guidance=True)
    for index, chunk in enumerate(previous):
        guided = model.generate_actions(**inputs, **rtc, previous_actions=chunk, rtc_method="guidance")
        assert relative(guided, eager["guidance", index]) <= 2e-2
    graphs = model._graphs
    print(f"\nguidance graph on {torch.cuda.get_device_name()}: "
          + (f"refused ({next(iter(graphs.refused.values()))})" if graphs.refused else f"kept ({len(graphs.graphs)} graph)"))


def test_a_refused_guidance_capture_leaves_cuda_usable(reference: OpenpiReference, monkeypatch: pytest.MonkeyPatch) -> None:
    """A capture CUDA really refuses (a host read forced into guided sampling while it records), after a plain graph
    was captured: that chunk samples eagerly, the caller's stream is current again, the plain graph still replays,
    and a new plain graph is captured (the refused capture's pool was the guided graphs' own, and is not used again)
    after `empty_cache`."""
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    rtc = dict(noise=noise, previous_actions=torch.randn_like(noise), inference_delay=3, execution_horizon=5, rtc_method="guidance")
    eager = model.generate_actions(**inputs, **rtc)
    eager_plain = model.generate_actions(**inputs, noise=noise)
    model.capture_sampling(guidance=True)
    model.generate_actions(**inputs, noise=noise)  # the plain graph, captured before the refusal
    sample = model._sample

    def reads_the_host_while_recording(sampling_inputs, plan):
        if torch.cuda.is_current_stream_capturing():
            sampling_inputs.noise.sum().item()  # not allowed while a stream records
        return sample(sampling_inputs, plan)

    monkeypatch.setattr(model, "_sample", reads_the_host_while_recording)
    stream = torch.cuda.current_stream()
    guided = model.generate_actions(**inputs, **rtc)
    assert relative(guided, eager) <= 2e-2 and not model.replays_graphs("guidance")
    assert torch.cuda.current_stream() == stream
    monkeypatch.undo()
    torch.cuda.empty_cache()
    assert relative(model.generate_actions(**inputs, noise=noise), eager_plain) <= 2e-2
    two_steps = model.generate_actions(**inputs, noise=noise, num_steps=2)  # a new plain graph
    assert len(model._graphs.graphs) == 2 and torch.isfinite(two_steps).all()


@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs two GPUs")
def test_a_model_on_another_gpu_than_the_current_one_captures_its_own_kernels(reference: OpenpiReference) -> None:
    """A model on cuda:1, captured while cuda:0 is current and after a capture there: its graph holds its kernels
    (torch's default capture stream is made once, on whichever GPU was current: a capture on it would record nothing
    and replay the capture's actions for any noise)."""
    first, inputs, noise = on_cuda(reference, torch.bfloat16)
    first.capture_sampling()
    first.generate_actions(**inputs, noise=noise)
    second = torch.device("cuda:1")
    model = reference.model(torch.bfloat16).to(second)
    inputs = {name: value.to(second) for name, value in inputs.items()}
    noises = [noise.to(second) * scale for scale in (1.0, 0.5)]
    eager = [model.generate_actions(**inputs, noise=each) for each in noises]
    model.capture_sampling()
    replays = [model.generate_actions(**inputs, noise=each) for each in noises + noises]
    for got, want in zip(replays, eager + eager):
        assert got.device == second and relative(got, want) <= 2e-2


@pytest.mark.parametrize("rtc_max_delay", [0, 3])  # the policy's method: guidance, conditioning
def test_a_captured_policy_warms_up_its_real_time_chunking_graph(rtc_max_delay: int) -> None:
    """`warmup` (in inference mode, as a server runs it) captures a plain and a continued chunk's graph (guidance:
    the plain one; guided chunks sample eagerly); a continued request then replays it (no capture while the robot
    waits), and the model still replays outside inference mode."""
    cpu = tiny_policy(rtc_max_delay=rtc_max_delay)
    policy = PI0Policy(cpu.model.to(CUDA), cpu.processor, num_steps=2, seed=0, cuda_graph=True)
    policy.warmup(1)
    graphs = 2 if rtc_max_delay else 1
    assert len(policy.model._graphs.graphs) == graphs
    frame = np.zeros((32, 32, 3), np.uint8)  # every camera, as the warm-up's layout (one left out: a graph of its own)
    observation = {"images": {"base_0_rgb": frame, "left_wrist_0_rgb": frame}, "state": np.ones(3), "prompt": "reach"}
    first = policy.infer(observation)["actions"]
    continued = policy.infer({**observation, "previous_actions": first, "inference_delay": 1, "execution_horizon": 2})
    assert np.isfinite(continued["actions"]).all() and len(policy.model._graphs.graphs) == graphs
    inputs = {name: tensor.to(CUDA) for name, tensor in policy.prepare(observation).inputs.items()}
    noise = torch.zeros(1, policy.model.config.action_horizon, policy.model.config.action_dim, device=CUDA)
    direct = policy.model.generate_actions(**inputs, noise=noise, num_steps=2)  # (the buffers were made in inference mode)
    assert len(policy.model._graphs.graphs) == graphs and torch.isfinite(direct).all() and not direct.is_inference()


def test_bad_inputs_after_capture_raise_named_errors(reference: OpenpiReference) -> None:
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    model.capture_sampling(batch_sizes=[2])
    model.generate_actions(**inputs, noise=noise)
    with pytest.raises(ValueError, match=r"pixel_values must have shape"):
        model.generate_actions(**dict(inputs, pixel_values=inputs["pixel_values"][:, :2]), noise=noise)
    with pytest.raises(ValueError, match=r"batch size 1: sampling is captured for batch sizes \[2\] only"):
        model.generate_actions(**{k: v[:1] for k, v in inputs.items()}, noise=noise[:1])


def test_moving_the_model_captures_again(reference: OpenpiReference) -> None:
    model, inputs, noise = on_cuda(reference, torch.float32)
    model.capture_sampling()
    model.generate_actions(**inputs, noise=noise)
    model.to(torch.bfloat16)
    assert not model._graphs.graphs
    replay = model.generate_actions(**inputs, noise=noise)
    model.capture_sampling(disable=True)
    assert relative(replay, model.generate_actions(**inputs, noise=noise)) <= 2e-2


def test_varlen_kernel_matches_sdpa(reference: OpenpiReference) -> None:
    """FlashAttention's varlen kernel (per-sample key ranges, no mask) against SDPA with the additive mask."""
    from pi0_torch.inference.attention import VARLEN_AVAILABLE

    if not VARLEN_AVAILABLE or torch.cuda.get_device_capability() < (8, 0):
        pytest.skip("no varlen_attn with seqused_k in this torch, or a GPU older than sm80")
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    model.attention_kernel = "sdpa"
    sdpa = model.generate_actions(**inputs, noise=noise)
    model.attention_kernel = "varlen"
    varlen = model.generate_actions(**inputs, noise=noise)
    assert relative(varlen, sdpa) <= 2e-2
    assert relative_error(varlen, reference["bf16_infer/actions"]) <= BF16_TOLERANCE
    loss = model(**inputs, actions=varlen).loss  # (training passes use SDPA: the varlen kernel has no backward here)
    assert torch.isfinite(loss)


@torch.no_grad()
@pytest.mark.parametrize("preset", ["pi0", "pi05"])
@pytest.mark.parametrize("setting", ["auto", "persistent"])
def test_fused_steps_hold_at_full_width_for_every_batch_class(preset: str, setting: str) -> None:
    """Full-size widths (two decoder layers, random weights), bf16, "auto" and "persistent": at batch 1 (one-row state token, key
    parts), 3 (64-row attention blocks) and 8 (row counts divisible by 16; 400 rows: the GEMM ops run cuBLAS's GEMM
    with the epilogue kernels, `CUBLAS_ROWS`) each call's first-use verification keeps the fused steps, and they give
    the unfused path's actions within bf16's bound. Eagerly "auto" runs each step's layers in one persistent launch at
    batch 1, five launches per layer at 3 and 8 (`runs_persistent`). "persistent" also replays its CUDA graph alike
    twice, near what it samples eagerly (the graph's prefix slots are bucketed: another rounding)."""
    from pi0_torch import PI0Config, PI0ForActionGeneration
    from pi0_torch.benchmark import example_batch
    from pi0_torch.inference.sampling import SamplingRoute

    torch.manual_seed(0)
    config = PI0Config.from_preset(preset, num_hidden_layers=2, vision_num_layers=2)
    with CUDA:
        model = PI0ForActionGeneration(config).to(torch.bfloat16).eval()
    for batch in (1, 3, 8):
        inputs = example_batch(config, 3, batch, CUDA, seed=batch)
        if config.pi05:
            inputs.pop("state")
        noise = torch.randn(batch, config.action_horizon, config.action_dim, device=CUDA)
        model.sampling_kernels = setting
        fused = model.generate_actions(**inputs, noise=noise)
        assert list(model._fused_refusals.values()) == [None], model._fused_refusals
        persistent = setting == "persistent" or batch <= model.PERSISTENT_EAGER_BATCH
        assert [plan.persistent for plan, _ in model._fused_refusals] == [persistent]
        assert model.last_sampling_route == SamplingRoute("persistent" if persistent else "triton", graph=False)
        if setting == "persistent":
            model.capture_sampling()
            replayed = [model.generate_actions(**inputs, noise=noise) for _ in range(2)]
            assert model.last_sampling_route == SamplingRoute("persistent", graph=True)
            model.capture_sampling(disable=True)
            print(f"{preset} batch {batch}: persistent graph against eager {relative(replayed[1], fused):.2e}")
            assert relative(replayed[1], replayed[0]) <= 1e-3 and relative(replayed[1], fused) <= 2e-2
        model.sampling_kernels = "torch"
        unfused = model.generate_actions(**inputs, noise=noise)
        print(f"{preset} batch {batch} {setting}: fused against unfused {relative(fused, unfused):.2e}")
        assert relative(fused, unfused) <= 3e-2


@torch.no_grad()
def test_auto_leaves_the_persistent_launch_once_one_gave_up_a_wait_on_this_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """Under "auto" an eager chunk of one sample takes the persistent launch. A launch that gives up its waits (the
    watchdog set, as the kernel sets it after `SPINS` spins) returns NaN: that chunk is lost. The next chunk reads the
    watchdog and samples with five launches per decoder layer, verified on its first call, and is fine again."""
    from pi0_torch import PI0Config, PI0ForActionGeneration
    from pi0_torch.benchmark import example_batch
    from pi0_torch.inference import checks
    from pi0_torch.inference.sampling import SamplingRoute
    from pi0_torch.kernels import persistent

    monkeypatch.setattr(persistent, "_watches", {})  # (this test's watchdog, not the process's)
    monkeypatch.setattr(checks, "_AVOIDED", set())
    torch.manual_seed(0)
    config = PI0Config.from_preset("pi0", num_hidden_layers=2, vision_num_layers=2)
    with CUDA:
        model = PI0ForActionGeneration(config).to(torch.bfloat16).eval()
    inputs = example_batch(config, 3, 1, CUDA)
    noise = torch.randn(1, config.action_horizon, config.action_dim, device=CUDA)
    first = model.generate_actions(**inputs, noise=noise)
    assert model.last_sampling_route == SamplingRoute("persistent", graph=False)
    launch = persistent.expert_layers_

    def gives_up(x: torch.Tensor, *args, **options) -> None:  # (a fault: every wait of this launch is given up)
        persistent.watchdog(x.device)[0] = 1
        launch(x, *args, **options)

    monkeypatch.setattr(persistent, "expert_layers_", gives_up)
    assert not bool(torch.isfinite(model.generate_actions(**inputs, noise=noise)).all())  # (the chunk it happened in)
    monkeypatch.setattr(persistent, "expert_layers_", launch)
    after = [model.generate_actions(**inputs, noise=noise) for _ in range(2)]
    assert model.last_sampling_route == SamplingRoute("triton", graph=False)
    assert all(bool(torch.isfinite(chunk).all()) and relative(chunk, first) <= 2e-2 for chunk in after)


@torch.no_grad()
def test_direct_launches_sample_what_tritons_own_launches_sample() -> None:
    """The fused kernels launched directly (`pi0_torch.kernels.launch`: every launch of a class after its first) give
    bit for bit the actions that triton's own launches give: full width, two layers, bf16, batch 1 (key parts,
    split-K) and 8 (64-row attention blocks, cuBLAS's GEMMs with the epilogue kernels)."""
    from pi0_torch import PI0Config, PI0ForActionGeneration
    from pi0_torch.benchmark import example_batch
    from pi0_torch.kernels import launch, triton_kernels  # noqa: F401  (the kernels, decorated)

    if launch.DIRECT_REASON is not None:
        pytest.skip(launch.DIRECT_REASON)
    torch.manual_seed(0)
    config = PI0Config.from_preset("pi0", num_hidden_layers=2, vision_num_layers=2)
    with CUDA:
        model = PI0ForActionGeneration(config).to(torch.bfloat16).eval()
    model.sampling_kernels = "triton"
    for batch in (1, 8):
        inputs = example_batch(config, 3, batch, CUDA, seed=batch)
        noise = torch.randn(batch, config.action_horizon, config.action_dim, device=CUDA)
        direct = [model.generate_actions(**inputs, noise=noise) for _ in range(2)]
        with launch.through_triton():
            through_triton = model.generate_actions(**inputs, noise=noise)
        assert sum(len(launcher.launches) for launcher in launch.LAUNCHERS) >= 5, "no kernel launched directly"
        assert torch.equal(direct[0], direct[1]), f"batch {batch}: two direct chunks differ"
        assert torch.equal(direct[1], through_triton), f"batch {batch}: {relative(direct[1], through_triton):.2e}"


@torch.no_grad()
@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs two GPUs")
def test_fused_kernels_run_on_the_models_gpu_whichever_is_current() -> None:
    """Triton launches on the current GPU: eager fused sampling (its first-use verification and self-check included)
    of a model on cuda:1 while cuda:0 is current gives, bit for bit, the actions the same model gives with cuda:1
    current."""
    from pi0_torch import PI0Config, PI0ForActionGeneration
    from pi0_torch.benchmark import example_batch

    torch.manual_seed(0)
    second = torch.device("cuda:1")
    config = PI0Config.from_preset("pi0", num_hidden_layers=2, vision_num_layers=2)
    model = PI0ForActionGeneration(config).to(torch.bfloat16).eval()
    twin = copy.deepcopy(model).to(second)
    model.to(second)
    inputs = example_batch(config, 3, 1, second, seed=1)
    noise = torch.randn(1, config.action_horizon, config.action_dim, device=second)
    with torch.cuda.device(0):
        elsewhere = [model.generate_actions(**inputs, noise=noise) for _ in range(2)]  # (verified, then fused alone)
    with torch.cuda.device(1):
        own = [twin.generate_actions(**inputs, noise=noise) for _ in range(2)]
    assert list(model._fused_refusals.values()) == [None], model._fused_refusals
    assert all(each.device == second for each in elsewhere)
    assert all(torch.equal(got, want) for got, want in zip(elsewhere, own))


def test_compiled_sampling_replays_as_one_graph(reference: OpenpiReference) -> None:
    """`compile_sampling(mode="reduce-overhead")`: compiled layers inside the hand-captured graph."""
    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    eager = model.generate_actions(**inputs, noise=noise)
    model.compile_sampling(mode="reduce-overhead")
    assert model.sampling_compiled and model.sampling_captured
    for _ in range(2):
        assert relative(model.generate_actions(**inputs, noise=noise), eager) <= 2e-2


def test_bench_counts_the_gpu_work_of_a_call(reference: OpenpiReference) -> None:
    """`pi0-torch bench` on CUDA adds each row's GPU work (activities and GPU time, by the profiler) and the host's
    side of it (time to the last launch, waits before it). A graph replay runs the eager call's kernels (plus its
    input copies) and no more; the numbers are printed for the notes."""
    from pi0_torch.benchmark import gpu_work

    model, inputs, noise = on_cuda(reference, torch.bfloat16)
    eager = gpu_work(lambda: model.generate_actions(**inputs, noise=noise), CUDA)
    model.capture_sampling()
    model.generate_actions(**inputs, noise=noise)  # (captured here)
    graph = gpu_work(lambda: model.generate_actions(**inputs, noise=noise), CUDA)
    for name, work in (("eager", eager), ("graph", graph)):
        assert work.issue_seconds is not None, f"no launch among the host's events of the {name} call"
        print(f"GPU work of one {name} call: {work.activities} activities, {work.gpu_seconds * 1e3:.2f} GPU ms; host "
              f"{work.issue_seconds * 1e3:.2f} ms to its last launch, {work.wait_seconds * 1e3:.2f} ms of it waiting")
        assert work.activities > 0 and work.gpu_seconds > 0
        assert 0 <= work.wait_seconds < work.issue_seconds  # (the launches were found among the host's events)
    assert sum(count for _, count, _ in eager.table) == eager.activities
    assert graph.activities <= eager.activities + 16


@torch.no_grad()
def test_fused_fast_decoding_on_cuda() -> None:
    """π0-FAST on CUDA: float32 greedy decoding gives openpi's tokens; in bf16 "auto" decodes with the fused kernels
    (`pi0_torch.inference.fast_decoding`), whose logits along the same tokens are the modules' to bf16 rounding;
    `capture_decoding` replays them as one hand-captured graph per step (one capture for every call), with eager's
    logits; compiled decoding replayed as CUDA graphs passes its verification against eager decoding (refused, with
    the reason, on torch < 2.12, where it crashed the process on an H200)."""
    from pi0_torch.inference.layer_pass import decoder_sampling_weights

    fast = FastReference()
    infer = {name: value.to(CUDA) for name, value in fast.inputs("infer").items()}
    steps = int(fast["inputs/max_decoding_steps"])
    model = fast.model().to(CUDA)
    np.testing.assert_array_equal(model.generate_tokens(**infer, max_new_tokens=steps).cpu().numpy(), fast["fp32/output_tokens"])
    model = model.to(torch.bfloat16)
    assert model.decoding_kernels_reason(CUDA, torch.bfloat16) is None
    tokens = model.generate_tokens(**infer, max_new_tokens=steps)
    arguments, weights = (*infer.values(), steps), decoder_sampling_weights(model.layers)
    _, fused = model.decode(model.prepare_decoding, model.decode_step, (*arguments, weights), 0.0, None, forced=tokens)
    _, modules = model.decode(model.prepare_decoding, model.decode_step, (*arguments, None), 0.0, None, forced=tokens)
    assert max(relative(got.float(), want.float()) for got, want in zip(fused, modules)) <= 2e-2
    model.capture_decoding()  # hand-captured graphs of the fused step, verified at capture
    graphs = model._decoding_graphs
    for _ in range(2):
        _, replayed = model.decode(graphs.prepare, graphs.step, (*arguments, weights), 0.0, None, forced=tokens)
        assert max(relative(got.float(), want.float()) for got, want in zip(replayed, fused)) <= 1e-2
    assert len(graphs.graphs) == 1 and not graphs.refused
    model.generate_tokens(**infer, max_new_tokens=steps)
    assert len(graphs.graphs) == 1 and not graphs.refused
    model.capture_decoding(disable=True)
    reason = model.decoding_graphs_reason()
    if reason is not None:  # (torch < 2.12: inductor's CUDA-graph partition of the step crashes the process)
        with pytest.raises(ValueError, match="crashes the process"):
            model.compile_decoding(mode="reduce-overhead")
        assert not model.decoding_compiled
        return
    model.compile_decoding(mode="reduce-overhead")
    for _ in range(model.VERIFY_CALLS + 1):
        model.generate_tokens(**infer, max_new_tokens=steps)
    assert model.decoding_compiled
