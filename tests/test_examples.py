"""The examples run as documented: the quickstart, and `make demo` reproducing the demo policy's recorded accuracy."""

from __future__ import annotations

import json
import re
import runpy
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart_runs(capsys: pytest.CaptureFixture[str]) -> None:
    runpy.run_path(str(EXAMPLES / "quickstart.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "action chunk (2, 50, 32)" in out and "reloaded model gives the same chunk: True" in out


def test_demo_reproduces_the_recorded_accuracy(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`make demo` / `pi0-torch demo` (`examples/demo.py` wraps `pi0_torch.demo`)."""
    from pi0_torch.demo import main

    plot = tmp_path / "demo.png"
    threads = torch.get_num_threads()
    try:
        assert main(["--plot", str(plot), "--policy", str(EXAMPLES / "demo_policy")]) == 0
    finally:
        torch.set_num_threads(threads)  # the demo runs on one thread
    out = capsys.readouterr().out
    ratio = float(re.search(r"error ratio\s+([0-9.]+)", out).group(1))
    recorded = json.loads((EXAMPLES / "demo_policy" / "demo_metrics.json").read_text())["error_ratio"]
    assert ratio == pytest.approx(recorded, rel=0.05, abs=5e-4)
    assert ratio < 0.05  # far better than always predicting the mean action
    assert plot.stat().st_size > 10_000
