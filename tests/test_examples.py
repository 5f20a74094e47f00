"""The examples run as documented: the quickstart, and `make demo` reproducing the demo policy's recorded accuracy."""

from __future__ import annotations

import json
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import HANG_S

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart_runs(capsys: pytest.CaptureFixture[str]) -> None:
    runpy.run_path(str(EXAMPLES / "quickstart.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "action chunk (2, 50, 32)" in out and "reloaded model gives the same chunk: True" in out


def test_demo_reproduces_the_recorded_closed_loop_success(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`make demo` / `pi0-torch demo` (`examples/demo.py` wraps `pi0_torch.demo`): the shipped policy acts in closed
    loop; its episodes are the ones recorded when the checkpoint was made (same seeds, same noise seeds)."""
    from pi0_torch.demo import demo_policy_dir, main

    threads = torch.get_num_threads()
    try:
        assert main(["--episodes", "10", "--output-dir", str(tmp_path)]) == 0
    finally:
        torch.set_num_threads(threads)  # the demo runs on one thread
    out = capsys.readouterr().out
    recorded = json.loads((demo_policy_dir() / "demo_metrics.json").read_text())["closed_loop"]
    for env_id in ("pi0_torch/Reach-v0", "pi0_torch/PickPlace-v0"):
        shown = float(re.search(rf"{re.escape(env_id)}\s+([0-9.]+)%", out).group(1)) / 100
        first_ten = recorded[env_id]["successes"][:10]
        assert shown == pytest.approx(sum(first_ten) / 10, abs=0.1)  # at most one borderline episode flips
    assert (tmp_path / "PickPlace-v0" / "rollout_1000000.mp4").stat().st_size > 10_000
    assert (tmp_path / "PickPlace-v0" / "rollout_1000000.png").stat().st_size > 1_000


def test_evaluate_notebook_runs(tmp_path: Path) -> None:
    """`examples/evaluate.ipynb` executes top to bottom (nbclient, a real kernel) and shows its table; nothing is
    written to stderr (with ipywidgets installed, as the notebook asks, tqdm has no IProgress warning)."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    notebook = nbformat.read(EXAMPLES / "evaluate.ipynb", as_version=4)
    nbclient.NotebookClient(notebook, timeout=HANG_S, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.get("outputs", [])]
    assert [output for output in outputs if output.get("name") == "stderr"] == []
    assert any("image/png" in output.get("data", {}) for output in outputs)  # the rollout strip, inline
    table = outputs[-1]["data"]["text/plain"]
    assert "pi0_torch/PickPlace-v0" in table and "expert" in table and "random" in table


def test_demo_recipe_runs_end_to_end_and_shares_its_plain_stages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`scripts/train_demo_policy.py` at a tiny scale: records, trains the plain stages (without image augmentation,
    as the shipped policy), evaluates, writes the policy; a second run with `--rtc-max-delay` reuses the plain stages
    and fine-tunes with delays in one more, a third with `--augment-stage` with openpi's augmentation."""
    script = runpy.run_path(str(EXAMPLES.parent / "scripts" / "train_demo_policy.py"))
    plain = [stage.name for stage in script["STAGES"]]
    threads = torch.get_num_threads()
    tiny = ["--work-dir", str(tmp_path), "--steps-scale", "0.001", "--episodes-scale", "0.001", "--eval-episodes", "1"]
    try:
        assert script["main"]([*tiny, "--destination", str(tmp_path / "plain")]) == 0
        assert script["main"]([*tiny, "--rtc-max-delay", "2", "--destination", str(tmp_path / "rtc")]) == 0
        assert script["main"]([*tiny, "--augment-stage", "--destination", str(tmp_path / "augmented")]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert all(out.count(f"stage {name}: reusing") == 2 for name in plain)
    assert "stage delays: reusing" not in out and "stage augmented: reusing" not in out
    for name, delay, stages in (("plain", 0, plain), ("rtc", 2, [*plain, "delays"]), ("augmented", 0, [*plain, "augmented"])):
        metrics = json.loads((tmp_path / name / "demo_metrics.json").read_text())
        assert list(metrics["steps"]) == stages and metrics["rtc_max_delay"] == delay
        assert metrics["reused_stages"] == ([] if name == "plain" else plain)
        assert metrics["augmented_stages"] == (["augmented"] if name == "augmented" else [])
        assert json.loads((tmp_path / name / "config.json").read_text())["rtc_max_delay"] == delay
    for stage in [*plain, "delays", "augmented"]:
        recorded = json.loads(next(tmp_path.glob(f"{stage}_rtc*/pi0_train_settings.json")).read_text())
        assert recorded["augment"] is (stage == "augmented")


def test_the_finetune_example_runs_twice_in_a_row(tmp_path: Path) -> None:
    """Issue 38.4: a second run ended in a traceback telling to pass --overwrite, which the example refused. The
    synthetic example replaces its own earlier run; a run on a user's data says what to pass, in one line."""
    script = [sys.executable, str(EXAMPLES / "finetune.py"), "--max-steps", "2", "--output-dir", str(tmp_path / "out")]
    for _ in range(2):
        done = subprocess.run(script, cwd=tmp_path, capture_output=True, text=True, timeout=HANG_S)
        assert done.returncode == 0, done.stderr[-2000:]
        assert "predicted first actions" in done.stdout
