"""The fused kernels of a sampling step (`pi0_torch.kernels`) against their torch references, and the engine's fused
steps against its unfused ones and the plain reference loop.

On a machine without CUDA the Triton kernels run in triton's interpreter (conftest sets `TRITON_INTERPRET=1`), with
float32 dot operands (its bf16 `tl.dot` is wrong; loads, stores and casts in bf16 are right). Skipped, with the
reason, only where triton cannot be imported.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import OpenpiReference, relative_error

from pi0_torch import PI0Config, PI0ForActionGeneration
from pi0_torch.benchmark import sample_on_meta
from pi0_torch.inference import checks, fused_pass, vision_pass
from pi0_torch.inference.layout import InputFacts
from pi0_torch.inference.plan import SamplingRoute
from pi0_torch.kernels import ops, reference
from pi0_torch.kernels.reference import rope_cos_sin
from pi0_torch.utils.op_count import AtenOpCounter

TRITON_REASON = ops.triton_reason(torch.device("cuda" if torch.cuda.is_available() else "cpu"))
pytestmark = pytest.mark.skipif(TRITON_REASON is not None, reason=str(TRITON_REASON))
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")
TOLERANCE = {torch.float32: 2e-6, torch.bfloat16: 2e-2}

# (width, heads, head_dim, mlp_width, action_dim): π0-like and π0.5-like small sizes, and odd ones (no block divides)
SIZES = {"small": (64, 2, 16, 128, 32), "odd": (48, 3, 32, 72, 7)}


def relative(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got.float() - want.float()).abs().max() / want.float().abs().max())


def kernels():
    from pi0_torch.kernels import triton_kernels

    return triton_kernels


def random(generator: torch.Generator, dtype: torch.dtype, *shape: int, scale: float = 1.0) -> torch.Tensor:
    return (torch.randn(*shape, generator=generator) * scale).to(device=DEVICE, dtype=dtype)


def compare(name: str, arguments: tuple, dtype: torch.dtype) -> None:
    """The Triton kernel and the reference on copies of `arguments`: the result and every tensor written agree."""
    theirs = tuple(a.clone() if isinstance(a, torch.Tensor) else a for a in arguments)
    ours = getattr(kernels(), name)(*arguments)
    expected = getattr(reference, name)(*theirs)
    if expected is not None:
        assert relative(ours, expected) <= TOLERANCE[dtype], name
    for mine, other in zip(arguments, theirs):  # (NaN where an input holds it: unwritten cache slots)
        if isinstance(mine, torch.Tensor) and not torch.equal(mine.nan_to_num(), other.nan_to_num()):
            assert torch.equal(mine.isnan(), other.isnan()), name
            assert relative(mine.nan_to_num(), other.nan_to_num()) <= TOLERANCE[dtype], name


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("sizes", SIZES)
@pytest.mark.parametrize("batch, tokens", [(1, 5), (3, 17)])
def test_each_kernel_equals_its_reference(dtype: torch.dtype, sizes: str, batch: int, tokens: int) -> None:
    width, heads, head_dim, mlp_width, action_dim = SIZES[sizes]
    generator = torch.Generator().manual_seed(batch * 100 + tokens)
    rows, slots = batch * tokens, tokens + 23
    x, scale = random(generator, dtype, rows, width), 1 + random(generator, dtype, width, scale=0.1)
    first = torch.randint(0, 20, (batch,), generator=generator).to(DEVICE)
    positions = torch.arange(tokens, device=DEVICE)[None] + first[:, None] + 3
    cos, sin = rope_cos_sin(positions, head_dim, 10_000.0)  # [B, T, H]: per-sample positions
    qkv_columns = (heads + 2) * head_dim
    for bias in (None, random(generator, dtype, qkv_columns)):  # π0, π0.5 (adaRMS shift through the projection)
        compare("norm_qkv_rope", (x, scale, bias, random(generator, dtype, qkv_columns, width, scale=width**-0.5).t(), cos, sin,
                                  torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE),
                                  torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE), slots - tokens, 1e-6), dtype)
    compare("norm_qkv_rope", (x, scale, None, random(generator, dtype, qkv_columns, width).t(), cos[:1], sin[:1],
                              random(generator, dtype, batch, slots, head_dim), random(generator, dtype, batch, slots, head_dim),
                              0, 1e-6), dtype)  # one RoPE table for every sample, the cache's first slots
    compare("rope_cache_write", (random(generator, dtype, rows, qkv_columns), cos, sin,
                                 torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE),
                                 torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE), 2), dtype)
    compare("rope_cache_write", (random(generator, dtype, rows, qkv_columns), cos, sin,
                                 random(generator, dtype, batch, slots, head_dim), random(generator, dtype, batch, slots, head_dim),
                                 0, torch.tensor([slots - tokens - 1], device=DEVICE)), dtype)  # the slot on the device (π0-FAST)
    compare("geglu", (random(generator, dtype, rows, 2 * mlp_width),), dtype)
    for bias in (None, random(generator, dtype, 2 * mlp_width)):
        compare("norm_gate_up_geglu", (x, scale, bias, random(generator, dtype, 2 * mlp_width, width, scale=width**-0.5).t(), 1e-6), dtype)
    for gate in (None, random(generator, dtype, width)):
        compare("matmul_residual_", (x.clone(), random(generator, dtype, rows, mlp_width),
                                     random(generator, dtype, width, mlp_width, scale=mlp_width**-0.5).t(), gate), dtype)
    keys, values = random(generator, dtype, batch, slots, head_dim), random(generator, dtype, batch, slots, head_dim)
    query = random(generator, dtype, batch, tokens, heads, head_dim)
    compare("range_attention", (query, keys, values, first, torch.full((tokens,), slots, device=DEVICE)), dtype)
    ends = torch.cat([torch.full((1,), slots - tokens + 1), torch.full((tokens - 1,), slots)]).to(DEVICE)  # π0's state row
    compare("range_attention", (query, keys, values, first, ends), dtype)
    unwritten = slots - tokens + 2  # (the slots from here on hold NaN: not yet written, as the action slots while π0's state runs)
    keys[:, unwritten:], values[:, unwritten:] = float("nan"), float("nan")
    compare("range_attention", (query[:, :1], keys, values, first, ends[:1]), dtype)
    long_keys, long_values = random(generator, dtype, batch, 600, head_dim), random(generator, dtype, batch, 600, head_dim)
    long_keys[:, 450:], long_values[:, 450:] = float("nan"), float("nan")
    assert kernels().key_splits(1, batch, 600) == 4  # one row of folded heads over a long cache: the keys in parts
    compare("range_attention", (query[:, :1], long_keys, long_values, first, torch.tensor([450], device=DEVICE)), dtype)
    assert not any(counters.any() for counters in kernels()._counters.values())  # (its last program put them back to 0)
    compare("norm_linear_euler_", (torch.randn(batch, tokens, action_dim, generator=generator).to(DEVICE), x, scale,
                                   random(generator, dtype, action_dim), random(generator, dtype, action_dim, width).t(), -0.1, 1e-6), dtype)
    x_t = torch.randn(batch, tokens, action_dim, generator=generator).to(DEVICE)
    compare("embed_actions", (x_t, random(generator, dtype, width, action_dim, scale=action_dim**-0.5).t(),
                              random(generator, dtype, width), None, None), dtype)  # π0.5: action_in_proj
    compare("embed_actions", (x_t, random(generator, dtype, width, action_dim, scale=action_dim**-0.5).t(), random(generator, dtype, width),
                              random(generator, dtype, mlp_width, width, scale=width**-0.5).t(), random(generator, dtype, mlp_width)),
            dtype)  # π0: with the time MLP (its widths differ here, to catch a swapped one)
    compare("add_layer_norm_", (x.clone(), random(generator, dtype, rows, width), 1 + random(generator, dtype, width, scale=0.1),
                                random(generator, dtype, width, scale=0.1), 1e-6), dtype)


def compare_gemm_ops(dtype: torch.dtype, sizes: str, seed: int) -> None:
    """The three GEMM ops (q/k/v + RoPE, gate/up + GeGLU, o / down + residual; with and without π0.5's bias and gate)
    against their references, at 18 rows (2 samples of 9 tokens)."""
    width, heads, head_dim, mlp_width, _ = SIZES[sizes]
    batch, tokens = 2, 9
    generator = torch.Generator().manual_seed(seed)
    rows, slots = batch * tokens, tokens + 4
    x, scale = random(generator, dtype, rows, width), 1 + random(generator, dtype, width, scale=0.1)
    cos, sin = rope_cos_sin(torch.arange(tokens, device=DEVICE)[None] + 2, head_dim, 10_000.0)
    for bias in (None, random(generator, dtype, (heads + 2) * head_dim)):
        compare("norm_qkv_rope", (x, scale, bias, random(generator, dtype, (heads + 2) * head_dim, width).t(), cos, sin,
                                  torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE),
                                  torch.zeros(batch, slots, head_dim, dtype=dtype, device=DEVICE), 4, 1e-6), dtype)
        compare("norm_gate_up_geglu", (x, scale, None if bias is None else random(generator, dtype, 2 * mlp_width),
                                       random(generator, dtype, 2 * mlp_width, width, scale=width**-0.5).t(), 1e-6), dtype)
    for gate in (None, random(generator, dtype, width)):
        compare("matmul_residual_", (x.clone(), random(generator, dtype, rows, mlp_width),
                                     random(generator, dtype, width, mlp_width, scale=mlp_width**-0.5).t(), gate), dtype)


@pytest.mark.parametrize("dtype, sizes, splits", [(torch.float32, "small", 2), (torch.float32, "odd", 3),
                                                  (torch.bfloat16, "odd", 4)])
def test_split_k_gemms_equal_their_references(dtype: torch.dtype, sizes: str, splits: int,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The GEMM kernels with their reduction cut into `splits` parts (16 columns deep blocks, so that 48 to 128
    columns make 3 to 8 of them; some parts empty where they do not divide), summed by the program that arrives
    last: the same results as the references, launch after launch on the same arrival counters (each launch leaves
    them at 0)."""
    monkeypatch.setattr(kernels(), "blocks", lambda rows, columns, depth: kernels().Blocks(16, 16, 16, splits=splits))
    compare_gemm_ops(dtype, sizes, seed=splits)
    assert not any(counters.any() for counters in kernels()._counters.values())


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_the_gemm_ops_run_cublas_from_cublas_rows_on(dtype: torch.dtype, monkeypatch: pytest.MonkeyPatch) -> None:
    """From `CUBLAS_ROWS` rows on (here lowered to 16) the GEMM ops run the GEMM in torch (cuBLAS on CUDA) with the
    epilogue kernels around it (`rope_cache_write`, `geglu`): the same results as the references; fewer rows keep
    the fused kernels."""
    monkeypatch.setattr(kernels(), "CUBLAS_ROWS", 16)
    width = SIZES["odd"][0]
    assert kernels().blocks(15, 64, width) is not None and kernels().blocks(16, 64, width) is None
    compare_gemm_ops(dtype, "odd", seed=1)


def test_each_op_is_one_op_on_the_meta_device_and_traces_under_compile() -> None:
    """Registered as custom ops: the op counter sees one op per call (their fake implementations give the shapes),
    and `torch.compile(fullgraph=True)` traces through one (no graph break)."""
    meta = torch.device("meta")
    x, scale, weight, down = (torch.empty(*shape, device=meta) for shape in ((10, 64), (64,), (64, 256), (128, 64)))
    with AtenOpCounter() as counter:
        hidden = ops.call(ops.norm_gate_up_geglu, x, scale, None, weight, 1e-6)
        ops.call(ops.matmul_residual_, x, hidden, down, None)
    assert hidden.shape == (10, 128) and counter.total == 2 and counter.ops["norm_gate_up_geglu"] == 1, counter.ops

    def mlp(x: torch.Tensor, scale: torch.Tensor, gate_up: torch.Tensor, down: torch.Tensor) -> torch.Tensor:
        out = x.clone()
        ops.call(ops.matmul_residual_, out, ops.call(ops.norm_gate_up_geglu, x, scale, None, gate_up, 1e-6), down, None)
        return out

    generator = torch.Generator().manual_seed(0)
    arguments = (torch.randn(6, 32, generator=generator), 1 + torch.randn(32, generator=generator) * 0.1,
                 torch.randn(32, 96, generator=generator) / 6, torch.randn(48, 32, generator=generator) / 7)
    torch.testing.assert_close(torch.compile(mlp, fullgraph=True, backend="aot_eager")(*arguments), mlp(*arguments))


def test_the_persistent_launch_refuses_layers_it_cannot_address() -> None:
    """One launch reads every layer's weights at layer 0's strides, from an offset per layer (`weight_offsets`): layers
    whose weights differ in shape, strides or dtype, or start off a 16-byte boundary, are refused by name."""
    from pi0_torch.kernels import persistent

    weights = [torch.randn(4, 64, 32).unbind(0) for _ in range(4)]
    table = persistent.weight_offsets(weights, torch.device("cpu"))
    assert table.shape == (4, 4) and table[0].eq(0).all()
    assert table[:, 0].tolist() == [(w.data_ptr() - weights[0][0].data_ptr()) // 4 for w in weights[0]]
    transposed = [list(weights[0]), list(weights[1]), list(weights[2]), [*weights[3][:3], weights[3][3].t().contiguous().t()]]
    with pytest.raises(ValueError, match=r"layer 3's down weight is \(64, 32\) with strides \(1, 64\)"):
        persistent.weight_offsets(transposed, torch.device("cpu"))
    storage = torch.randn(64 * 32 + 1)
    shifted = [list(weights[0]), [weights[1][0], storage[1:].view(64, 32), *weights[1][2:]], list(weights[2]),
               list(weights[3])]
    with pytest.raises(ValueError, match="layer 1's o weight starts at an address that is not a multiple of 16 bytes"):
        persistent.weight_offsets(shifted, torch.device("cpu"))


def sampling_inputs(config: PI0Config, batch: int, seed: int) -> dict[str, torch.Tensor]:
    """Padded prompts of several lengths and a camera no sample shows."""
    generator = torch.Generator().manual_seed(seed)
    masks = torch.ones(batch, config.num_cameras, dtype=torch.bool)
    masks[:, -1] = False
    lengths = torch.randint(1, config.max_token_len + 1, (batch,), generator=generator)
    return dict(
        pixel_values=torch.rand(batch, config.num_cameras, 3, config.image_size, config.image_size, generator=generator) * 2 - 1,
        image_masks=masks,
        input_ids=torch.randint(0, config.vocab_size, (batch, config.max_token_len), generator=generator),
        attention_mask=torch.arange(config.max_token_len)[None] < lengths[:, None],
        state=torch.randn(batch, config.action_dim, generator=generator),
        noise=torch.randn(batch, config.action_horizon, config.action_dim, generator=generator),
    )


def tiny_config(preset: str = "pi0_small", **overrides) -> PI0Config:
    return PI0Config.from_preset(preset, image_size=28, vision_hidden_size=32, vision_intermediate_size=64,
                                 vision_num_layers=1, vision_num_heads=2, max_token_len=12, action_horizon=10, **overrides)


PRECISIONS = [(torch.float32, 1e-5), (torch.bfloat16, 3e-2)]


@pytest.mark.parametrize("setting, preset, dtype, tolerance, batch", [
    *(("triton", preset, *precision, batch) for preset in ("pi0_small", "pi05_small") for precision in PRECISIONS
      for batch in (1, 3)),
    # (the persistent launch: each family, precision and batch size once; 10 s each in the interpreter)
    ("persistent", "pi0_small", *PRECISIONS[0], 3), ("persistent", "pi0_small", *PRECISIONS[1], 1),
    ("persistent", "pi05_small", *PRECISIONS[0], 1), ("persistent", "pi05_small", *PRECISIONS[1], 3),
])
def test_fused_steps_equal_the_unfused_ones_and_the_reference_loop(setting: str, preset: str, dtype: torch.dtype,
                                                                     tolerance: float, batch: int,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """`sampling_kernels="triton"`: every Euler step in the fused kernels ("persistent": each step's decoder layers in
    one launch, `kernels.persistent`). The actions equal the unfused engine's and `sample_actions_reference`'s (float32
    tightly; bf16 to its rounding: the fused epilogues round less often). At batch 3 the step's GEMMs run as from
    `CUBLAS_ROWS` rows on (here lowered to 30: cuBLAS's GEMMs with the epilogue kernels around them; the persistent
    launch has no such switch)."""
    monkeypatch.setattr(kernels(), "CUBLAS_ROWS", 30)
    torch.manual_seed(0)
    config = tiny_config(preset)
    model = PI0ForActionGeneration(config).eval().to(DEVICE, dtype)
    inputs = {name: value.to(DEVICE) for name, value in sampling_inputs(config, batch, seed=batch).items()}
    if config.pi05:
        inputs.pop("state")
    model.sampling_kernels = "torch"
    unfused = model.generate_actions(**inputs, num_steps=3)
    plain = model.sample_actions_reference(**inputs, num_steps=3)
    model.sampling_kernels = setting
    assert model.fused_steps_reason(DEVICE, dtype) is None
    fused = model.generate_actions(**inputs, num_steps=3)
    assert relative(fused, unfused) <= tolerance and relative(fused, plain) <= tolerance


@pytest.mark.slow  # (5 minutes in the interpreter; on CUDA in bf16 "auto" fuses, and test_cuda checks the fixtures)
def test_fused_steps_match_openpi(references: dict[str, OpenpiReference]) -> None:
    """The openpi fixtures' actions, sampled with every step fused (float32 in the interpreter on a CPU)."""
    for ref in references.values():
        model = ref.model().to(DEVICE)
        model.sampling_kernels = "triton"
        inputs = {name: value.to(DEVICE) for name, value in ref.model_inputs().items()}
        actions = model.generate_actions(**inputs, noise=ref.tensor("inputs/sample_noise").to(DEVICE))
        assert relative_error(actions, ref["fp32/actions"]) <= 1e-4


def test_auto_runs_the_fused_steps_only_where_they_apply(monkeypatch: pytest.MonkeyPatch) -> None:
    """"auto" fuses only on CUDA in bf16 / fp16; "triton" refuses, naming why, a model it cannot run; a kernel that
    differs from its reference on a device keeps that device on the torch path (checked once, logged)."""
    model = PI0ForActionGeneration(PI0Config.from_preset("pi0_small")).eval()
    assert "run on CUDA in bf16 / fp16" in model.fused_steps_reason(torch.device("cpu"), torch.float32)
    assert model.fused_steps_reason(torch.device("cpu"), torch.float32, "guidance").startswith("real-time chunking")
    model.sampling_kernels = "triton"
    grouped = PI0ForActionGeneration(PI0Config.from_preset("pi0_small", num_key_value_heads=2)).eval()
    grouped.sampling_kernels = "triton"
    with pytest.raises(ValueError, match="sampling_kernels='triton' cannot run: the fused attention folds the query heads onto one kv head"):
        grouped.fused_steps_reason(torch.device("cpu"), torch.float32)
    with pytest.raises(ValueError, match="sampling_kernels must be one of"):
        model.sampling_kernels = "cuda"

    checks.sampling_ops_reason.cache_clear()
    broken = kernels().norm_gate_up_geglu
    monkeypatch.setattr(kernels(), "norm_gate_up_geglu", lambda *args: broken(*args) * 1.5)
    reason = checks.sampling_ops_reason(DEVICE, torch.float32, 64, 2, 16, 128, 32, 48)
    assert reason.startswith("the fused kernel norm_gate_up_geglu differs from its torch reference"), reason
    checks.sampling_ops_reason.cache_clear()


def test_each_fused_plan_is_verified_against_the_unfused_path_on_its_first_call(monkeypatch: pytest.MonkeyPatch,
                                                                                caplog: pytest.LogCaptureFixture) -> None:
    """Triton compiles each kernel anew per class of arguments (row-count blocks, integers equal to 1 or divisible
    by 16), so a new batch size or prompt layout launches variants the self-check never ran. The first call of each
    plan and input shapes samples unfused and fused and compares; a verified plan runs fused from then on, one that
    deviates or fails samples unfused (a warning; "triton" raises instead), and its actions are the unfused ones.
    Eager, the first call returns the verification's own actions."""
    torch.manual_seed(0)
    model = PI0ForActionGeneration(tiny_config(num_hidden_layers=1)).eval().to(DEVICE)
    inputs = {name: value.to(DEVICE) for name, value in sampling_inputs(model.config, 2, seed=4).items()}
    model.sampling_kernels = "torch"
    unfused = model.generate_actions(**inputs, num_steps=2)
    samplings: list[bool] = []  # plan.fused of each `sample_planned`
    sample = model.sample_planned
    monkeypatch.setattr(model, "sample_planned", lambda inputs, plan, *weights: samplings.append(plan.fused) or sample(inputs, plan, *weights))

    model.sampling_kernels = "triton"
    first = model.generate_actions(**inputs, num_steps=2)
    assert samplings == [False, True]  # verified: unfused, then fused (the call's actions)
    assert model.last_sampling_route == SamplingRoute("triton", graph=False)
    assert model.generate_actions(**inputs, num_steps=2).equal(first) and samplings[2:] == [True]
    assert relative(first, unfused) <= 1e-5 and list(model._fused_refusals.values()) == [None]
    model.generate_actions(**{name: value[:1] for name, value in inputs.items()}, num_steps=2)  # batch 1: verified anew
    assert samplings[3:] == [False, True]

    broken = kernels().norm_linear_euler_  # (an Euler update off by 1.5x: wrong actions, finite)
    monkeypatch.setattr(kernels(), "norm_linear_euler_", lambda x_t, tokens, scale, bias, weight, dt, eps:
                        broken(x_t, tokens, scale, bias, weight, 1.5 * dt, eps))
    model.sampling_kernels = "triton"  # (clears the verdicts)
    with pytest.raises(ValueError, match=r"sampling_kernels='triton' cannot run sampling \(batch 2, 2 steps, .*its actions "
                                         r"deviate from the unfused path's by .* of the largest action \(bound 0.0001\)"):
        model.generate_actions(**inputs, num_steps=2)

    model.sampling_kernels = "auto"  # (as on CUDA in bf16, where "auto" fuses)
    monkeypatch.setattr(model, "fused_steps_reason", lambda *args: None)
    monkeypatch.setattr(model, "PERSISTENT_EAGER_BATCH", 0)  # (five launches per layer; persistent ones: the next test)
    del samplings[:]
    with caplog.at_level("WARNING", logger="pi0_torch.inference.sampling"):
        refused = model.generate_actions(**inputs, num_steps=2)
        assert model.generate_actions(**inputs, num_steps=2).equal(refused)
    assert refused.equal(unfused) and samplings == [False, True, False]
    route = model.last_sampling_route
    assert route.steps == "torch" and not route.graph and len(route.refusals) == 1, route
    assert route.refusals[0].startswith("fused steps: its actions deviate from the unfused path's by ")
    assert route.why_unfused == f"the fused steps were refused: {route.refusals[0].removeprefix('fused steps: ')}"
    assert [record.getMessage().split(":")[0] for record in caplog.records] == [
        "the fused kernels were refused for sampling (batch 2, 2 steps, 19 prefix slots, fused steps)"], caplog.text

    def out_of_resources(*args):  # (what triton raises for a variant larger than the device's shared memory)
        raise RuntimeError("out of resource: shared memory, Required: 102400, Hardware limit: 101376")

    monkeypatch.setattr(kernels(), "range_attention", out_of_resources)
    model.sampling_kernels = "auto"
    with caplog.at_level("WARNING", logger="pi0_torch.inference.sampling"):
        assert model.generate_actions(**inputs, num_steps=2).equal(unfused)
    assert list(model._fused_refusals.values()) == [
        "it failed (RuntimeError: out of resource: shared memory, Required: 102400, Hardware limit: 101376)"]


def test_auto_runs_the_persistent_launch_in_eager_calls_of_few_samples(monkeypatch: pytest.MonkeyPatch,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    """Under "auto" where the fused steps apply (as on CUDA in bf16), an eager call of at most
    `PERSISTENT_EAGER_BATCH` samples runs each step's decoder layers in one persistent launch, a larger batch and a
    CUDA graph's replay five launches per layer (measured faster there); "triton" never, "persistent" always. A
    persistent plan refused on its first call falls back to five launches per layer, verified in their turn against
    the unfused actions its own verification sampled, with a warning; `last_sampling_route` says what ran."""
    from pi0_torch.kernels import persistent

    torch.manual_seed(0)
    model = PI0ForActionGeneration(tiny_config(num_hidden_layers=1)).eval().to(DEVICE)
    inputs = {name: value.to(DEVICE) for name, value in sampling_inputs(model.config, 3, seed=4).items()}
    assert model.sampling_kernels == "auto" and model.PERSISTENT_EAGER_BATCH == 2
    assert [model.runs_persistent(batch, False, DEVICE) for batch in (1, 2, 3, 8)] == [True, True, False, False]
    assert not model.runs_persistent(1, True, DEVICE)
    model.sampling_kernels = "triton"
    assert not model.runs_persistent(1, False, DEVICE)
    model.sampling_kernels = "persistent"
    assert model.runs_persistent(8, True, DEVICE)

    model.sampling_kernels = "torch"
    unfused = model.generate_actions(**inputs, num_steps=2)
    model.sampling_kernels = "auto"
    monkeypatch.setattr(model, "fused_steps_reason", lambda *args: None)
    samplings: list[tuple[bool, bool]] = []  # (plan.fused, plan.persistent) of each `sample_planned`
    sample = model.sample_planned
    monkeypatch.setattr(model, "sample_planned", lambda inputs, plan, *weights: samplings.append((plan.fused, plan.persistent))
                        or sample(inputs, plan, *weights))
    first = {name: value[:1] for name, value in inputs.items()}
    one = model.generate_actions(**first, num_steps=2)
    assert samplings == [(False, False), (True, True)]  # verified: unfused, then in persistent launches
    assert relative(one, unfused[:1]) <= 1e-5 and model.last_sampling_route == SamplingRoute("persistent", False)
    del samplings[:]
    assert relative(model.generate_actions(**inputs, num_steps=2), unfused) <= 1e-5
    assert samplings == [(False, False), (True, False)]  # batch 3: five launches per layer
    assert model.last_sampling_route == SamplingRoute("triton", False)

    def fails(*args):
        raise RuntimeError("out of resource: shared memory")

    monkeypatch.setattr(persistent, "expert_layers_", fails)
    model.sampling_kernels = "auto"  # (clears the verdicts)
    del samplings[:]
    with caplog.at_level("WARNING", logger="pi0_torch.inference.sampling"):
        refused = model.generate_actions(**first, num_steps=2)
        assert model.generate_actions(**first, num_steps=2).equal(refused)
    # (unfused once: the persistent plan's verification, whose unfused actions the five launches are checked against)
    assert samplings == [(False, False), (True, True), (True, False), (True, False)]
    assert relative(refused, unfused[:1]) <= 1e-5
    assert model.last_sampling_route == SamplingRoute(
        "triton", False, refusals=("persistent launch: it failed (RuntimeError: out of resource: shared memory)",))
    assert [record.getMessage() for record in caplog.records] == [
        "the fused kernels were refused for sampling (batch 1, 2 steps, 19 prefix slots, fused steps in persistent "
        "launches): it failed (RuntimeError: out of resource: shared memory); it runs five launches per decoder layer "
        "from now on"], caplog.text


def test_the_fused_steps_run_few_kernels_per_layer_and_step() -> None:
    """Counted on the meta device at full size (no weights), bf16, 3 cameras, 48 prompt tokens, 10 steps, batch 1:
    each fused step is the action embedding, five ops per decoder layer and the fused final norm + Euler update; the
    prefix pass keeps cuBLAS's GEMMs with RoPE + cache write and GeGLU fused around them, π0's state token runs with
    the first step's action tokens, SigLIP nine ops per layer, and one RoPE table serves every pass. 1,370 (π0) and
    1,439 (π0.5) kernels, from 3,735 and 3,868 unfused (issue 37: 1,500 / 1,600); 482 and 555 with each step's
    layers in one launch (`sampling_kernels="persistent"`)."""
    facts = InputFacts(((True, True, True),), (48,), 48)
    for preset, ceiling in (("pi0", 1_375), ("pi05", 1_445)):
        config = PI0Config.from_preset(preset)
        _, unfused = sample_on_meta(config, facts, 10, torch.bfloat16)
        _, fused = sample_on_meta(config, facts, 10, torch.bfloat16, fused=True)
        layers = config.num_hidden_layers
        assert fused.ops["norm_qkv_rope"] == 10 * layers, fused.ops  # (π0's state token: in the first step's)
        assert fused.ops["range_attention"] == fused.ops["norm_gate_up_geglu"] == 10 * layers
        assert fused.ops["matmul_residual_"] == 2 * fused.ops["norm_gate_up_geglu"] and fused.ops["norm_linear_euler_"] == 10
        assert fused.ops["embed_actions"] == 10
        assert fused.ops["rope_cache_write"] == layers and fused.ops["geglu"] == layers - 1  # (the last layer: k/v only)
        assert fused.ops["add_layer_norm_"] == 2 * config.vision_num_layers == 2 * fused.ops["_addmm_activation"]
        assert fused.kernels <= ceiling < unfused.kernels, (preset, fused.kernels, unfused.kernels)
        _, persistent = sample_on_meta(config, facts, 10, torch.bfloat16, fused=True, persistent=True)
        assert persistent.ops["expert_layers_"] == 10, persistent.ops
        assert not any(persistent.ops[name] for name in ("norm_qkv_rope", "range_attention", "matmul_residual_",
                                                          "norm_gate_up_geglu")), persistent.ops
        # (the steps' 5 ops per layer become one per step; plus the stacked norm scales and adaRMS tensors: 2 and 6)
        assert persistent.kernels <= fused.kernels - 10 * (5 * layers - 1) + (6 if config.pi05 else 2), (
            persistent.kernels, fused.kernels)


def test_every_fused_op_the_engine_launches_has_a_self_check_case() -> None:
    """Each fused op a sampling or decoding path launches is checked against its torch reference before first use:
    the ops counted on the meta device (full size, bf16, five launches per layer; π0-FAST's decoded token) all have a
    case in `checks.sampling_cases` / `checks.decoding_cases`, paired by the op itself. The persistent launch
    (`expert_layers_`) is the five per-layer ops in one kernel: each plan of it is verified on its first call
    (`checks.verify_fused_sampling`), which `test_auto_runs_the_persistent_launch_in_eager_calls_of_few_samples`
    covers."""
    from pi0_torch.benchmark import decode_step_on_meta
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig

    ours = {name for name in dir(ops) if isinstance(getattr(ops, name), torch._library.custom_ops.CustomOpDef)}
    cpu = torch.device("cpu")
    checked = {checks.op_name(op) for op, _ in checks.sampling_cases(cpu, torch.float32, 64, 2, 16, 128, 32, 48)}
    facts = InputFacts(((True, True, True),), (48,), 48)
    for preset in ("pi0", "pi05"):
        _, fused = sample_on_meta(PI0Config.from_preset(preset), facts, 2, torch.bfloat16, fused=True)
        launched = {name for name, count in fused.ops.items() if count and name in ours}
        assert launched and launched <= checked, (preset, launched - checked)
    decoded = decode_step_on_meta(PI0FastConfig.from_preset("pi0_fast"), fused=True)
    launched = {name for name, count in decoded.ops.items() if count and name in ours}
    checked = {checks.op_name(op) for op, _ in checks.decoding_cases(cpu, torch.float32, 2, 16, 128, 1, 64)}
    assert launched and launched <= checked, launched - checked


def test_every_kernel_variant_fits_the_shared_memory_of_an_rtx_4090() -> None:
    """benchmarks/kernel_resources.py compiles every kernel variant of full-size π0 / π0.5 sampling (batch 1 and 8;
    π0's persistent launch at batch 1) and π0-FAST decoding for sm_89 on this CPU (triton's ptxas, no GPU): none needs
    more shared memory than one block may have there (99 KiB, also the RTX 3090's and 5090's). The 64-row attention blocks of batch 8 took 100 KiB with
    triton's default three stages of loads and would have failed to launch ("out of resource: shared memory")."""
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "kernel_resources.py"
    environment = {name: value for name, value in os.environ.items() if name != "TRITON_INTERPRET"}
    result = subprocess.run([sys.executable, str(script), "--arch", "89", "--batches", "1,8", "--check"],
                            capture_output=True, text=True, env=environment, timeout=600)
    assert result.returncode == 0 and "TOO LARGE" not in result.stdout, result.stdout + result.stderr[-3000:]
    rows = [line.split() for line in result.stdout.splitlines() if line.startswith("_range_attention_kernel")]
    assert ["64,", "32"] in [row[1:3] for row in rows], result.stdout  # (batch 8's blocks were compiled)
    persistent = [line for line in result.stdout.splitlines() if line.startswith("_expert_layers_kernel")]
    assert len(persistent) == 1, result.stdout  # (the steps' 50 rows; the first step's 51, π0's state token ahead)


@pytest.mark.parametrize("experiment", ["persistent_mlp.py", "persistent_layers.py"])
def test_the_persistent_experiments_equal_the_reference(experiment: str) -> None:
    """Issue 37's experiments, timed where a GPU is lent: the MLP half of a layer-step
    (benchmarks/persistent_mlp.py) and every layer of an Euler step (benchmarks/persistent_layers.py) as one launch
    whose programs take tiles in ticket order and wait on each other's counters. Each computes what the reference
    ops compute: in triton's interpreter here (one and several row blocks and samples, partial tiles; the layers
    π0's and π0.5's), at full size on a GPU. The layers also leave each counter at the count its waits need, launch
    again on the counters they put back to 0, and compute the same with their tiles in other orders their waits
    allow (recorded from the kernel's waits and count-ins): a race on a GPU is likely to come out wrong there,
    though the interpreter never runs two tiles at once."""
    script = Path(__file__).resolve().parents[1] / "benchmarks" / experiment
    result = subprocess.run([sys.executable, str(script), "--check"], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0 and "against the reference" in result.stdout, result.stdout + result.stderr[-3000:]


def test_direct_launches_equal_tritons_own() -> None:
    """A direct launch (`pi0_torch.kernels.launch`) hands the compiled kernel's launcher what triton's `kernel[grid]`
    hands it: tests/launch_check.py compiles kernels for sm_89 on this CPU, records each launch, and compares triton's
    path with the direct one for each of the nine kernels (every variant sampling runs), tensors at and off a 16-byte
    boundary, integers 1, 16 and 17, split-K, key parts, with and without a launch hook (where the installed triton is
    one the direct launches are written for; else it checks nothing and says so)."""
    script = Path(__file__).resolve().parent / "launch_check.py"
    environment = {name: value for name, value in os.environ.items() if name != "TRITON_INTERPRET"}
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=environment, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr[-3000:]
    assert "launches compared" in result.stdout or "triton's launch throughout" in result.stdout, result.stdout


def test_direct_launches_step_aside_where_they_are_not_written_for(monkeypatch: pytest.MonkeyPatch) -> None:
    """Triton's own launch where asked (`PI0_TORCH_TRITON_LAUNCH=triton`), with a triton version the direct launches
    are not written for, and for interpreted kernels (`TRITON_INTERPRET=1`, as in these tests)."""
    import triton

    from pi0_torch.kernels import launch, triton_kernels

    monkeypatch.setenv("PI0_TORCH_TRITON_LAUNCH", "triton")
    assert launch._direct_reason() == "PI0_TORCH_TRITON_LAUNCH=triton"
    monkeypatch.delenv("PI0_TORCH_TRITON_LAUNCH")
    monkeypatch.setattr(triton, "__version__", "3.10.0")
    assert launch._direct_reason() == "triton 3.10.0: direct launches are written for triton 3.5 to 3.9"
    monkeypatch.setattr(triton, "__version__", "3.4.1")
    assert launch._direct_reason() is not None
    if os.environ.get("TRITON_INTERPRET") == "1":
        assert not triton_kernels._geglu_kernel.direct
        assert triton_kernels._geglu_kernel[(1,)] is not None  # (the interpreter's own launcher)


def test_the_vision_pass_equals_siglip_and_runs_nine_kernels_per_layer() -> None:
    """`vision_pass.vision_tokens` computes SigLIP's last hidden state (float32 tightly, bf16 to its rounding) in nine
    ops per encoder layer (CUDA's count, on the meta device), and `tower_pass` declines a tower whose modules do more
    than their weights (a hook, a `nn.Linear` subclass such as LoRA) or that is not π0's (another MLP activation)."""
    config = PI0Config.from_preset("pi0_small", image_size=28, vision_hidden_size=48, vision_intermediate_size=72,
                                   vision_num_layers=3, vision_num_heads=3)
    torch.manual_seed(0)
    model = PI0ForActionGeneration(config).eval()
    images = torch.rand(3, 3, 28, 28, generator=torch.Generator().manual_seed(1)) * 2 - 1
    for dtype, tolerance in ((torch.float32, 1e-5), (torch.bfloat16, 2e-2)):
        tower = model.vision_tower.to(DEVICE, dtype)
        with torch.no_grad():
            expected = tower(pixel_values=images.to(DEVICE, dtype)).last_hidden_state
            got = vision_pass.tower_pass(tower)(images.to(DEVICE, dtype))
        assert got.shape == expected.shape and relative(got, expected) <= tolerance, dtype

    with torch.device("meta"):
        tower = PI0ForActionGeneration(PI0Config.from_preset("pi0")).vision_tower.to(torch.bfloat16)
    with torch.no_grad(), AtenOpCounter() as counter:
        vision_pass.tower_pass(tower)(torch.empty(3, 3, 224, 224, device="meta", dtype=torch.bfloat16))
    layers = len(tower.encoder.layers)
    embedding = 3  # the patches' convolution, the positions' add, the first LayerNorm
    assert counter.kernels == embedding + 9 * layers, counter.ops

    tower = model.vision_tower.float()
    hook = tower.encoder.layers[1].mlp.register_forward_hook(lambda *_: None)
    assert vision_pass.tower_pass(tower) is None
    hook.remove()
    tower.config.hidden_act = "gelu"
    assert vision_pass.tower_pass(tower) is None
    tower.config.hidden_act = "gelu_pytorch_tanh"
    assert vision_pass.tower_pass(tower) is not None

    class Adapted(torch.nn.Linear):
        pass

    attention = tower.encoder.layers[0].self_attn
    attention.v_proj = Adapted(attention.v_proj.in_features, attention.v_proj.out_features)
    assert vision_pass.tower_pass(tower) is None
