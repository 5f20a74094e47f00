"""Issue 28, classes 1 and 10: where a command may write, what `--overwrite` may replace, and that what it publishes
is on disk first.

One mechanism (`pi0_torch.utils.files.check_output_dir`, the manifest pi0-torch writes into its folders, `fsync`
before the rename) is used by every writer; these tests run each writer (eval outputs, the dataset writer of
`pi0-torch demos`, the generic atomic folder of convert / consolidate / the FAST tokenizer) against each kind of
folder it must refuse, and check that nothing there changed.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from pi0_torch.cli import main
from pi0_torch.data.lerobot_writer import EpisodeRecord, write_lerobot_dataset
from pi0_torch.envs.demos import record_demos
from pi0_torch.runtime.rollout import EvalResult, EvalSettings, check_eval_output, write_outputs
from pi0_torch.utils import files
from pi0_torch.utils.files import OutputPathError, atomic_output_dir, check_output_dir, resumable_output_dir

DEMO_POLICY = Path(__file__).resolve().parents[1] / "pi0_torch" / "demo_policy"
VECTORS = {"observation.state": ["x"], "action": ["x"]}


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def eval_result() -> EvalResult:
    return EvalResult(env="pi0_torch/Reach-v0", episodes=1, seed=0, execution="sync", inference_delay=0, replan_steps=4,
                      success_rate=1.0, success_ci95=(0.2, 1.0), mean_steps=3.0, latency_ms=1.0, boundary_jerk=None,
                      interior_jerk=None, policy={}, episodes_detail=[{"seed": 0, "success": True, "steps": 3}])


def write_eval(folder: Path, overwrite: bool) -> None:  # (as `evaluate` writes its output folder)
    check_output_dir(folder, overwrite)
    with resumable_output_dir(folder, overwrite) as staging:
        write_outputs(eval_result(), {}, staging, fps=10)


def write_dataset(folder: Path, overwrite: bool) -> None:
    episode = EpisodeRecord("wave", {"observation.images.top": np.zeros((2, 8, 8, 3), np.uint8)},
                            {"observation.state": np.zeros((2, 1)), "action": np.zeros((2, 1))})
    write_lerobot_dataset(folder, [episode], fps=10, vector_names=VECTORS, storage="image", overwrite=overwrite)


def write_demos(folder: Path, overwrite: bool) -> None:
    record_demos("pi0_torch/Reach-v0", 1, folder, image_size=16, storage="image", overwrite=overwrite)


def write_atomic(folder: Path, overwrite: bool) -> None:  # convert, consolidate, a FAST tokenizer's folder
    with atomic_output_dir(folder, overwrite=overwrite) as partial:
        (partial / "model.safetensors").write_bytes(b"weights")


WRITERS: dict[str, Callable[[Path, bool], None]] = {
    "eval": write_eval, "dataset": write_dataset, "demos": write_demos, "atomic": write_atomic,
}


@pytest.mark.parametrize("writer", sorted(WRITERS))
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_with_files_pi0_torch_did_not_write_is_never_replaced(writer: str, overwrite: bool, tmp_path: Path) -> None:
    """Issue 28.1 / 28.10: `--output-dir results` deleted `results/other_run/` and `results/notes.md`; `demos
    --overwrite` deleted a folder holding `src/main.py`. Now refused, with or without --overwrite, nothing touched."""
    target = tmp_path / "results"
    (target / "other_run").mkdir(parents=True)
    (target / "other_run" / "eval.json").write_text("{}")
    (target / "notes.md").write_text("mine")
    before = tree(target)
    with pytest.raises(OutputPathError, match="holds files that pi0-torch did not write") as refused:
        WRITERS[writer](target, overwrite)
    assert "notes.md" in str(refused.value) and "\n" not in str(refused.value)
    assert tree(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]  # no partial folder left behind


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_an_earlier_output_is_replaced_only_with_overwrite(writer: str, tmp_path: Path) -> None:
    target = tmp_path / "out"
    WRITERS[writer](target, False)
    assert files.MANIFEST_FILE in os.listdir(target) and not list(files.foreign_files(target))
    before = tree(target)
    with pytest.raises(OutputPathError, match=r"exists and is not empty \(pass --overwrite"):
        WRITERS[writer](target, False)
    assert tree(target) == before
    WRITERS[writer](target, True)
    assert not list(files.foreign_files(target))
    (target / "added by hand.txt").write_text("x")  # from now on the folder is the user's too
    with pytest.raises(OutputPathError, match=r"did not write \(added by hand.txt\)"):
        WRITERS[writer](target, True)


@pytest.mark.parametrize("writer", sorted(WRITERS))
@pytest.mark.parametrize("where", ["the working directory", "a parent of the working directory", "a file"])
def test_the_working_directory_its_parents_and_files_are_refused(
    writer: str, where: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 28.10: `demos --output-dir . --overwrite` replaced the current directory."""
    working = tmp_path / "project" / "src"
    working.mkdir(parents=True)
    (working / "main.py").write_text("print()")
    monkeypatch.chdir(working)
    (tmp_path / "file.txt").write_text("x")
    target = {"the working directory": Path("."), "a parent of the working directory": Path(".."),
              "a file": tmp_path / "file.txt"}[where]
    before = tree(tmp_path)
    with pytest.raises(OutputPathError, match="is the working directory|is a parent of|is not a folder"):
        WRITERS[writer](target, True)
    assert tree(tmp_path) == before


def test_eval_never_writes_into_the_evaluated_policy(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 28.1: `--output-dir` = the policy's own folder deleted its weights and config. Refused (also inside or
    around it, and for a folder pi0-torch wrote) before the policy loads or an episode runs."""
    policy = tmp_path / "policy"
    shutil.copytree(DEMO_POLICY, policy)
    files.record_written(policy, [policy])  # as if pi0-torch had written all of it
    before = tree(policy)
    for output in (policy, policy / "eval", tmp_path):
        settings = EvalSettings(env="pi0_torch/Reach-v0", output_dir=str(output), overwrite=True)
        with pytest.raises(OutputPathError, match="the input"):
            check_eval_output(settings, policy)
    assert main(["eval", "--policy", str(policy), "--env", "pi0_torch/Reach-v0", "--episodes", "1",
                 "--output-dir", str(policy), "--overwrite"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pi0-torch eval: error: output folder") and "is the input" in err and "\n" not in err, err
    assert tree(policy) == before


def test_published_files_and_folders_are_flushed_before_the_rename(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 28.10: a power loss after the rename must not publish empty files: every file and folder of the
    partial folder is fsync'ed before it is renamed into place, and the parent folder after."""
    events: list[tuple[str, str]] = []
    fsync, rename = os.fsync, Path.rename

    def record_fsync(descriptor: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{descriptor}")))
        fsync(descriptor)

    def record_rename(self: Path, target: Path) -> Path:
        events.append(("rename", str(target)))
        return rename(self, target)

    monkeypatch.setattr(os, "fsync", record_fsync)
    monkeypatch.setattr(Path, "rename", record_rename)
    with atomic_output_dir(tmp_path / "model") as partial:
        (partial / "sub").mkdir()
        (partial / "sub" / "weights.bin").write_bytes(b"w")
        (partial / "config.json").write_text("{}")
    renamed = events.index(("rename", str(tmp_path / "model")))
    synced_before = {Path(path).name for kind, path in events[:renamed] if kind == "fsync"}
    assert {"weights.bin", "config.json", files.MANIFEST_FILE, "sub"} <= synced_before
    assert any(Path(path).name.startswith(".model.partial-") for kind, path in events[:renamed] if kind == "fsync")
    assert ("fsync", str(tmp_path)) in events[renamed:]
