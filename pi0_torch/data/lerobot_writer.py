"""Write episodes as a LeRobot v3.0 dataset folder (the layout LeRobot itself writes).

```
meta/info.json                                    codebase_version "v3.0", fps, features, path templates, splits, counts
meta/tasks.parquet                                task string (index) -> task_index
meta/episodes/chunk-000/file-000.parquet          per episode: length, tasks, data and video file + offsets, stats
meta/stats.json                                   mean/std/min/max/count/q01/q99 of every vector feature
data/chunk-000/file-XXX.parquet                   one row per frame: vectors, timestamp, indices (and PNG images)
videos/<camera>/chunk-000/file-XXX.mp4            one video per group of `episodes_per_file` episodes (PyAV)
```

Cameras are stored as video (`storage="video"`, mp4 encoded with PyAV; frame k of an episode sits at
`from_timestamp + k / fps`) or as PNG bytes inside the parquet (`storage="image"`). The folder is assembled aside
and renamed into place whole (`pi0_torch.utils.files.atomic_output_dir`); `pi0_torch.data.LeRobotEpisodeDataset`
reads it back.

>>> import tempfile
>>> import numpy as np
>>> from pi0_torch.data import LeRobotEpisodeDataset
>>> frames = np.zeros((5, 16, 16, 3), np.uint8)
>>> episode = EpisodeRecord("wave", {"observation.images.top": frames},
...                         {"observation.state": np.zeros((5, 2), np.float32), "action": np.ones((5, 2), np.float32)})
>>> root = write_lerobot_dataset(tempfile.mkdtemp() + "/waves", [episode], fps=10, storage="image",
...                              vector_names={"observation.state": ["x", "y"], "action": ["x", "y"]})
>>> LeRobotEpisodeDataset(root, action_horizon=2, progress=False)[4]["prompt"]
'wave'
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from PIL import Image

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("datasets", "pandas", "pyarrow", "av"))
import datasets
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pi0_torch.data.video import encode_video
from pi0_torch.utils import files

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
INDEX_COLUMNS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
PROGRESS_FILE = ".pi0-torch-progress.json"  # in the partial folder of a resumable writer
Storage = Literal["video", "image"]


@dataclass
class EpisodeRecord:
    """One episode to write.

    Attributes:
        task: the instruction (LeRobot's task string).
        frames: camera key -> uint8 `[T, H, W, 3]` frames.
        vectors: feature name (e.g. `observation.state`, `action`) -> `[T, D]` values (stored as float32).
        extra: additional per-episode columns of `meta/episodes` (e.g. `{"seed": 3}`).
    """

    task: str
    frames: dict[str, np.ndarray]
    vectors: dict[str, np.ndarray]
    extra: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(next(iter(self.vectors.values())))


def png_bytes(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def vector_stats(values: np.ndarray) -> dict[str, list[float]]:
    """LeRobot's per-feature statistics of `[N, D]` values."""
    return {
        "mean": values.mean(0).tolist(), "std": values.std(0).tolist(), "min": values.min(0).tolist(),
        "max": values.max(0).tolist(), "count": [len(values)],
        "q01": np.quantile(values, 0.01, axis=0).tolist(), "q99": np.quantile(values, 0.99, axis=0).tolist(),
    }


def _check_episode(episode: EpisodeRecord, vector_names: dict[str, list[str]], camera_shapes: dict[str, tuple[int, ...]]) -> None:
    length = len(episode)
    if length < 1:
        raise ValueError(f"episode {episode.task!r} has no frames")
    if set(episode.vectors) != set(vector_names):
        raise ValueError(f"episode vectors must be {sorted(vector_names)}, got {sorted(episode.vectors)}")
    for name, values in episode.vectors.items():
        if np.shape(values) != (length, len(vector_names[name])):
            raise ValueError(f"episode {name} must have shape {(length, len(vector_names[name]))}, got {np.shape(values)}")
    if set(episode.frames) != set(camera_shapes):
        raise ValueError(f"episode cameras must be {sorted(camera_shapes)}, got {sorted(episode.frames)}")
    for key, frames in episode.frames.items():
        frames = np.asarray(frames)
        if frames.dtype != np.uint8 or frames.shape != (length, *camera_shapes[key]):
            raise ValueError(
                f"episode {key} must be uint8 {(length, *camera_shapes[key])}, got {frames.dtype} {frames.shape}"
            )


def write_lerobot_dataset(
    root: str | Path,
    episodes: Iterable[EpisodeRecord],
    *,
    fps: int,
    vector_names: dict[str, list[str]],
    storage: Storage = "video",
    codec: str = "libx264",
    episodes_per_file: int = 50,
    robot_type: str = "unknown",
    num_heldout: int = 0,
    tasks: Sequence[str] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write `episodes` (consumed one by one) to the LeRobot v3.0 folder `root` and return it; the folder appears
    whole or not at all (see [`LeRobotDatasetWriter`] for a dataset that survives an interruption).

    Args:
        fps: frames per second (timestamps are `frame_index / fps`).
        vector_names: vector feature name -> the names of its dimensions (its width), e.g.
            `{"observation.state": ["x", "y"], "action": ["dx", "dy"]}`; every episode holds exactly these.
        storage: cameras as "video" (mp4 per group of `episodes_per_file` episodes) or "image" (PNG in the parquet).
        codec: PyAV encoder for the videos (LeRobot defaults to libsvtav1; h264 decodes everywhere).
        num_heldout: the last `num_heldout` episodes form the `heldout` split of `meta/info.json`.
        tasks: the task strings in `task_index` order (default: in order of first appearance).
        overwrite: replace a non-empty `root` that pi0-torch wrote (otherwise it must be absent or empty).
    """
    with LeRobotDatasetWriter(root, fps=fps, vector_names=vector_names, storage=storage, codec=codec,
                              episodes_per_file=episodes_per_file, robot_type=robot_type, tasks=tasks,
                              overwrite=overwrite) as writer:
        for episode in episodes:
            writer.add(episode)
        return writer.finish(num_heldout)


class LeRobotDatasetWriter:
    """Writes a LeRobot v3.0 dataset folder episode by episode, in files of `episodes_per_file` episodes, into a
    hidden partial folder beside `root` that [`finish`] publishes whole (`pi0_torch.utils.files`).

    With `resumable=True` nothing written is lost to an interruption: every file of episodes is flushed to disk
    (`fsync`) together with a progress record (`.pi0-torch-progress.json`: the episodes' metadata, and the caller's
    `run_state` of the last one, e.g. the next seed), and the partial folder, named `.NAME.partial-resumable`, is
    kept when the writer fails or is killed. A later writer with `resume=True` continues it after its last flushed
    file (the settings must match, `run_settings` included: each difference is named); one without `resume` refuses
    it unless `overwrite` (which starts over).

    ```python
    with LeRobotDatasetWriter(root, fps=10, vector_names=names, resumable=True, resume=True) as writer:
        for episode in make_episodes(start=writer.run_state.get("next", 0)):
            writer.add(episode, run_state={"next": ...})
        writer.finish()
    ```
    """

    def __init__(
        self,
        root: str | Path,
        *,
        fps: int,
        vector_names: dict[str, list[str]],
        storage: Storage = "video",
        codec: str = "libx264",
        episodes_per_file: int = 50,
        robot_type: str = "unknown",
        tasks: Sequence[str] | None = None,
        overwrite: bool = False,
        resumable: bool = False,
        resume: bool = False,
        run_settings: dict[str, Any] | None = None,
    ) -> None:
        if storage not in ("video", "image"):
            raise ValueError(f"storage must be 'video' or 'image', got {storage!r}")
        if episodes_per_file < 1:
            raise ValueError(f"episodes_per_file must be >= 1, got {episodes_per_file}")
        self.root = Path(root).expanduser().absolute()
        self.fps, self.vector_names, self.storage, self.codec = fps, vector_names, storage, codec
        self.episodes_per_file, self.robot_type, self.tasks = episodes_per_file, robot_type, tasks
        self.overwrite, self.resumable, self.resume = overwrite, resumable, resume
        self.settings = {"fps": fps, "vector_names": vector_names, "storage": storage, "codec": codec,
                         "episodes_per_file": episodes_per_file, "robot_type": robot_type,
                         "tasks": list(tasks) if tasks is not None else None, "run": run_settings or {}}
        self.task_index: dict[str, int] = {task: i for i, task in enumerate(tasks or ())}
        self.camera_shapes: dict[str, tuple[int, ...]] | None = None
        self.episode_rows: list[dict[str, Any]] = []
        self.total_frames = 0
        self.file_index = 0
        self.run_state: dict[str, Any] = {}  # the caller's state after the last flushed episode
        self.all_vectors: dict[str, list[np.ndarray]] = {name: [] for name in vector_names}  # for meta/stats.json
        self._group: list[tuple[EpisodeRecord, dict[str, Any] | None]] = []
        self._folders = contextlib.ExitStack()
        self._finished = False
        self.folder: Path | None = None

    @property
    def partial_folder(self) -> Path:
        """Where a resumable writer keeps its unfinished dataset."""
        return self.root.with_name(files.partial_name(self.root.name, files.RESUMABLE_TAG))

    @property
    def episodes_written(self) -> int:
        """Episodes flushed to disk so far (a resumed writer starts with those of the earlier run)."""
        return len(self.episode_rows)

    def __enter__(self) -> LeRobotDatasetWriter:
        files.check_output_dir(self.root, self.overwrite)
        if not self.resumable:
            self.folder = self._folders.enter_context(files.atomic_output_dir(self.root, overwrite=self.overwrite))
            return self
        partial = self.partial_folder
        if files.in_use(partial):
            raise files.OutputPathError(f"{partial} is being written by another run (see its {files.OWNER_FILE})")
        if (partial / PROGRESS_FILE).is_file() and not self.resume and not self.overwrite:
            raise files.OutputPathError(f"{partial} holds {partial_dataset_episodes(self.root)} episodes of an "
                                        "interrupted run: pass --resume to continue it, or --overwrite to start over")
        restoring = self.resume and (partial / PROGRESS_FILE).is_file()
        self.folder = self._folders.enter_context(files.resumable_output_dir(self.root))
        if restoring:
            try:
                self._restore()
            except BaseException:
                self._folders.__exit__(*sys.exc_info())  # keeps the partial folder for a later --resume
                raise
        else:  # a fresh start: nothing of an earlier run (or of one killed before its first flush) stays
            for entry in self.folder.iterdir():
                if entry.is_dir():
                    shutil.rmtree(entry)
                elif entry.name != files.OWNER_FILE:
                    entry.unlink()
        return self

    def __exit__(self, kind: Any, error: Any, traceback: Any) -> bool | None:
        if kind is None and not self._finished:
            kind, error = RuntimeError, RuntimeError("LeRobotDatasetWriter: finish() was not called")
            traceback = None
        return self._folders.__exit__(kind, error, traceback)

    def add(self, episode: EpisodeRecord, run_state: dict[str, Any] | None = None) -> None:
        """Queue one episode; every `episodes_per_file` episodes are written (and, resumable, flushed) as one file.
        `run_state`: the caller's state after this episode, saved with the file it lands in."""
        if episode.task not in self.task_index:
            if self.tasks is not None:
                raise ValueError(f"episode task {episode.task!r} is not among the given tasks {list(self.tasks)}")
            self.task_index[episode.task] = len(self.task_index)
        self._group.append((episode, run_state))
        if len(self._group) == self.episodes_per_file:
            self._flush()

    def finish(self, num_heldout: int = 0) -> Path:
        """Write the last file and the metadata; the folder is published when the `with` block ends."""
        if self._group:
            self._flush()
        if not self.episode_rows:
            raise ValueError("no episodes to write")
        if not 0 <= num_heldout < len(self.episode_rows):
            raise ValueError(f"num_heldout must be in [0, {len(self.episode_rows)}), got {num_heldout}")
        self._write_meta(num_heldout)
        (self._folder / PROGRESS_FILE).unlink(missing_ok=True)
        self._finished = True
        return self.root

    @property
    def _folder(self) -> Path:
        if self.folder is None:
            raise RuntimeError("LeRobotDatasetWriter is used outside its `with` block")
        return self.folder

    def _flush(self) -> None:
        episodes = [episode for episode, _ in self._group]
        states = [state for _, state in self._group if state is not None]
        written = self._write_file(episodes)
        self._group = []
        if states:
            self.run_state = states[-1]
        if self.resumable:  # the files and their folder entries are on disk before the record that names them
            for path in written:
                files.fsync_file(path)
                files.sync_folder(path.parent)
            self._save_progress()

    def _save_progress(self) -> None:
        progress = {
            "settings": self.settings, "task_index": self.task_index, "episode_rows": self.episode_rows,
            "total_frames": self.total_frames, "file_index": self.file_index, "run_state": self.run_state,
            "camera_shapes": {key: list(shape) for key, shape in (self.camera_shapes or {}).items()},
        }
        staged = self._folder / (PROGRESS_FILE + ".tmp")
        staged.write_text(json.dumps(progress, default=_plain))
        files.fsync_file(staged)
        staged.replace(self._folder / PROGRESS_FILE)
        files.sync_folder(self._folder)

    def _restore(self) -> None:
        """Continue the partial folder after its last flushed file (files of an unflushed one are removed)."""
        progress = json.loads((self._folder / PROGRESS_FILE).read_text())
        saved = progress["settings"]
        differing = [f"{name} {saved.get(name)!r} there, {value!r} now" for name, value in self.settings.items()
                     if name != "run" and saved.get(name) != _plain_json(value)]
        differing += [f"{name} {saved['run'].get(name)!r} there, {value!r} now" for name, value in
                      self.settings["run"].items() if saved.get("run", {}).get(name) != _plain_json(value)]
        if differing:
            raise ValueError(f"--resume: the partial dataset {self._folder} was written with other settings: "
                             f"{'; '.join(differing)}; resume with the same settings, or pass --overwrite to start over")
        self.task_index = progress["task_index"]
        self.episode_rows = progress["episode_rows"]
        self.total_frames, self.file_index = progress["total_frames"], progress["file_index"]
        self.run_state = progress["run_state"]
        self.camera_shapes = {key: tuple(shape) for key, shape in progress["camera_shapes"].items()} or None
        for path in [*self._folder.glob("data/*/*.parquet"), *self._folder.glob("videos/*/*/*.mp4")]:
            if int(path.stem.split("-")[-1]) >= self.file_index:
                path.unlink()  # written after the last progress record: its episodes are recorded again
        shutil.rmtree(self._folder / "meta", ignore_errors=True)  # (written only by finish, which did not end)
        for number in range(self.file_index):
            table = pq.read_table(self._folder / DATA_PATH.format(chunk_index=0, file_index=number),
                                  columns=list(self.vector_names))
            for name in self.vector_names:
                self.all_vectors[name].append(np.asarray(table[name].to_pylist(), np.float32))

    def hf_features(self) -> datasets.Features:
        assert self.camera_shapes is not None
        return datasets.Features(
            {
                **({key: datasets.Image() for key in self.camera_shapes} if self.storage == "image" else {}),
                **{
                    name: datasets.Sequence(datasets.Value("float32"), length=len(names))
                    for name, names in self.vector_names.items()
                },
                "timestamp": datasets.Value("float32"),
                **{name: datasets.Value("int64") for name in INDEX_COLUMNS[1:]},
            }
        )

    def _write_file(self, episodes: list[EpisodeRecord]) -> list[Path]:
        """Write one data file (and its videos) of `episodes`; returns the paths written."""
        if self.camera_shapes is None:
            self.camera_shapes = {key: tuple(np.shape(frames)[1:]) for key, frames in episodes[0].frames.items()}
        hf_features = self.hf_features()
        columns: dict[str, list[Any]] = {name: [] for name in hf_features}
        video_frames: dict[str, list[np.ndarray]] = {key: [] for key in self.camera_shapes}
        for episode in episodes:
            _check_episode(episode, self.vector_names, self.camera_shapes)
            length, first = len(episode), self.total_frames
            vectors = {name: np.asarray(values, np.float32) for name, values in episode.vectors.items()}
            video_offset = len(next(iter(video_frames.values()), []))
            self.episode_rows.append(
                {
                    "episode_index": len(self.episode_rows),
                    "tasks": [episode.task],
                    "length": length,
                    "data/chunk_index": 0,
                    "data/file_index": self.file_index,
                    "dataset_from_index": first,
                    "dataset_to_index": first + length,
                    **{
                        f"videos/{key}/{column}": value
                        for key in (self.camera_shapes if self.storage == "video" else ())
                        for column, value in (
                            ("chunk_index", 0), ("file_index", self.file_index),
                            ("from_timestamp", video_offset / self.fps), ("to_timestamp", (video_offset + length) / self.fps),
                        )
                    },
                    "meta/episodes/chunk_index": 0,
                    "meta/episodes/file_index": 0,
                    **{
                        f"stats/{name}/{stat}": value
                        for name, values in vectors.items()
                        for stat, value in vector_stats(values).items()
                    },
                    **episode.extra,
                }
            )
            for name, values in vectors.items():
                self.all_vectors[name].append(values)
                columns[name].extend(values.tolist())
            columns["timestamp"].extend(t / self.fps for t in range(length))
            columns["frame_index"].extend(range(length))
            columns["episode_index"].extend([len(self.episode_rows) - 1] * length)
            columns["index"].extend(range(first, first + length))
            columns["task_index"].extend([self.task_index[episode.task]] * length)
            for key, frames in episode.frames.items():
                if self.storage == "image":
                    columns[key].extend({"bytes": png_bytes(frame), "path": None} for frame in frames)
                else:
                    video_frames[key].extend(frames)
            self.total_frames += length
        data_path = self._folder / DATA_PATH.format(chunk_index=0, file_index=self.file_index)
        data_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pydict(columns, schema=hf_features.arrow_schema), data_path)
        written = [data_path]
        for key, frames in video_frames.items():
            if frames:
                path = self._folder / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=self.file_index)
                encode_video(path, frames, self.fps, self.codec)
                written.append(path)
        self.file_index += 1
        return written

    def features(self) -> dict[str, dict[str, Any]]:
        assert self.camera_shapes is not None
        features: dict[str, dict[str, Any]] = {}
        for key, shape in self.camera_shapes.items():
            camera: dict[str, Any] = {"dtype": self.storage, "shape": list(shape), "names": ["height", "width", "channels"]}
            if self.storage == "video":
                camera["info"] = {
                    "video.height": shape[0], "video.width": shape[1], "video.codec": self.codec,
                    "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "video.fps": self.fps,
                    "video.channels": shape[2], "has_audio": False,
                }
            features[key] = camera
        for name, names in self.vector_names.items():
            features[name] = {"dtype": "float32", "shape": [len(names)], "names": list(names)}
        features["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
        for name in INDEX_COLUMNS[1:]:
            features[name] = {"dtype": "int64", "shape": [1], "names": None}
        return features

    def _write_meta(self, num_heldout: int) -> None:
        task_index = self.task_index
        meta = self._folder / "meta"
        (meta / "episodes" / "chunk-000").mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist(self.episode_rows), meta / "episodes" / "chunk-000" / "file-000.parquet")
        # LeRobot's tasks table: a pandas frame indexed by the task string, one column task_index
        pd.DataFrame({"task_index": list(task_index.values())}, index=pd.Index(list(task_index), name="task")).to_parquet(
            meta / "tasks.parquet"
        )
        stats = {name: vector_stats(np.concatenate(values)) for name, values in self.all_vectors.items()}
        (meta / "stats.json").write_text(json.dumps(stats, indent=2))
        num_episodes = len(self.episode_rows)
        splits = {"train": f"0:{num_episodes - num_heldout}"}
        if num_heldout:
            splits["heldout"] = f"{num_episodes - num_heldout}:{num_episodes}"
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": self.robot_type,
            "total_episodes": num_episodes,
            "total_frames": self.total_frames,
            "total_tasks": len(task_index),
            "chunks_size": 1000,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500,
            "fps": self.fps,
            "splits": splits,
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.storage == "video" else None,
            "features": self.features(),
        }
        (meta / "info.json").write_text(json.dumps(info, indent=4))


def partial_dataset_episodes(root: str | Path) -> int:
    """Episodes flushed into the resumable partial folder of `root` (0 when there is none or it has no record)."""
    root = Path(root).expanduser().absolute()
    progress = root.with_name(files.partial_name(root.name, files.RESUMABLE_TAG)) / PROGRESS_FILE
    try:
        return len(json.loads(progress.read_text())["episode_rows"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _plain(value: Any) -> Any:
    """JSON for numpy scalars and arrays in progress records."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot store {type(value).__name__} in a progress record")


def _plain_json(value: Any) -> Any:
    """`value` as it reads back from a progress record (tuples become lists, numpy scalars numbers)."""
    return json.loads(json.dumps(value, default=_plain))
