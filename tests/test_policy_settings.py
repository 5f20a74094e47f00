"""Issue 38.2, 38.3, 38.5: a model folder carries the settings it was validated with (`policy_settings.json`), the
Python API picks CPU threads as the CLI does, and `pi0-torch eval` checks that its output folder can be written
before the first episode and prints its result whatever becomes of the files."""

from __future__ import annotations

import errno
import json
import logging
import shutil
from pathlib import Path

import pytest
import torch

from pi0_torch import demo_policy_dir
from pi0_torch.cli import main
from pi0_torch.demo import DEMO_NOISE_SCALE, DEMO_REPLAN_STEPS
from pi0_torch.runtime import rollout
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.policy_settings import SETTINGS_FILE, PolicySettings
from pi0_torch.utils import files


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_the_demo_policy_carries_the_settings_its_success_was_measured_with(caplog: pytest.LogCaptureFixture,
                                                                            restore_threads: None) -> None:
    """`PI0Policy.from_pretrained("demo")` (it failed, while `--policy demo` worked) runs with the noise scale of the
    documented success and tells clients the replan steps; an explicit argument wins."""
    assert PolicySettings.load(demo_policy_dir()) == PolicySettings(noise_scale=DEMO_NOISE_SCALE, replan_steps=DEMO_REPLAN_STEPS)
    with caplog.at_level(logging.INFO, logger="pi0_torch.runtime.policy_base"):
        policy = PI0Policy.from_pretrained("demo", device="cpu")
    assert policy.noise_scale == DEMO_NOISE_SCALE and policy.metadata["replan_steps"] == DEMO_REPLAN_STEPS
    assert f"using its recommended noise_scale {DEMO_NOISE_SCALE} ({SETTINGS_FILE})" in caplog.text
    assert PI0Policy.from_pretrained("demo", device="cpu", noise_scale=1.0).noise_scale == 1.0


def test_settings_files_are_checked_by_name(tmp_path: Path) -> None:
    for text, message in [('{"noise_scale": -1}', "noise_scale must be"), ('{"replan_step": 4}', "unknown settings \\['replan_step'\\]"),
                          ("[4]", "expected a JSON object"), ("{", "not a readable JSON file"),
                          ('{"rtc_method": "steer"}', "rtc_method must be one of")]:
        (tmp_path / SETTINGS_FILE).write_text(text)
        with pytest.raises(ValueError, match=message):
            PolicySettings.load(tmp_path)


def test_the_python_api_picks_cpu_threads_as_the_cli_does(restore_threads: None) -> None:
    """A policy under 10 M parameters runs on one CPU thread unless told otherwise (1.1-1.3 s a chunk on two busy
    cores, 21 ms on one); `threads` sets the count."""
    torch.set_num_threads(2)
    PI0Policy.from_pretrained("demo", device="cpu")
    assert torch.get_num_threads() == 1
    PI0Policy.from_pretrained("demo", device="cpu", threads=2)
    assert torch.get_num_threads() == 2
    with pytest.raises(ValueError, match=r"threads must be an integer in \[1, 1024\]"):
        PI0Policy.from_pretrained("demo", device="cpu", threads=10**6)


def test_eval_uses_the_recommended_replan_steps_and_says_so(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                                           restore_threads: None) -> None:
    assert main(["eval", "--policy", "demo", "--env", "pi0_torch/Reach-v0", "--episodes", "1", "--num-envs", "1",
                 "--output-dir", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert f"replan steps {DEMO_REPLAN_STEPS}: the policy's recommended setting ({SETTINGS_FILE}" in out, out
    assert json.loads((tmp_path / "out" / "eval.json").read_text())["replan_steps"] == DEMO_REPLAN_STEPS


def test_eval_refuses_an_unwritable_output_folder_before_the_first_episode(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full or read-only file system (simulated: root writes into read-only folders here) is found by a probe
    file before the policy loads: nothing runs."""
    episodes = []
    monkeypatch.setattr(rollout, "evaluate", lambda *args: episodes.append(args))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.tempfile, "NamedTemporaryFile", full)
    assert main(["eval", "--policy", "demo", "--env", "pi0_torch/Reach-v0", "--episodes", "1",
                 "--output-dir", str(tmp_path / "out")]) == 2
    assert f"--output-dir {tmp_path / 'out'}: cannot write there (No space left on device); nothing was run" in capsys.readouterr().err
    assert not episodes


def test_eval_prints_its_result_when_the_disk_fills_up_during_the_episodes(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, restore_threads: None
) -> None:
    """The folder was writable at the start and is full at the end: the success line still reaches the terminal."""

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rollout, "write_outputs", full)
    assert main(["eval", "--policy", "demo", "--env", "pi0_torch/Reach-v0", "--episodes", "1", "--num-envs", "1",
                 "--output-dir", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    assert "pi0_torch/Reach-v0 sync d=0 s=4: success" in captured.out, captured.out
    assert "the episodes ran, but" in captured.err and "No space left on device" in captured.err
    assert not (tmp_path / "out").exists()


def test_fine_tuned_copies_keep_their_settings(tmp_path: Path) -> None:
    """A folder copied with its files keeps its settings; one written without them has none (the defaults)."""
    shutil.copytree(demo_policy_dir(), tmp_path / "copy")
    assert PolicySettings.load(tmp_path / "copy").replan_steps == DEMO_REPLAN_STEPS
    (tmp_path / "copy" / SETTINGS_FILE).unlink()
    assert PI0Policy.from_pretrained(tmp_path / "copy", device="cpu").noise_scale == 1.0


BROKEN_JSON = {"nested 100,000 deep": ("[" * 100_000, "nested too deeply"), "empty": ("", "Expecting value"),
               "a 5,000-digit integer": ('{"a": ' + "9" * 5_000 + "}", "Exceeds the limit")}


@pytest.mark.parametrize("name", [SETTINGS_FILE, "norm_stats.json", "processor_config.json", "config.json"])
@pytest.mark.parametrize("broken", sorted(BROKEN_JSON))
def test_a_broken_json_file_of_a_policy_folder_is_one_line_naming_it(tmp_path: Path, name: str, broken: str) -> None:
    """Issue 63, round 5 items 9 and 11: a `policy_settings.json`, `config.json`, `norm_stats.json` or
    `processor_config.json` nested 100,000 deep gave a RecursionError traceback, an empty `norm_stats.json` or one
    with a 5,000-digit integer a parser message naming no file. Each is one line naming the file now."""
    folder = tmp_path / "policy"
    shutil.copytree(demo_policy_dir(), folder)
    text, reason = BROKEN_JSON[broken]
    (folder / name).write_text(text)
    with pytest.raises(ValueError, match=rf"^{folder / name}: not a readable JSON file \(.*{reason}") as refused:
        PI0Policy.from_pretrained(str(folder), device="cpu")
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("kind", ["a folder", "a link to /dev/zero"])
def test_a_settings_file_that_is_no_file_is_refused_not_skipped(tmp_path: Path, kind: str) -> None:
    """Issue 63, round 5 item 10: a `policy_settings.json` that was a folder, or a link to /dev/zero, was ignored and
    the defaults used."""
    if kind == "a folder":
        (tmp_path / SETTINGS_FILE).mkdir()
    else:
        (tmp_path / SETTINGS_FILE).symlink_to("/dev/zero")
    with pytest.raises(ValueError, match=rf"{SETTINGS_FILE}: expected a JSON file, found (a folder|no regular file)"):
        PolicySettings.load(tmp_path)


@pytest.mark.parametrize(("setting", "value", "config_setting"), [("pi05", True, "pi05"), ("action_horizon", 50, "action_horizon"),
                                                                   ("max_token_len", 20, "max_token_len")])
def test_a_processor_that_describes_another_model_is_refused(tmp_path: Path, setting: str, value: object,
                                                             config_setting: str) -> None:
    """Issue 63, round 5 item 10: `processor_config.json` with `pi05: true` beside a π0 model changed the actions by
    2.0, and a `config.json` at `action_horizon` 50 beside a model trained at 16 was taken; both were silent."""
    folder = tmp_path / "policy"
    shutil.copytree(demo_policy_dir(), folder)
    edited = "config.json" if setting == "action_horizon" else "processor_config.json"
    document = json.loads((folder / edited).read_text())
    document[setting] = value
    (folder / edited).write_text(json.dumps(document))
    with pytest.raises(ValueError, match=rf"the processor's {setting} is .* but the model's config.json has "
                                         rf"{config_setting} .*describe different models"):
        PI0Policy.from_pretrained(str(folder), device="cpu")
