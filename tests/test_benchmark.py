"""`pi0-torch bench` runs end to end on small presets and prints its tables (timings are printed, never asserted)."""

from __future__ import annotations

import argparse
import re

import pytest
import torch

from pi0_torch import benchmark
from pi0_torch.kernels import ops
from pi0_torch.utils import hardware


def bench(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    parser = argparse.ArgumentParser()
    benchmark.add_arguments(parser)
    assert benchmark.run(parser.parse_args(["--repeats", "2", *argv])) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_generate_and_train_tables(capsys: pytest.CaptureFixture[str], compiled: bool) -> None:
    out = bench(capsys, "--presets", "pi0_small", "--dtypes", "float32", "--cameras", "2", "--batches", "1", "--train",
                *(["--compile"] if compiled else []))
    assert re.search(r"measured matmul ceiling: float32 \d+ GFLOP/s", out)
    rows = re.findall(r"^pi0_small\s+float32\s+(\S+)\s+torch\s+-\s+(\d)\s+1\s+[\d.]+\s+[\d.]+\s+[\d.]+\s+[\d.]+\s+\d+\s+\d+\s+\d+$", out, re.MULTILINE)
    assert rows == [("eager", "2"), ("compiled", "2")][: 2 if compiled else 1], out  # no CUDA-graph rows on CPU
    assert re.search(r"^pi0_small\s+float32\s+1\s+[\d.]+", out.split("training step")[1], re.MULTILINE), out


def test_plot_draws_the_generate_table(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    """Issue 63, first hour 8: `pi0-torch bench --plot PNG` draws its generate_actions table (one bar per row)."""
    from PIL import Image

    out = bench(capsys, "--presets", "pi0_small", "--dtypes", "float32", "--cameras", "1,2", "--batches", "1",
                "--plot", str(tmp_path / "bench.png"))
    assert f"wrote {tmp_path / 'bench.png'}" in out
    with Image.open(tmp_path / "bench.png") as chart:
        assert chart.format == "PNG" and chart.size[1] >= 2 * 30  # (two rows)


def test_real_time_chunking_rows(capsys: pytest.CaptureFixture[str]) -> None:
    """`--rtc` adds a row per method after each plain one: chunks continued by real-time chunking (guidance
    differentiates every step, so its FLOP/s of plain sampling are not shown)."""
    out = bench(capsys, "--presets", "pi05_small", "--dtypes", "float32", "--cameras", "1", "--batches", "1", "--rtc",
                "guidance,conditioning")
    rows = re.findall(r"^pi05_small\s+float32\s+eager\s+torch\s+(\S+)\s+1\s+1\s+[\d.]+\s+([\d.]+)\s+[\d.]+\s+[\d.]+\s+\d+\s+(\S+)\s+(\S+)$",
                      out, re.MULTILINE)
    assert [(method, rate, share) for method, _, rate, share in rows][1:] == [("guidance", "-", "-"), ("conditioning", "-", "-")], out
    assert rows[0][0] == "-" and float(rows[0][2]) > 0, out
    parser = argparse.ArgumentParser()
    benchmark.add_arguments(parser)
    assert benchmark.run(parser.parse_args(["--rtc", "guided"])) == 2
    assert "--rtc: expected guidance and/or conditioning, got guided" in capsys.readouterr().err


def test_side_by_side_with_transformers_agrees(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """float32 and bfloat16 rows on any CPU: bfloat16 instructions claimed (an emulating CPU only runs it slower)."""
    monkeypatch.setattr(hardware, "cpu_has_native_bf16", lambda: True)
    out = bench(capsys, "--skip-generate", "--side-by-side", "--side-by-side-preset", "pi0_small")
    rows = dict(re.findall(r"^eager\s+(float32|bfloat16)\s.*x\s+(\S+)$", out, re.MULTILINE))
    assert sorted(rows) == ["bfloat16", "float32"], out
    assert float(rows["float32"]) <= 1e-4  # identical weights, inputs and noise
    assert float(rows["bfloat16"]) <= 0.5  # both in bf16, each with its own rounding


def test_op_count_table(capsys: pytest.CaptureFixture[str]) -> None:
    out = bench(capsys, "--skip-generate", "--ops", "--presets", "pi0_small,pi05_small")
    rows = dict(re.findall(r"^(pi0_small|pi05_small)\s+(\d+)\s+\d+\s+\d+\s+\d+\s+0$", out, re.MULTILINE))
    assert sorted(rows) == ["pi05_small", "pi0_small"] and all(int(ops) > 0 for ops in rows.values()), out
    full_size = re.findall(r"^(pi0|pi05)\s+(torch|fused)\s+([13])\s+(\d+)\s+(\d+)\s+(\d+)\s+0\s+([\d.]+)$", out, re.MULTILINE)
    assert [row[:3] for row in full_size] == [(p, k, c) for p in ("pi0", "pi05") for k in ("torch", "fused") for c in "13"], out
    assert all(0 < int(kernels) < int(ops) for *_, ops, _, kernels, _ in full_size), out  # (meta: no host copy)
    per_step = {(preset, steps): float(value) for preset, steps, cameras, *_, value in full_size if cameras == "3"}
    # five fused ops per layer and step, plus each step's action embedding and final norm + Euler update (pi0: 96 a step)
    assert 5.0 < per_step[("pi0", "fused")] <= 5.4 and 5.0 < per_step[("pi05", "fused")] <= 5.4, per_step
    assert per_step[("pi0", "torch")] > 15 and per_step[("pi05", "torch")] > 15, per_step
    # a π0-FAST decoded token: 423 kernels through the modules, 171 fused (nine a layer: cuBLAS's GEMMs and norms,
    # rope_cache_write, range_attention, geglu; then the embedding, RoPE rows, final norm and LM head)
    fast = dict(re.findall(r"^pi0_fast\s+(torch|fused)\s+\d+\s+\d+\s+(\d+)\s+0\s+[\d.]+$", out, re.MULTILINE))
    assert int(fast["fused"]) <= 175 < 400 <= int(fast["torch"]), out


def test_fast_decoding_table(capsys: pytest.CaptureFixture[str]) -> None:
    """A row per decoding mode and `decoding_kernels` (the range_attention kernel in triton's interpreter here)."""
    kernels = ["torch"] + (["triton"] if ops.triton_reason(torch.device("cpu")) is None else [])
    out = bench(capsys, "--skip-generate", "--fast", "--fast-presets", "pi0_fast_small", "--fast-tokens", "4", "--dtypes",
                "float32", "--batches", "1", "--kernels", ",".join(kernels))
    rows = re.findall(r"^pi0_fast_small\s+float32\s+eager\s+(\w+)\s+1\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+(\S+)\s+\d+$", out, re.MULTILINE)
    assert [row[0] for row in rows] == kernels, out
    for _, chunk_ms, prefill_ms, _, _ in rows:
        assert float(chunk_ms) > 0 and float(prefill_ms) > 0


def test_bfloat16_is_skipped_with_a_note_where_the_device_has_no_native_bfloat16(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without bfloat16 instructions (as the CPU reports them; here claimed absent) the bf16 rows, which would time
    the emulation for minutes, are left out with a one-line note."""
    monkeypatch.setattr(hardware, "cpu_has_native_bf16", lambda: False)
    out = bench(capsys, "--presets", "pi0_small", "--dtypes", "float32,bfloat16", "--cameras", "1", "--batches", "1")
    assert re.search(r"^bfloat16 rows skipped: this CPU \(.*\) has no bfloat16 instructions, so bfloat16 is emulated",
                     out, re.MULTILINE), out
    assert "measured matmul ceiling: float32 " in out and "bfloat16 " not in out.split("measured matmul ceiling")[1]


def test_native_bfloat16_is_read_from_the_cpu_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without torch's own report, the flags of /proc/cpuinfo decide (x86: avx512_bf16 or amx_bf16; Arm: bf16)."""
    for machine, flags, native in [("x86_64", {"avx2", "fma"}, False), ("x86_64", {"avx2", "avx512_bf16"}, True),
                                   ("x86_64", {"amx_bf16"}, True), ("aarch64", {"asimd", "bf16"}, True),
                                   ("aarch64", {"asimd"}, False), ("riscv64", {"bf16"}, False)]:
        hardware.cpu_has_native_bf16.cache_clear()
        monkeypatch.setattr(hardware.platform, "machine", lambda machine=machine: machine)
        monkeypatch.setattr(hardware.platform, "system", lambda: "Linux")
        monkeypatch.setattr(hardware, "_cpu_flags", lambda flags=flags: flags)
        monkeypatch.delattr(hardware.torch.cpu, "_is_avx512_bf16_supported", raising=False)
        assert hardware.cpu_has_native_bf16() is native, (machine, flags)
    hardware.cpu_has_native_bf16.cache_clear()


def test_host_side_of_a_profiled_call() -> None:
    """The host's columns of a CUDA row (`benchmark.host_side`), from a profile's events: the time from the call's
    first host event to the end of its last launch, and the copies and synchronizations before that (not the
    benchmark's own synchronization after the last launch). The events' names are the CUDA calls' that the profiler
    records; `tests/test_cuda.py` finds them in a real profile."""
    from torch.autograd import DeviceType
    from torch.autograd.profiler_util import FunctionEvent

    def event(name: str, start: int, end: int, device: DeviceType = DeviceType.CPU) -> FunctionEvent:
        return FunctionEvent(0, name, 0, start, end, device_type=device)

    events = [
        event("aten::mm", 100, 130), event("cudaLaunchKernel", 110, 120),
        event("cudaMemcpyAsync", 140, 400), event("cudaStreamSynchronize", 400, 900),  # (a read of a device value)
        event("cuLaunchKernelEx", 1000, 1010), event("sm90_gemm", 1200, 5000, DeviceType.CUDA),
        event("cudaDeviceSynchronize", 1010, 6000),  # (the benchmark's, after the last launch)
    ]
    assert benchmark.host_side(events) == pytest.approx((910e-6, 760e-6))
    assert benchmark.host_side([event("aten::mm", 0, 10)]) == (None, None)
