"""`pi0-torch doctor`: every sampling path against its reference, one table, a non-zero exit on any failure."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys

import pytest
import torch

from pi0_torch import doctor


def run_doctor(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser()
    doctor.add_arguments(parser)
    code = doctor.run(parser.parse_args(list(argv)))
    return code, capsys.readouterr().out


def test_doctor_passes_at_the_small_size_on_this_machine(capsys: pytest.CaptureFixture[str]) -> None:
    """The CPU runs every row that needs no CUDA (the CUDA rows say so); each is within its bound."""
    code, out = run_doctor(capsys, "--device", "cpu")
    assert code == 0, out
    rows = re.findall(r"^(π0\S*|π0-FAST) (.+?)\s+cpu\s+(float32|bfloat16)\s+(\S+)\s+(\S+)\s+(pass|FAIL|skip)", out, re.MULTILINE)
    results = [row[-1] for row in rows]
    assert results.count("pass") >= 20 and "FAIL" not in results, out
    assert all(note == "needs CUDA" for note in re.findall(r"skip\s+[\d.]+\s+(.*)$", out, re.MULTILINE)), out
    assert re.search(r"^\d+ passed, 0 failed, \d+ skipped$", out, re.MULTILINE), out
    for path in ("eager", "RTC guidance, eager", "RTC conditioning, eager", "training forward vs reference step",
                 "training step, bf16 autocast", "LoRA (adapters, merged)", "CUDA graph", "fused kernels",
                 "auto kernels, eager", "persistent layers, CUDA graph"):
        assert re.search(rf"^π0\.5 {re.escape(path)}\s", out, re.MULTILINE), path
    assert re.search(r"^π0-FAST decoding, 60 new tokens\s+cpu\s+bfloat16", out, re.MULTILINE), out


def test_a_row_out_of_bounds_or_raising_fails_and_a_lost_cuda_context_stops_the_run(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    checkup = doctor.Doctor(torch.device("cpu"), full=False)
    checkup.row("within", torch.float32, lambda: (1e-6, 1e-4, ""))
    checkup.row("beyond", torch.float32, lambda: (1e-3, 1e-4, ""))
    checkup.row("raises", torch.float32, lambda: 1 / 0)
    assert [row.result for row in checkup.rows] == ["pass", "FAIL", "FAIL"]
    assert checkup.rows[2].note == "ZeroDivisionError: division by zero"
    checkup.cuda = True  # (as on a GPU whose context a kernel lost)
    monkeypatch.setattr(doctor, "_cuda_usable", lambda device: False)
    with pytest.raises(doctor.ContextLost, match="the CUDA context was lost in the row 'broken'"):
        checkup.row("broken", torch.bfloat16, lambda: (_ for _ in ()).throw(RuntimeError("CUDA error: misaligned address")))

    def lost(self: doctor.Doctor, preset: str) -> None:
        self.cuda = True
        self.row("the row that breaks CUDA", torch.bfloat16, lambda: 1 / 0)

    monkeypatch.setattr(doctor.Doctor, "pi0_rows", lost)
    code, out = run_doctor(capsys, "--device", "cpu")
    assert code == 1 and "STOPPED: the CUDA context was lost in the row 'the row that breaks CUDA'" in out, out


def test_bad_devices_are_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    doctor.add_arguments(parser)
    assert doctor.run(parser.parse_args(["--device", "tpu"])) == 2
    assert "--device: 'tpu' is not a torch device" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert doctor.run(parser.parse_args(["--device", "cuda"])) == 2
        assert re.search(r"--device: cuda: this torch \(.*\) is built without CUDA|no CUDA GPU is visible", capsys.readouterr().err)


def test_rows_that_would_not_fit_in_memory_are_skipped_by_name(capsys: pytest.CaptureFixture[str],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """`--full` on a 24 GB CPU machine was killed for memory: each row now knows what it needs and is skipped, saying
    so, where it does not fit; the table finishes. (Here the small models with a machine of very little memory.)"""
    checkup = doctor.Doctor(torch.device("cpu"), full=False)
    checkup.model_bytes = 10 * 10**9
    monkeypatch.setattr(doctor.Doctor, "available_bytes", lambda self: 20 * 10**9)
    checkup.row("fits", torch.float32, lambda: (0.0, 1e-4, ""))
    checkup.row("a training step", torch.float32, lambda: (0.0, 1e-4, ""), needs=doctor.MEMORY_NEEDS["training step"])
    assert [row.result for row in checkup.rows] == ["pass", "skip"]
    assert checkup.rows[1].note == "needs about 33.0 GB, this machine has 20.0 GB available"

    monkeypatch.setattr(doctor.Doctor, "available_bytes", lambda self: 10**5)  # (less than even the small models)
    code, out = run_doctor(capsys, "--device", "cpu")
    assert code == 0, out
    for family in ("π0", "π0.5", "π0-FAST"):
        assert re.search(rf"^{re.escape(family)} \(every row\)\s+cpu\s+float32\s+-\s+-\s+skip\s+[\d.]+\s+the model needs "
                         r"about \d+ MB, this machine has 0 MB available", out, re.MULTILINE), out
    assert re.search(r"^\d+ passed, 0 failed, \d+ skipped$", out, re.MULTILINE), out


def test_an_address_space_limit_counts_as_the_memory_there_is() -> None:
    """Issue 63, round 5 item 9: `doctor --full` under `ulimit -v` failed with the allocator's traceback: the rows
    counted the machine's RAM, not what the process may still map. Each row past the limit is skipped, naming it."""
    script = ("import resource, psutil\n"
              "limit = psutil.Process().memory_info().vms + 3 * 2**30\n"
              "resource.setrlimit(resource.RLIMIT_AS, (limit, resource.RLIM_INFINITY))\n"
              "from pi0_torch.cli import main\nraise SystemExit(main(['doctor', '--full', '--device', 'cpu']))\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stdout[-2000:] + run.stderr[-2000:]
    assert re.search(r"the model needs about [\d.]+ GB, this process's address-space limit \(ulimit -v\) leaves "
                     r"[\d.]+ GB", run.stdout), run.stdout
