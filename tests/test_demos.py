"""Issue 28, classes 8 and 10: `pi0-torch demos` loses nothing to an interruption (episodes flushed in files,
`--resume` continues after the last one) and fails in one line, before recording, on settings it cannot use."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import HANG_S
from pi0_torch.cli import main
from pi0_torch.data import LeRobotEpisodeDataset
from pi0_torch.data.lerobot_writer import PROGRESS_FILE, LeRobotDatasetWriter, partial_dataset_episodes
from pi0_torch.envs.demos import record_demos

REPO = Path(__file__).resolve().parents[1]
SETTINGS = dict(image_size=16, storage="image", episodes_per_file=2)


def demos(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pi0_torch.cli", "demos", "--env", "pi0_torch/Reach-v0", *args],
                          cwd=tmp_path, capture_output=True, text=True, timeout=HANG_S, env={**os.environ, "OMP_NUM_THREADS": "1"})


def same_dataset(a: Path, b: Path) -> bool:
    first, second = LeRobotEpisodeDataset(a, 4, progress=False), LeRobotEpisodeDataset(b, 4, progress=False)
    return len(first) == len(second) and all(
        np.array_equal(first[i]["actions"], second[i]["actions"]) and np.array_equal(first[i]["state"], second[i]["state"])
        and all(np.array_equal(first[i]["images"][k], second[i]["images"][k]) for k in first.camera_keys)
        for i in range(len(first))
    ) and (a / "meta" / "stats.json").read_text() == (b / "meta" / "stats.json").read_text()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("whole") / "reach"
    record_demos("pi0_torch/Reach-v0", 7, root, **SETTINGS)
    return root


@pytest.mark.parametrize("interruption", ["SIGKILL", "full disk"])
def test_an_interrupted_recording_resumes_after_its_last_flushed_file(
    interruption: str, tmp_path: Path, uninterrupted: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 28.10: a kill after 200 episodes lost all of them. Now the files of flushed episodes stay in the partial
    folder, and `--resume` records only the rest: the result equals an uninterrupted recording, seeds included."""
    root = tmp_path / "reach"
    if interruption == "SIGKILL":  # killed right after its second file of 2 episodes was flushed
        script = f"""
import os, signal
from pi0_torch.data import lerobot_writer
from pi0_torch.envs.demos import record_demos
flush, count = lerobot_writer.LeRobotDatasetWriter._save_progress, [0]
def then_die(self):
    flush(self)
    count[0] += 1
    if count[0] == 2:
        os.kill(os.getpid(), signal.SIGKILL)
lerobot_writer.LeRobotDatasetWriter._save_progress = then_die
record_demos("pi0_torch/Reach-v0", 7, {str(root)!r}, **{SETTINGS!r})
"""
        killed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=HANG_S)
        assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    else:  # the disk fills while the third file is written
        write_table, calls = pq.write_table, [0]

        def full_disk(*args: object, **kwargs: object) -> None:
            calls[0] += 1
            if calls[0] == 3:
                raise OSError(errno.ENOSPC, "No space left on device")
            write_table(*args, **kwargs)

        monkeypatch.setattr(pq, "write_table", full_disk)
        with pytest.raises(OSError, match="No space left"):
            record_demos("pi0_torch/Reach-v0", 7, root, **SETTINGS)
        monkeypatch.undo()
    assert not root.exists() and partial_dataset_episodes(root) == 4
    with pytest.raises(ValueError, match="holds 4 episodes of an interrupted run: pass --resume"):
        record_demos("pi0_torch/Reach-v0", 7, root, **SETTINGS)  # nothing is dropped without being asked
    with pytest.raises(ValueError, match="image_size 16 there, 32 now"):
        record_demos("pi0_torch/Reach-v0", 7, root, **{**SETTINGS, "image_size": 32}, resume=True)
    summary = record_demos("pi0_torch/Reach-v0", 7, root, **SETTINGS, resume=True)
    assert summary.episodes == 7 and same_dataset(root, uninterrupted)
    seeds = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").column("seed").to_pylist()
    assert seeds == [0, 1, 2, 3, 4, 5, 6]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reach"]  # the partial folder became the dataset
    assert not (root / PROGRESS_FILE).exists()


def test_overwrite_discards_a_partial_dataset_and_resume_without_one_starts_afresh(tmp_path: Path) -> None:
    root = tmp_path / "reach"
    with pytest.raises(KeyboardInterrupt):
        with LeRobotDatasetWriter(root, fps=10, vector_names={"observation.state": ["x"], "action": ["x"]},
                                  resumable=True) as writer:
            (writer.partial_folder / PROGRESS_FILE).write_text('{"episode_rows": [{}]}')
            raise KeyboardInterrupt
    assert partial_dataset_episodes(root) == 1
    assert record_demos("pi0_torch/Reach-v0", 2, root, **SETTINGS, overwrite=True).episodes == 2
    assert record_demos("pi0_torch/Reach-v0", 2, tmp_path / "fresh", **SETTINGS, resume=True).episodes == 2


@pytest.mark.parametrize(("args", "message"), [
    (("--seed", "-1"), "--seed must be an integer in [0, "),
    (("--seed", str(2**64 + 1)), "--seed must be an integer in [0, "),  # once failed after recording everything
    (("--episodes", "0"), "--episodes must be an integer in [1, "),
    (("--image-size", "3"), "--image-size must be an integer in [8, "),
    (("--output-dir", "file.txt"), "file.txt exists and is not a folder"),
    (("--output-dir", "locked/reach"), "Permission denied"),
    (("--output-dir", "file.txt/reach"), "Not a directory"),
    (("--output-dir", "."), "is the working directory"),
])
def test_unusable_settings_fail_in_one_line_before_recording(args: tuple[str, ...], message: str, tmp_path: Path) -> None:
    """Issue 28.8: a file, an unwritable folder, a bad seed gave a traceback (a seed over 2**64 only after recording
    everything)."""
    (tmp_path / "file.txt").write_text("mine")
    (tmp_path / "locked").mkdir(mode=0o500)
    if os.geteuid() == 0 and "locked/reach" in args:
        pytest.skip("root writes into read-only folders")
    options = {"--output-dir": "reach", "--episodes": "2", "--image-size": "16", **dict(zip(args[::2], args[1::2]))}
    finished = demos(tmp_path, "--storage", "image", *[part for item in options.items() for part in item])
    assert finished.returncode != 0
    err = finished.stderr.strip()
    assert err.startswith("pi0-torch demos: error: ") and message in err and "\n" not in err, err
    assert (tmp_path / "file.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "locked"]


def test_a_failure_while_recording_says_how_to_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills while the metadata is written, after the episodes were flushed: one line that says how many
    episodes are kept and how to continue; `--resume` then only writes the metadata."""
    write_table, calls = pq.write_table, [0]

    def full_disk(*args: object, **kwargs: object) -> None:
        calls[0] += 1
        if calls[0] == 2:  # the first is the data file of the 3 episodes
            raise OSError(errno.ENOSPC, "No space left on device")
        write_table(*args, **kwargs)

    command = ["demos", "--env", "pi0_torch/Reach-v0", "--episodes", "3", "--output-dir", str(tmp_path / "reach"),
               "--storage", "image", "--image-size", "16"]
    monkeypatch.setattr(pq, "write_table", full_disk)
    with pytest.raises(SystemExit) as failed:
        main(command)
    text = str(failed.value)
    assert text == ("pi0-torch demos: error: [Errno 28] No space left on device; 3 episodes are kept: run the same "
                    "command with --resume to continue"), text
    monkeypatch.undo()
    assert main([*command, "--resume"]) == 0
    assert len(LeRobotEpisodeDataset(tmp_path / "reach", 4, progress=False).episodes) == 3
