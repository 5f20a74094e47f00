"""Folders that appear whole or not at all, and cleaning up after runs that died while writing one.

Every folder this package writes for the user (a converted checkpoint, a training checkpoint, a downloaded
checkpoint, a dataset) is first written into a hidden *partial* folder beside its final place, named
`.{name}.partial-{tag}`, and renamed into place only once it is complete. A rename within one file system is atomic,
so a reader sees either nothing or the whole folder.

A run that is killed (SIGKILL, out of memory, a lost node) cannot remove its partial folder. Each partial folder
therefore holds an owner file naming the process that writes it (host, pid and that process's start time, so a
recycled pid is not mistaken for the owner). The next run that writes beside it removes partial folders whose owner
is dead on this host ([`remove_stale_partials`]); folders of live runs, of other hosts, or without an owner file are
left alone.

```python
>>> import tempfile
>>> from pathlib import Path
>>> parent = Path(tempfile.mkdtemp())
>>> with atomic_output_dir(parent / "model") as folder:
...     _ = (folder / "weights.bin").write_bytes(b"...")
>>> sorted(p.name for p in parent.iterdir())  # only the finished folder; the owner file is gone too
['model']
>>> sorted(p.name for p in (parent / "model").iterdir())
['weights.bin']

```
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil

logger = logging.getLogger(__name__)

OWNER_FILE = ".pi0-torch-owner.json"
PARTIAL_MARKER = ".partial-"
RESUMABLE_TAG = "resumable"  # the fixed tag of a partial folder that a later run continues (a download)


class OutputPathError(ValueError):
    """An output location that cannot be used (it overlaps the input, or exists and may not be replaced)."""


def partial_name(final_name: str, tag: str | None = None) -> str:
    """The hidden name of the partial folder of `final_name` (a random tag unless one is given)."""
    return f".{final_name}{PARTIAL_MARKER}{tag or uuid.uuid4().hex[:8]}"


def check_separate(input_path: str | os.PathLike[str], output_path: str | os.PathLike[str]) -> None:
    """Refuse an output folder that equals, contains or lies inside the input (symlinks resolved).

    Replacing such an output would delete the input it is made from.
    """
    source, target = Path(input_path).expanduser().resolve(), Path(output_path).expanduser().resolve()
    if source == target:
        raise OutputPathError(f"output folder {output_path} is the input {input_path}; choose another --output-dir")
    if source.is_relative_to(target):
        raise OutputPathError(f"output folder {output_path} contains the input {input_path}; choose another --output-dir")
    if target.is_relative_to(source):
        raise OutputPathError(f"output folder {output_path} lies inside the input {input_path}; choose another --output-dir")


def check_output_dir(output_dir: Path, overwrite: bool) -> None:
    """An output folder may be absent or empty; a non-empty one only with `overwrite`."""
    if output_dir.exists() and not output_dir.is_dir():
        raise OutputPathError(f"output path {output_dir} exists and is not a folder")
    if output_dir.is_dir() and any(output_dir.iterdir()) and not overwrite:
        raise OutputPathError(f"output folder {output_dir} exists and is not empty (pass --overwrite to replace it)")


def claim(folder: Path) -> None:
    """Write the owner file of a partial folder: this host, this process and its start time."""
    me = psutil.Process()
    owner = {"host": socket.gethostname(), "pid": me.pid, "started": me.create_time()}
    (folder / OWNER_FILE).write_text(json.dumps(owner))


def _owner_is_dead(folder: Path) -> bool:
    """True only when the owner file says this host and no process with that pid and start time is running."""
    try:
        owner = json.loads((folder / OWNER_FILE).read_text())
        host, pid, started = owner["host"], int(owner["pid"]), float(owner["started"])
    except (OSError, ValueError, KeyError, TypeError):
        return False  # not ours, or being written right now: leave it
    if host != socket.gethostname():
        return False
    try:
        return abs(psutil.Process(pid).create_time() - started) > 1.0  # a recycled pid belongs to another process
    except psutil.NoSuchProcess:
        return True
    except psutil.Error:
        return False


def remove_stale_partials(parent: str | os.PathLike[str]) -> list[Path]:
    """Remove the partial folders in `parent` whose owner died on this host; returns what was removed.

    Resumable partial folders ([`resumable_output_dir`]) are kept: the next run of their owner's job continues them."""
    parent = Path(parent)
    removed = []
    if not parent.is_dir():
        return removed
    for folder in parent.iterdir():
        resumable = folder.name.endswith(PARTIAL_MARKER + RESUMABLE_TAG)
        if folder.name.startswith(".") and PARTIAL_MARKER in folder.name and not resumable and folder.is_dir() and _owner_is_dead(folder):
            shutil.rmtree(folder, ignore_errors=True)
            logger.info("removed %s, left behind by a run that died while writing it", folder)
            removed.append(folder)
    return removed


def publish(partial: Path, final: Path) -> None:
    """Rename a finished partial folder to `final` (replacing an existing `final`), dropping its owner file."""
    (partial / OWNER_FILE).unlink(missing_ok=True)
    if final.exists():
        retired = final.with_name(partial_name(final.name, "old-" + uuid.uuid4().hex[:8]))
        final.rename(retired)
        partial.rename(final)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        partial.rename(final)


@contextmanager
def atomic_output_dir(output_dir: str | os.PathLike[str], overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh partial folder next to `output_dir`; on success it replaces `output_dir`, on failure it is
    removed (with any parent folders created for it), so a failed run leaves nothing behind. Stale partial folders
    of dead runs beside it are removed first."""
    output_dir = Path(output_dir).expanduser().absolute()
    check_output_dir(output_dir, overwrite)
    created = [p for p in (output_dir.parent, *output_dir.parent.parents) if not p.exists()]
    output_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(output_dir.parent)
    partial = output_dir.with_name(partial_name(output_dir.name))
    partial.mkdir()
    try:
        claim(partial)
        yield partial
        check_output_dir(output_dir, overwrite)  # it may have appeared meanwhile
        publish(partial, output_dir)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        for parent in created:  # innermost first
            try:
                parent.rmdir()
            except OSError:
                break
        raise


@contextmanager
def resumable_output_dir(output_dir: str | os.PathLike[str]) -> Iterator[Path]:
    """Like [`atomic_output_dir`], but the partial folder has a fixed name and is KEPT when the block fails, so that
    the next call continues what it holds (a download resumes its files). It is published only when the block
    succeeds. Refuses (`OutputPathError`) when a live run (or one on another host) holds the partial folder."""
    output_dir = Path(output_dir).expanduser().absolute()
    partial = output_dir.with_name(partial_name(output_dir.name, RESUMABLE_TAG))
    if partial.is_dir() and (partial / OWNER_FILE).exists() and not _owner_is_dead(partial):
        raise OutputPathError(f"{partial} is being written by another run (see its {OWNER_FILE}); wait for it, or remove the folder if that run is gone")
    partial.mkdir(parents=True, exist_ok=True)
    claim(partial)
    try:
        yield partial
    except BaseException:
        (partial / OWNER_FILE).unlink(missing_ok=True)  # free for the next run, which continues it
        raise
    publish(partial, output_dir)
