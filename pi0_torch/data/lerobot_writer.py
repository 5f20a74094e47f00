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

import io
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

import av
import datasets
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from pi0_torch.utils.files import atomic_output_dir

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
INDEX_COLUMNS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
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


def encode_video(path: Path, frames: Sequence[np.ndarray], fps: int, codec: str) -> None:
    """Encode uint8 `[H, W, 3]` frames into an mp4 at `fps` (yuv420p, one frame per 1/fps second)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(codec, rate=fps)
        height, width = frames[0].shape[:2]
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.time_base = Fraction(1, fps)
        stream.codec_context.gop_size = 10
        if codec in ("libx264", "h264"):
            stream.options = {"crf": "8", "bf": "0"}
        for number, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(frame, format="rgb24")
            picture.pts = number
            container.mux(stream.encode(picture))
        container.mux(stream.encode(None))


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
    """Write `episodes` (consumed one by one) to the LeRobot v3.0 folder `root` and return it.

    Args:
        fps: frames per second (timestamps are `frame_index / fps`).
        vector_names: vector feature name -> the names of its dimensions (its width), e.g.
            `{"observation.state": ["x", "y"], "action": ["dx", "dy"]}`; every episode holds exactly these.
        storage: cameras as "video" (mp4 per group of `episodes_per_file` episodes) or "image" (PNG in the parquet).
        codec: PyAV encoder for the videos (LeRobot defaults to libsvtav1; h264 decodes everywhere).
        num_heldout: the last `num_heldout` episodes form the `heldout` split of `meta/info.json`.
        tasks: the task strings in `task_index` order (default: in order of first appearance).
        overwrite: replace a non-empty `root` (otherwise it must be absent or empty).
    """
    if storage not in ("video", "image"):
        raise ValueError(f"storage must be 'video' or 'image', got {storage!r}")
    if episodes_per_file < 1:
        raise ValueError(f"episodes_per_file must be >= 1, got {episodes_per_file}")
    task_index: dict[str, int] = {task: i for i, task in enumerate(tasks or ())}
    with atomic_output_dir(root, overwrite=overwrite) as folder:
        writer = _FolderWriter(folder, fps, vector_names, storage, codec, robot_type)
        group: list[EpisodeRecord] = []
        for episode in episodes:
            if episode.task not in task_index:
                if tasks is not None:
                    raise ValueError(f"episode task {episode.task!r} is not among the given tasks {list(tasks)}")
                task_index[episode.task] = len(task_index)
            group.append(episode)
            if len(group) == episodes_per_file:
                writer.write_file(group, task_index)
                group = []
        if group:
            writer.write_file(group, task_index)
        if not writer.episode_rows:
            raise ValueError("no episodes to write")
        if not 0 <= num_heldout < len(writer.episode_rows):
            raise ValueError(f"num_heldout must be in [0, {len(writer.episode_rows)}), got {num_heldout}")
        writer.write_meta(task_index, num_heldout)
    return Path(root)


class _FolderWriter:
    """The data/video files, then the metadata, of one dataset folder."""

    def __init__(self, root: Path, fps: int, vector_names: dict[str, list[str]], storage: str, codec: str, robot_type: str) -> None:
        self.root, self.fps, self.vector_names = root, fps, vector_names
        self.storage, self.codec, self.robot_type = storage, codec, robot_type
        self.camera_shapes: dict[str, tuple[int, ...]] | None = None
        self.episode_rows: list[dict[str, Any]] = []
        self.all_vectors: dict[str, list[np.ndarray]] = {name: [] for name in vector_names}
        self.total_frames = 0
        self.file_index = 0

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

    def write_file(self, episodes: list[EpisodeRecord], task_index: dict[str, int]) -> None:
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
            columns["task_index"].extend([task_index[episode.task]] * length)
            for key, frames in episode.frames.items():
                if self.storage == "image":
                    columns[key].extend({"bytes": png_bytes(frame), "path": None} for frame in frames)
                else:
                    video_frames[key].extend(frames)
            self.total_frames += length
        data_path = self.root / DATA_PATH.format(chunk_index=0, file_index=self.file_index)
        data_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pydict(columns, schema=hf_features.arrow_schema), data_path)
        for key, frames in video_frames.items():
            if frames:
                path = self.root / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=self.file_index)
                encode_video(path, frames, self.fps, self.codec)
        self.file_index += 1

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

    def write_meta(self, task_index: dict[str, int], num_heldout: int) -> None:
        meta = self.root / "meta"
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
