"""Folders that appear whole or not at all, and cleaning up after runs that died while writing one.

Every folder this package writes for the user (a converted checkpoint, a training checkpoint, a downloaded
checkpoint, a dataset) is first written into a hidden *partial* folder beside its final place, named
`.{name}.partial-{tag}`, and renamed into place only once it is complete. A rename within one file system is atomic,
so a reader sees either nothing or the whole folder.

Before the rename, every file and folder of the partial folder is flushed to disk (`fsync`), and the parent folder
after it, so that a power loss cannot publish a folder of empty or truncated files.

**What may be replaced.** A command writes only where [`check_output_dir`] allows: an absent or empty folder; a
non-empty one only with `overwrite` (`--overwrite`), and only when everything in it was written by pi0-torch. Each
folder written here carries a manifest, `.pi0-torch-manifest.json`, listing its files ([`record_written`]); a file
that is not listed (a user's notes, another project's output, an older folder without a manifest) makes the folder
off-limits even with `overwrite`. The working directory, its parents, the home folder and a file-system root are
never written or replaced.

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
>>> sorted(p.name for p in (parent / "model").iterdir())  # and the manifest of what pi0-torch wrote
['.pi0-torch-manifest.json', 'weights.bin']
>>> with atomic_output_dir(parent / "model") as folder:  # a non-empty folder needs overwrite=True
...     pass
Traceback (most recent call last):
pi0_torch.utils.files.OutputPathError: output folder .../model exists and is not empty (pass --overwrite to replace it)

```
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import shutil
import socket
import stat
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path


logger = logging.getLogger(__name__)

OWNER_FILE = ".pi0-torch-owner.json"
MANIFEST_FILE = ".pi0-torch-manifest.json"  # the files pi0-torch wrote into a folder (see the module docstring)
SHOWN_FOREIGN_FILES = 5  # foreign files named in a refusal
PARTIAL_MARKER = ".partial-"
LOCK_SUFFIX = ".pi0-torch-lock"  # `.{name}.pi0-torch-lock` beside a folder a run holds (`output_lock`)
RESUMABLE_TAG = "resumable"  # the fixed tag of a partial folder that a later run continues (a download)


class OutputPathError(ValueError):
    """An output location that cannot be used (it overlaps the input, or exists and may not be replaced)."""


def check_writable(output_dir: str | os.PathLike[str], what: str) -> None:
    """Refuse (`OutputPathError` naming `what`) an output folder whose file system refuses a file: a read-only or full
    one. The folder or its nearest existing parent gets a small probe file, removed at once."""
    folder = Path(output_dir)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".pi0-torch-probe-") as probe:
            probe.write(b"\0" * 4096)
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as error:
        raise OutputPathError(f"{what} {output_dir}: cannot write there ({error.strerror or error}); nothing was run") from None


def write_text_atomically(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file beside it, renamed into place: the file is whole or absent."""
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    temporary.replace(path)


def give_default_mode(path: Path) -> None:
    """Give the file `path` the permissions a file newly created beside it gets (0o666 less the umask, usually 0644):
    safetensors' `save_file` creates its files 0600, readable by their owner only, unlike the other files of a model
    folder and unlike the weights the converter writes."""
    probe = path.with_name(f".{path.name}.mode-{uuid.uuid4().hex}")
    os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    try:
        os.chmod(path, stat.S_IMODE(probe.stat().st_mode))
    finally:
        probe.unlink()


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


def check_output_dir(output_dir: str | os.PathLike[str], overwrite: bool) -> None:
    """Refuse (`OutputPathError`) an output folder this package may not write or replace.

    Allowed: an absent or empty folder; a non-empty one only with `overwrite`, and only when every file in it is
    listed in its manifest (written by pi0-torch). Never a file, the working directory or one of its parents, the
    home folder or a file-system root (symlinks resolved)."""
    output_dir = Path(output_dir).expanduser()
    if output_dir.exists() and not output_dir.is_dir():
        raise OutputPathError(f"output path {output_dir} exists and is not a folder")
    protected = _protected_reason(output_dir)
    if protected:
        raise OutputPathError(f"output folder {output_dir} is {protected}; pi0-torch never writes or replaces it "
                              "(choose a new folder)")
    if not output_dir.is_dir() or not any(output_dir.iterdir()):
        return
    foreign = list(itertools.islice(foreign_files(output_dir), SHOWN_FOREIGN_FILES + 1))
    if foreign:
        shown = ", ".join(foreign[:SHOWN_FOREIGN_FILES]) + (" ..." if len(foreign) > SHOWN_FOREIGN_FILES else "")
        raise OutputPathError(f"output folder {output_dir} holds files that pi0-torch did not write ({shown}); "
                              "choose a new or empty folder (pi0-torch replaces only folders it wrote, and never "
                              "with files of others in them, even with --overwrite)")
    if not overwrite:
        raise OutputPathError(f"output folder {output_dir} exists and is not empty (pass --overwrite to replace it)")


def _protected_reason(path: Path) -> str | None:
    """Why `path` may never be an output folder, or None."""
    resolved = path.resolve()
    if resolved.parent == resolved:
        return "a file-system root"
    if resolved == Path.home().resolve():
        return "the home folder"
    working = Path.cwd().resolve()
    if working == resolved:
        return "the working directory"
    if working.is_relative_to(resolved):
        return "a parent of the working directory"
    return None


def written_files(folder: Path) -> set[str]:
    """The files (paths relative to `folder`, with `/`) that its manifest lists; empty without a readable one."""
    try:
        listed = json.loads((folder / MANIFEST_FILE).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return set()
    return {name for name in listed if isinstance(name, str)} if isinstance(listed, list) else set()


def record_written(folder: Path, paths: Iterable[Path]) -> None:
    """Add the files at or under `paths` (inside `folder`) to `folder`'s manifest, which is replaced atomically.

    Entries of files deleted since stay listed: a listed name only ever allows replacing what sits there."""
    listed = written_files(folder)
    for path in paths:
        for file in [path] if path.is_file() or path.is_symlink() else _files_under(path):
            listed.add(file.relative_to(folder).as_posix())
    listed.discard(MANIFEST_FILE)
    manifest = folder / MANIFEST_FILE
    staged = manifest.with_name(f"{MANIFEST_FILE}.{uuid.uuid4().hex[:8]}.tmp")
    staged.write_text(json.dumps({"written_by": "pi0-torch", "files": sorted(listed)}, indent=0) + "\n")
    fsync_file(staged)
    staged.replace(manifest)


def foreign_files(folder: Path) -> Iterator[str]:
    """The files under `folder` that its manifest does not list (relative paths; symlinks count as files), lazily:
    a refusal needs only the first few of a large folder."""
    listed = written_files(folder) | {MANIFEST_FILE}
    return (name for file in _files_under(folder) if (name := file.relative_to(folder).as_posix()) not in listed)


def _files_under(folder: Path) -> Iterator[Path]:
    """Every file and symlink under `folder` (symlinked folders are not followed)."""
    for root, folders, names in os.walk(folder):
        base = Path(root)
        yield from (base / name for name in names)
        yield from (base / name for name in folders if (base / name).is_symlink())


def sync_tree(folder: Path) -> None:
    """Flush every file under `folder` and every folder (itself included) to disk (`fsync`)."""
    for root, _, names in os.walk(folder):
        for name in names:
            path = Path(root) / name
            if not path.is_symlink():
                fsync_file(path)
        sync_folder(Path(root))


def fsync_file(path: Path) -> None:
    """Flush one file's contents to disk."""
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries (names created, renamed or removed in it) to disk; a no-op where folders cannot be
    opened (Windows)."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass  # some file systems refuse fsync on folders
    finally:
        os.close(descriptor)


def _this_process() -> dict[str, object]:
    """This host, this process and its start time (a recycled pid is another process)."""
    import psutil  # (imported where used: a torch-free deploy install may lack it)

    me = psutil.Process()
    return {"host": socket.gethostname(), "pid": me.pid, "started": me.create_time()}


def claim(folder: Path) -> None:
    """Write the owner file of a partial folder: this host, this process and its start time."""
    (folder / OWNER_FILE).write_text(json.dumps(_this_process()))


def _owner_is_dead(folder: Path) -> bool:
    """True only when the owner file says this host and no process with that pid and start time is running."""
    try:
        owner = json.loads((folder / OWNER_FILE).read_text())
        host, pid, started = owner["host"], int(owner["pid"]), float(owner["started"])
    except (OSError, ValueError, KeyError, TypeError):
        return False  # not ours, or being written right now: leave it
    if host != socket.gethostname():
        return False
    import psutil

    try:
        return abs(psutil.Process(pid).create_time() - started) > 1.0  # a recycled pid belongs to another process
    except psutil.NoSuchProcess:
        return True
    except psutil.Error:
        return False


def in_use(partial: Path) -> bool:
    """Whether a live run (or one on another host) holds the partial folder `partial` (its owner file says so)."""
    return (partial / OWNER_FILE).exists() and not _owner_is_dead(partial)


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
    """Rename a finished partial folder to `final` (replacing an existing `final`), dropping its owner file. Its
    files and folders are flushed to disk first, and the parent folder after the rename."""
    (partial / OWNER_FILE).unlink(missing_ok=True)
    sync_tree(partial)
    if final.exists():
        retired = final.with_name(partial_name(final.name, "old-" + uuid.uuid4().hex[:8]))
        final.rename(retired)
        partial.rename(final)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        partial.rename(final)
    sync_folder(final.parent)


@contextmanager
def atomic_output_dir(output_dir: str | os.PathLike[str], overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh partial folder next to `output_dir`; on success it replaces `output_dir` (with a manifest of
    its files), on failure it is removed (with any parent folders created for it), so a failed run leaves nothing
    behind. `output_dir` must pass [`check_output_dir`] (before and after the block). Stale partial folders of dead
    runs beside it are removed first."""
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
        (partial / OWNER_FILE).unlink(missing_ok=True)
        record_written(partial, [partial])
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
def output_lock(output_dir: str | os.PathLike[str], what: str = "--output-dir") -> Iterator[None]:
    """Hold `output_dir` for one run: an exclusive lock (`flock`) on `.{name}.pi0-torch-lock` beside it, naming the
    holder (host, pid, start time). A second run into the same folder is refused in one line (`OutputPathError`)
    instead of mixing its checkpoints with the first's. The kernel drops the lock when its process dies, however it
    dies, so a killed run never leaves a stale lock; the file is removed when the block ends."""
    import fcntl

    output_dir = Path(output_dir).expanduser().absolute()
    lock = output_dir.with_name(f".{output_dir.name}{LOCK_SUFFIX}")
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        handle = open(lock, "a+")  # noqa: SIM115 (held for the block)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "a process that is starting"
            handle.close()
            raise OutputPathError(f"{output_dir} is being written by another run ({holder}); wait for it to finish or "
                                  f"choose another {what}") from None
        try:
            same = os.fstat(handle.fileno()).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:  # (else the holder removed the file as we opened it: lock the new one)
            break
        handle.close()
    try:
        handle.seek(0)
        handle.truncate()
        owner = _this_process()
        handle.write(f"pid {owner['pid']} on {owner['host']}")
        handle.flush()
        yield
    finally:
        lock.unlink(missing_ok=True)  # (while still locked: a run waiting on this file retries on the new one)
        handle.close()


@contextmanager
def resumable_output_dir(output_dir: str | os.PathLike[str], overwrite: bool | None = None) -> Iterator[Path]:
    """Like [`atomic_output_dir`], but the partial folder has a fixed name and is KEPT when the block fails, so that
    the next call continues what it holds (a download resumes its files, an evaluation its episodes). It is published
    only when the block succeeds, after [`check_output_dir`] with `overwrite` where that is given (what appeared in
    `output_dir` meanwhile is never replaced unasked). Refuses (`OutputPathError`) when a live run (or one on another
    host) holds the partial folder."""
    output_dir = Path(output_dir).expanduser().absolute()
    partial = output_dir.with_name(partial_name(output_dir.name, RESUMABLE_TAG))
    if partial.is_dir() and in_use(partial):
        raise OutputPathError(f"{partial} is being written by another run (see its {OWNER_FILE}); wait for it, or remove the folder if that run is gone")
    partial.mkdir(parents=True, exist_ok=True)
    claim(partial)
    try:
        yield partial
    except BaseException:
        (partial / OWNER_FILE).unlink(missing_ok=True)  # free for the next run, which continues it
        raise
    (partial / OWNER_FILE).unlink(missing_ok=True)
    if overwrite is not None:
        check_output_dir(output_dir, overwrite)
    record_written(partial, [partial])
    publish(partial, output_dir)
