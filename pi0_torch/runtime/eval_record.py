"""The append-only record of an evaluation, `episodes.jsonl`: each episode written as it ends, so that nothing
finished is lost however the run stops, and `pi0-torch eval --resume` continues from it.

Line 1 is the evaluation's identity (`{"evaluation": {...}}`: env, policy, seeds, execution and the other settings
its episodes depend on); then one line per finished episode (`{"episode": {...}}`) and one per policy call
(`{"call_ms": ...}`, for the latency summary). Each episode line is flushed to disk before the next step runs.

While the episodes run, the record lives in the output folder's partial folder (`.{name}.partial-resumable`, see
`pi0_torch.utils.files`); when the evaluation ends (finished, or stopped by Ctrl-C, SIGTERM or a failure) it is
published with `eval.json` into the output folder. A run killed outright (SIGKILL, out of memory) leaves the partial
folder: `--resume` continues from either place. Every episode's noise comes from its seed, so a resumed evaluation
gives the episodes an uninterrupted one gives.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

from pi0_torch.utils.files import RESUMABLE_TAG, partial_name

RECORD_FILE = "episodes.jsonl"


class EvalRecord:
    """`episodes.jsonl` in `folder`, open for appending: the `identity` line first (written by `start`), then what
    `add_episode` and `add_call` append. `episodes` / `calls_ms`: what it held when opened, plus what was added."""

    def __init__(self, folder: Path, identity: dict[str, Any], episodes: list[dict[str, Any]], calls_ms: list[float]) -> None:
        self.path = folder / RECORD_FILE
        self.identity, self.episodes, self.calls_ms = identity, episodes, calls_ms
        self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (closed by `close`)

    @classmethod
    def start(cls, folder: Path, identity: dict[str, Any], resumed: Path | None = None) -> EvalRecord:
        """A record in `folder`: a new one, or with `resumed` (a stopped evaluation's record file) its episodes and
        calls carried over (a `ValueError` naming what differs where its identity is not `identity`)."""
        episodes: list[dict[str, Any]] = []
        calls_ms: list[float] = []
        if resumed is not None:
            recorded, episodes, calls_ms = read_record(resumed)
            differing = sorted(key for key in set(identity) | set(recorded) if identity.get(key) != recorded.get(key))
            if differing:
                shown = ", ".join(f"{key} {recorded.get(key)!r} there, {identity.get(key)!r} now" for key in differing)
                raise ValueError(f"--resume: {resumed} records another evaluation ({shown}); resume it with the same "
                                 "settings, or start over with --overwrite")
        lines = [{"evaluation": identity}, *({"episode": episode} for episode in episodes),
                 *({"call_ms": call} for call in calls_ms)]
        folder.mkdir(parents=True, exist_ok=True)
        temporary = folder / f".{RECORD_FILE}.tmp"
        temporary.write_text("".join(json.dumps(line) + "\n" for line in lines), encoding="utf-8")
        os.replace(temporary, folder / RECORD_FILE)
        return cls(folder, identity, episodes, calls_ms)

    def add_episode(self, result: Any) -> None:
        """Append a finished episode (an `EpisodeResult`), flushed to disk."""
        episode = asdict(result)
        self.episodes.append(episode)
        self._file.write(json.dumps({"episode": episode}) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())

    def add_call(self, milliseconds: float) -> None:
        """Append one policy call's time (flushed, not synced: losing the last few costs nothing)."""
        self.calls_ms.append(milliseconds)
        self._file.write(json.dumps({"call_ms": milliseconds}) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_record(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]], list[float]]:
    """A record's identity, episodes and call times; a `ValueError` naming the file and line where it is not a
    record. A last line cut short (the run was killed while writing it) is dropped."""
    lines = path.read_text(encoding="utf-8").splitlines()
    identity: dict[str, Any] | None = None
    episodes: list[dict[str, Any]] = []
    calls_ms: list[float] = []
    for number, line in enumerate(lines, start=1):
        try:
            entry = json.loads(line)
        except ValueError:
            if number == len(lines):  # (cut short by a kill)
                break
            raise ValueError(f"{path} line {number} is not a record line (JSON)") from None
        if number == 1:
            if not isinstance(entry, dict) or not isinstance(entry.get("evaluation"), dict):
                raise ValueError(f"{path} is not an evaluation record (line 1 holds no 'evaluation')")
            identity = entry["evaluation"]
        elif isinstance(entry, dict) and isinstance(entry.get("episode"), dict):
            episodes.append(entry["episode"])
        elif isinstance(entry, dict) and isinstance(entry.get("call_ms"), (int, float)):
            calls_ms.append(float(entry["call_ms"]))
        else:
            raise ValueError(f"{path} line {number} is not a record line")
    if identity is None:
        raise ValueError(f"{path} is empty: not an evaluation record")
    return identity, episodes, calls_ms


def partial_folder(output_dir: Path) -> Path:
    """Where an evaluation into `output_dir` keeps its record while it runs."""
    return output_dir.with_name(partial_name(output_dir.name, RESUMABLE_TAG))


def stopped_record(output_dir: Path) -> Path | None:
    """The record of a stopped evaluation into `output_dir`: in its partial folder (killed), or published in the
    folder itself with an `eval.json` that says it is not complete; None where there is none."""
    killed = partial_folder(output_dir) / RECORD_FILE
    if killed.is_file():
        return killed
    published = output_dir / RECORD_FILE
    if published.is_file():
        try:
            complete = json.loads((output_dir / "eval.json").read_text()).get("complete", True)
        except (OSError, ValueError, AttributeError):
            complete = False  # (no readable eval.json: the record is what there is)
        return None if complete else published
    return None
