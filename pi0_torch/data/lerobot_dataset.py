"""LeRobot episode datasets on disk (format v3.0, and v2.0/v2.1) as π0 training samples.

A LeRobot dataset folder holds

- `meta/info.json`: `codebase_version`, `fps`, `features` (name -> dtype, shape, names), and the path templates
  `data_path` / `video_path`. v3.0: `data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet` and
  `videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4`, many episodes per file. v2.x:
  `data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet` and
  `videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4`, one episode per file.
- tasks: v3.0 `meta/tasks.parquet` (task string -> `task_index`); v2.x `meta/tasks.jsonl`.
- episodes: v3.0 `meta/episodes/chunk-*/file-*.parquet` (per episode: `length`, `tasks`, `data/chunk_index`,
  `data/file_index`, and per camera `videos/{key}/chunk_index`, `file_index`, `from_timestamp`); v2.x
  `meta/episodes.jsonl`.
- frames in parquet: one row per frame with `episode_index`, `frame_index`, `timestamp`, `task_index`, the state and
  action vectors, and cameras of dtype `image` as `{bytes, path}` structs (PNG/JPEG). Cameras of dtype `video`
  live in the mp4 files: frame `k` of an episode is the video frame at `from_timestamp + timestamp[k]` seconds
  (decoded with PyAV, so any codec its FFmpeg reads: LeRobot's default AV1, h264, hevc, ...), so `timestamp[k]`
  must be within half a frame of `k / fps` ([`check_video_timestamps`]).

Whatever the files hold is checked before it is used, and refused with a `LeRobotDatasetError` naming the file and
field (and the episode, frame and camera where there is one): the path templates ([`check_path_template`]), `fps`,
the video times, finite state and action values, and each image cell (its size is read before it is decoded).

[`LeRobotEpisodeDataset`] turns every frame into one training sample: the camera images (uint8 HWC), the state,
the task string as prompt, and the target action chunk of the next `action_horizon` actions.

Episode ends: the chunk of frame t holds actions t .. t+horizon-1. Past the last frame of the episode the chunk
repeats the episode's last action, and `action_is_pad` marks those steps (LeRobot's and openpi's convention:
LeRobot clamps the query to the episode and flags `action_is_pad`; openpi trains on the repeated actions). The
flow-matching loss of `PI0ForActionGeneration` covers every step, like openpi, so the policy learns to hold the
final pose; `action_is_pad` is returned for users who want to weight or drop those steps. An episode shorter than
the horizon has a padded chunk at every frame; `short_episodes` chooses to pad it (with a warning), skip it, or
raise.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import re
import string
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from PIL import Image
from pi0_torch.utils.progress import tqdm

from pi0_torch.utils.extras import require_extra

require_extra("train", __name__, modules=("datasets", "pyarrow", "av"))
import av
import datasets
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pi0_torch.masks import generate_chunk_data
from pi0_torch.processing.images import pil_frame
from pi0_torch.utils.validation import check_float, first_line, is_hub_id

logger = logging.getLogger(__name__)

SUPPORTED_MAJOR_VERSIONS = (2, 3)
ShortEpisodePolicy = Literal["pad", "skip", "error"]
# A handful of values (1 in 10,000 frames, at least one) whose removal shrinks a dimension's std by this factor
# dominate its normalization statistics: every other value would normalize to about 0 ([`check_value_spread`]).
DOMINATING_STD_FACTOR = 100.0
# The fields each path template of meta/info.json may name, by major version ([`check_path_template`]).
PATH_TEMPLATE_FIELDS: dict[int, dict[str, tuple[str, ...]]] = {
    2: {"data_path": ("episode_chunk", "episode_index"), "video_path": ("video_key", "episode_chunk", "episode_index")},
    3: {"data_path": ("chunk_index", "file_index"), "video_path": ("video_key", "chunk_index", "file_index")},
}
MAX_TEMPLATE_WIDTH = 32  # the widest field a path template may ask for (LeRobot's widest: `{episode_index:06d}`)
MAX_PATH_CHARS = 4096  # the longest path a template may make (Linux's PATH_MAX)


class LeRobotDatasetError(ValueError):
    """A LeRobot dataset on disk is malformed (metadata and files disagree, wrong shapes, bad values)."""


@dataclass(frozen=True)
class VideoSegment:
    """Where one episode of one camera lives: the mp4 file and the time of the episode's first frame in it."""

    path: Path
    from_timestamp: float


@dataclass(frozen=True)
class Episode:
    """One episode as the metadata describes it."""

    index: int
    length: int
    tasks: tuple[str, ...]
    data_path: Path
    videos: dict[str, VideoSegment]


# ----------------------------------------------------------------------------------------------------------------
# Metadata.
# ----------------------------------------------------------------------------------------------------------------


def read_info(root: Path) -> dict[str, Any]:
    """`meta/info.json`, checked for the fields the reader needs and a supported `codebase_version`."""
    path = root / "meta" / "info.json"
    if not path.is_file() and is_hub_id(str(root)):
        local = Path("data") / root.name
        raise FileNotFoundError(f"{root} is no local folder: a dataset on the Hugging Face hub is read from a local "
                                f"copy; make one with `hf download {root} --repo-type dataset --local-dir {local}` "
                                f"(the hf command comes with huggingface_hub), then pass --dataset {local}")
    if not path.is_file():
        raise FileNotFoundError(f"{root} is not a LeRobot dataset: {path} is missing")
    info = _read_json(path)
    if not isinstance(info, dict):
        raise LeRobotDatasetError(f"{path} must hold a JSON object, got a JSON {type(info).__name__}")
    missing = [field for field in ("codebase_version", "fps", "features", "data_path") if field not in info]
    if missing:
        raise LeRobotDatasetError(f"{path} lacks {', '.join(missing)}")
    if not isinstance(info["features"], dict) or not all(isinstance(f, dict) for f in info["features"].values()):
        raise LeRobotDatasetError(f"{path}: 'features' must map feature names to objects (dtype, shape, names)")
    version = str(info["codebase_version"])
    try:
        major = int(version.lstrip("v").split(".")[0])
    except ValueError:
        raise LeRobotDatasetError(f"{path}: unreadable codebase_version {version!r}") from None
    if major not in SUPPORTED_MAJOR_VERSIONS:
        raise LeRobotDatasetError(f"{path}: codebase_version {version} is not supported (v2.x and v3.x are)")
    try:
        check_float(f"{path}: fps", info["fps"], minimum=0.0, exclusive_minimum=True)
    except ValueError as error:
        raise LeRobotDatasetError(str(error)) from None
    video_keys = [key for key, feature in info["features"].items() if feature.get("dtype") == "video"]
    for key, fields in PATH_TEMPLATE_FIELDS[major].items():
        if key == "data_path" or info.get(key) is not None:  # (a dataset without videos may have no video_path)
            samples = {field: max(video_keys or ["camera"], key=len) if field == "video_key" else 0 for field in fields}
            check_path_template(path, key, info[key], samples)
    return info


def check_path_template(info_path: Path, key: str, template: Any, samples: dict[str, Any]) -> None:
    """Refuse (`LeRobotDatasetError` naming `key` of `info_path`) a path template that `str.format` could not fill
    with the fields of `samples` alone, or would fill with an absurd width, before any path is built from it: not a
    string, unbalanced braces, a field other than those (`{nope}`, `{0}`, `{chunk_index.real}`), a nested format, a
    width or precision above `MAX_TEMPLATE_WIDTH` (`{chunk_index:0200000000d}` would build a 200 MB string per
    episode), or more than `MAX_PATH_CHARS` characters once filled with `samples` (index 0, the longest video key).
    A path built from it is then longer than that only by the digits of large indices."""
    fields = list(samples)
    if not isinstance(template, str):
        raise LeRobotDatasetError(f"{info_path}: {key} must be a path template string (e.g. "
                                  f"'data/chunk-{{{fields[0]}:03d}}/...'), got {template!r:.80} ({type(template).__name__})")
    shown = f"{info_path}: {key} {template!r:.200}"
    try:
        parts = list(string.Formatter().parse(template))
    except ValueError as error:
        raise LeRobotDatasetError(f"{shown} is not a format string ({first_line(error)})") from None
    for _, field, spec, _ in parts:
        if field is None:
            continue
        if field not in fields:
            raise LeRobotDatasetError(f"{shown} names the field {{{field}}}; its fields are {', '.join(fields)}")
        if "{" in spec:
            raise LeRobotDatasetError(f"{shown} nests a field in the format of {{{field}:{spec}}}")
        widest = max((int(number) for number in re.findall(r"\d+", spec)), default=0)
        if widest > MAX_TEMPLATE_WIDTH:
            raise LeRobotDatasetError(f"{shown} asks for a width of {widest} characters in {{{field}:{spec}}}; "
                                      f"at most {MAX_TEMPLATE_WIDTH}")
    try:
        filled = template.format(**samples)
    except (ValueError, TypeError) as error:
        raise LeRobotDatasetError(f"{shown} cannot be filled ({first_line(error)})") from None
    if len(filled) > MAX_PATH_CHARS:
        raise LeRobotDatasetError(f"{shown} makes paths of {len(filled)} characters; a path has at most {MAX_PATH_CHARS}")


def inside_root(root: Path, relative: Any, what: str) -> Path:
    """`root / relative` for a path the dataset's own files name (a path template, an image cell); refused
    (`LeRobotDatasetError`) when it is absolute or its `..` parts lead out of `root`. Symlinks inside `root` (a hub
    cache's) are not resolved: the check is on the path as written."""
    if not isinstance(relative, str) or not relative:
        raise LeRobotDatasetError(f"{what} must be a relative path inside {root}, got {relative!r:.80}")
    path = Path(os.path.normpath(root / relative))
    if Path(relative).is_absolute() or not path.is_relative_to(os.path.normpath(root)):
        raise LeRobotDatasetError(f"{what} {relative!r:.80} leads outside the dataset folder {root}; refused")
    return path


def _major_version(info: dict[str, Any]) -> int:
    return int(str(info["codebase_version"]).lstrip("v").split(".")[0])


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise LeRobotDatasetError(f"{path} is not valid JSON ({first_line(error)})") from None


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise FileNotFoundError(f"LeRobot metadata file {path} is missing")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError as error:
                raise LeRobotDatasetError(f"{path} line {number} is not valid JSON ({error})") from None
    return rows


def _parquet_columns(path: Path) -> list[str]:
    """The column names of a parquet file; a truncated or foreign file raises an error naming it."""
    try:
        return pq.ParquetFile(path).schema_arrow.names
    except (pa.ArrowException, OSError) as error:
        raise LeRobotDatasetError(f"{path} is not a readable parquet file ({first_line(error)})") from None


def _read_parquet(path: Path, columns: list[str] | None = None, memory_map: bool = False) -> pa.Table:
    try:
        return pq.read_table(path, columns=columns, memory_map=memory_map)
    except (pa.ArrowException, OSError) as error:
        raise LeRobotDatasetError(f"{path} is not a readable parquet file ({first_line(error)})") from None


def read_tasks(root: Path, info: dict[str, Any]) -> dict[int, str]:
    """task_index -> task string."""
    if _major_version(info) >= 3:
        path = root / "meta" / "tasks.parquet"
        if not path.is_file():
            raise FileNotFoundError(f"LeRobot metadata file {path} is missing")
        table = _read_parquet(path)
        # LeRobot writes a pandas frame indexed by the task string: the index is stored as a column named "task"
        # (or "__index_level_0__" when it was unnamed).
        text_column = next((c for c in ("task", "__index_level_0__") if c in table.column_names), None)
        if text_column is None or "task_index" not in table.column_names:
            raise LeRobotDatasetError(f"{path} must hold columns 'task' and 'task_index', got {table.column_names}")
        return dict(zip(table["task_index"].to_pylist(), table[text_column].to_pylist()))
    rows = _read_jsonl(root / "meta" / "tasks.jsonl")
    return {int(row["task_index"]): str(row["task"]) for row in rows}


def read_episodes(root: Path, info: dict[str, Any]) -> list[Episode]:
    """Every episode of the dataset with its data file and video segments, in episode order."""
    video_keys = [key for key, feature in info["features"].items() if feature.get("dtype") == "video"]
    if video_keys and not info.get("video_path"):
        raise LeRobotDatasetError(f"{root}/meta/info.json has video features {video_keys} but no video_path")
    episodes = _read_episodes_v3(root, info, video_keys) if _major_version(info) >= 3 else _read_episodes_v2(root, info, video_keys)
    return sorted(episodes, key=lambda episode: episode.index)


def _read_episodes_v3(root: Path, info: dict[str, Any], video_keys: list[str]) -> list[Episode]:
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise FileNotFoundError(f"LeRobot v3 dataset {root} has no episode metadata under meta/episodes/chunk-*/")
    wanted = ["episode_index", "length", "tasks", "data/chunk_index", "data/file_index"]
    for key in video_keys:
        wanted += [f"videos/{key}/chunk_index", f"videos/{key}/file_index", f"videos/{key}/from_timestamp"]
    episodes = []
    for path in files:
        available = _parquet_columns(path)
        missing = [column for column in wanted if column not in available]
        if missing:
            raise LeRobotDatasetError(f"{path} lacks columns {missing}")
        rows = _read_parquet(path, columns=wanted).to_pylist()
        for row in rows:
            index = int(row["episode_index"])
            data_path = _episode_path(root, info, "data_path", index, chunk_index=row["data/chunk_index"],
                                      file_index=row["data/file_index"])
            videos = {}
            for key in video_keys:
                start = row[f"videos/{key}/from_timestamp"]
                if not isinstance(start, (int, float)) or not 0.0 <= start < math.inf:
                    raise LeRobotDatasetError(f"{path}: episode {index} has videos/{key}/from_timestamp {start!r}; "
                                              "expected the time in seconds (>= 0) of its first frame in the video")
                video = _episode_path(root, info, "video_path", index, video_key=key,
                                      chunk_index=row[f"videos/{key}/chunk_index"], file_index=row[f"videos/{key}/file_index"])
                videos[key] = VideoSegment(video, float(start))
            episodes.append(Episode(index, int(row["length"]), tuple(row["tasks"] or ()), data_path, videos))
    return episodes


def _read_episodes_v2(root: Path, info: dict[str, Any], video_keys: list[str]) -> list[Episode]:
    chunks_size = int(info.get("chunks_size", 1000))
    episodes = []
    for row in _read_jsonl(root / "meta" / "episodes.jsonl"):
        index = int(row["episode_index"])
        names = dict(episode_chunk=index // chunks_size, episode_index=index)
        videos = {key: VideoSegment(_episode_path(root, info, "video_path", index, video_key=key, **names), 0.0)
                  for key in video_keys}
        data_path = _episode_path(root, info, "data_path", index, **names)
        episodes.append(Episode(index, int(row["length"]), tuple(row.get("tasks", ())), data_path, videos))
    return episodes


def _episode_path(root: Path, info: dict[str, Any], key: str, episode: int, **names: Any) -> Path:
    """The file of one episode: the path template `info[key]` (checked by [`read_info`]) filled with `names`, inside
    `root`; an index of the wrong type (`{chunk_index:03d}` of a string) is refused naming the episode."""
    try:
        relative = info[key].format(**names)
    except (ValueError, TypeError) as error:
        raise LeRobotDatasetError(f"{root}/meta/info.json: {key} {info[key]!r} cannot be filled for episode {episode} "
                                  f"with {names} ({first_line(error)})") from None
    return inside_root(root, relative, f"meta/info.json {key}")


def split_episodes(root: str | Path, split: str) -> list[int]:
    """Episode indices of a split named in `meta/info.json` (`"splits": {"train": "0:96", "heldout": "96:120"}`)."""
    info = read_info(Path(root))
    splits = info.get("splits") or {}
    if split not in splits:
        raise LeRobotDatasetError(f"split {split!r} is not in {root}/meta/info.json; it has {sorted(splits)}")
    start, stop = (int(n) for n in str(splits[split]).split(":"))
    return list(range(start, stop))


def camera_frame_shape(key: str, feature: dict[str, Any]) -> tuple[int, int, int]:
    """The (height, width, channels) a camera feature declares (LeRobot stores HWC; some v2.0 ports CHW)."""
    shape = tuple(int(n) for n in feature["shape"])
    names = feature.get("names") or []
    if len(shape) != 3:
        raise LeRobotDatasetError(f"camera feature {key!r} must have a 3-D shape, got {list(shape)}")
    if names and names[0] in ("channel", "channels"):
        return shape[1], shape[2], shape[0]
    return shape


# ----------------------------------------------------------------------------------------------------------------
# Video frames.
# ----------------------------------------------------------------------------------------------------------------


class _OpenVideo:
    """One open mp4 file: its container, first video stream, and a forward decoding position."""

    def __init__(self, path: Path) -> None:
        self.container = av.open(str(path))
        self.stream = self.container.streams.video[0]
        self.stream.thread_type = "AUTO"
        self.frames: Iterator[av.VideoFrame] | None = None
        self.last_time = -math.inf  # time of the last frame handed out by `frames`

    def seek(self, timestamp: float) -> None:
        offset = max(0, int(timestamp / self.stream.time_base))  # in stream time-base units
        self.container.seek(offset, stream=self.stream, backward=True, any_frame=False)
        self.frames = self.container.decode(self.stream)
        self.last_time = -math.inf


class VideoFrameReader:
    """Frames of mp4 files by timestamp, decoded with PyAV (FFmpeg), with an LRU cache of decoded frames.

    A request seeks to the key frame before the timestamp and decodes forward; a request just after the previous
    one keeps decoding without seeking. Every frame decoded on the way is cached (up to `cache_bytes`), so a
    second pass over a small dataset decodes nothing. A frame is accepted when its presentation time is within
    `tolerance_s` of the request (LeRobot's default is 1e-4 s).
    """

    # decode forward instead of seeking when the request is at most this far ahead of the decoding position
    max_forward_s = 1.0

    def __init__(self, fps: float, tolerance_s: float = 1e-4, cache_bytes: int = 256 << 20) -> None:
        self.fps = float(fps)
        self.tolerance_s = tolerance_s
        self.cache_bytes = cache_bytes
        self._videos: dict[Path, _OpenVideo] = {}
        self._cache: OrderedDict[tuple[Path, int], tuple[float, np.ndarray]] = OrderedDict()
        self._cached_bytes = 0

    def frame(self, path: Path, timestamp: float) -> np.ndarray:
        """The RGB frame (uint8 `[H, W, 3]`) of `path` shown at `timestamp` seconds."""
        key = (path, round(timestamp * self.fps))
        hit = self._lookup(key, timestamp)
        if hit is not None:
            return hit
        video = self._open(path)
        behind = timestamp < video.last_time - self.tolerance_s
        far_ahead = timestamp > video.last_time + self.max_forward_s
        if video.frames is None or behind or far_ahead:
            video.seek(timestamp)
        first_time = self._decode_until(video, path, timestamp)
        hit = self._lookup(key, timestamp)
        if hit is None and first_time is not None and first_time > timestamp:
            video.seek(0.0)  # the seek landed past the request (no key frame index before it): decode from the start
            self._decode_until(video, path, timestamp)
            hit = self._lookup(key, timestamp)
        return hit if hit is not None else self._missing(path, timestamp)

    def _decode_until(self, video: _OpenVideo, path: Path, timestamp: float) -> float | None:
        """Decode forward, caching every frame, up to the first frame at or after `timestamp`; returns the time of
        the first frame decoded (None when the file had no more frames)."""
        first_time = None
        for decoded in video.frames:  # type: ignore[union-attr]
            time = float(decoded.time)
            first_time = time if first_time is None else first_time
            self._store((path, round(time * self.fps)), time, decoded.to_ndarray(format="rgb24"))
            video.last_time = time
            if time >= timestamp - self.tolerance_s:
                return first_time
        video.frames = None  # end of file
        return first_time

    def _missing(self, path: Path, timestamp: float) -> np.ndarray:
        nearby = sorted(t for (p, _), (t, _) in self._cache.items() if p == path and abs(t - timestamp) < 1.0)
        raise LeRobotDatasetError(
            f"{path}: no video frame within {self.tolerance_s} s of t={timestamp:.6f} s"
            f" (decoded frames near it: {[round(t, 6) for t in nearby][:6]}); the video is shorter than the"
            " episode metadata says, or its frame times do not match the dataset fps"
        )

    def _lookup(self, key: tuple[Path, int], timestamp: float) -> np.ndarray | None:
        entry = self._cache.get(key)
        if entry is None or abs(entry[0] - timestamp) > self.tolerance_s:
            return None
        self._cache.move_to_end(key)
        return entry[1]

    def _store(self, key: tuple[Path, int], time: float, frame: np.ndarray) -> None:
        if key in self._cache:
            return
        self._cache[key] = (time, frame)
        self._cached_bytes += frame.nbytes
        while self._cached_bytes > self.cache_bytes and len(self._cache) > 1:
            _, (_, dropped) = self._cache.popitem(last=False)
            self._cached_bytes -= dropped.nbytes

    def _open(self, path: Path) -> _OpenVideo:
        video = self._videos.get(path)
        if video is None:
            if not path.is_file():
                raise FileNotFoundError(f"video file {path} is missing")
            video = self._videos[path] = _OpenVideo(path)
        return video

    def close(self) -> None:
        for video in self._videos.values():
            video.container.close()
        self._videos.clear()
        self._cache.clear()
        self._cached_bytes = 0


# ----------------------------------------------------------------------------------------------------------------
# Frames.
# ----------------------------------------------------------------------------------------------------------------


def _vector_column(column: pa.ChunkedArray, name: str, width: int, path: Path) -> np.ndarray:
    """A parquet column of per-frame vectors (list / fixed-size list, or a scalar when width is 1) -> `[N, width]`."""
    array = column.combine_chunks()
    if pa.types.is_list(array.type) or pa.types.is_large_list(array.type) or pa.types.is_fixed_size_list(array.type):
        lengths = pc.list_value_length(array).to_numpy(zero_copy_only=False)
        if len(lengths) and (lengths.min() != width or lengths.max() != width):
            bad = int(np.flatnonzero(lengths != width)[0])
            raise LeRobotDatasetError(
                f"{path}: column {name!r} has rows of length {int(lengths[bad])} (row {bad}), but meta/info.json "
                f"declares shape [{width}]"
            )
        values = pc.list_flatten(array).to_numpy(zero_copy_only=False)
        return values.astype(np.float32).reshape(len(array), width)
    if width != 1:
        raise LeRobotDatasetError(
            f"{path}: column {name!r} holds scalars, but meta/info.json declares shape [{width}]"
        )
    return array.to_numpy(zero_copy_only=False).astype(np.float32)[:, None]


@dataclass
class _Frames:
    """Per-frame columns of the selected episodes, concatenated in episode order."""

    state: np.ndarray  # float32 [N, S]
    action: np.ndarray  # float32 [N, A]
    timestamp: np.ndarray  # float64 [N], seconds from the episode start
    task_index: np.ndarray  # int64 [N], -1 where the data has none
    images: dict[str, list[pa.Array]]  # camera (dtype image) -> per data file, its {bytes, path} column
    image_rows: np.ndarray  # int64 [N, 2]: (data file number, row in it) for image lookups


def _read_frames(
    episodes: list[Episode], state_key: str, action_key: str, camera_keys: tuple[list[str], list[str]],
    dims: tuple[int, int], fps: float, progress: bool,
) -> _Frames:
    """The frames of `episodes` from their parquet files, checked against the metadata: each episode's frames
    0..length-1, finite state and action values, and, where `camera_keys` (image keys, video keys) name video
    cameras, timestamps that select the episode's own video frames ([`check_video_timestamps`])."""
    image_keys, video_keys = camera_keys
    by_file: dict[Path, list[Episode]] = {}
    for episode in episodes:
        by_file.setdefault(episode.data_path, []).append(episode)
    state_dim, action_dim = dims
    per_episode: dict[int, tuple[np.ndarray, ...]] = {}
    image_columns: dict[str, list[pa.Array]] = {key: [] for key in image_keys}
    for file_number, (path, file_episodes) in enumerate(
        tqdm(by_file.items(), desc="reading episode frames", unit="file", disable=not progress or len(by_file) < 4)
    ):
        if not path.is_file():
            raise FileNotFoundError(f"data file {path} (episodes {[e.index for e in file_episodes][:8]}) is missing")
        available = _parquet_columns(path)
        wanted = ["episode_index", "frame_index", state_key, action_key, *image_keys]
        missing = [column for column in wanted if column not in available]
        if missing:
            raise LeRobotDatasetError(f"{path} lacks columns {missing} (it has {available})")
        optional = [column for column in ("timestamp", "task_index") if column in available]
        table = _read_parquet(path, columns=wanted + optional, memory_map=True)
        episode_column = table["episode_index"].to_numpy()
        frame_column = table["frame_index"].to_numpy()
        state = _vector_column(table[state_key], state_key, state_dim, path)
        action = _vector_column(table[action_key], action_key, action_dim, path)
        timestamp = table["timestamp"].to_numpy().astype(np.float64) if "timestamp" in optional else frame_column / fps
        task_index = table["task_index"].to_numpy().astype(np.int64) if "task_index" in optional else np.full(len(table), -1)
        for key in image_keys:
            image_columns[key].append(table[key].combine_chunks())
        for episode in file_episodes:
            rows = np.flatnonzero(episode_column == episode.index)
            rows = rows[np.argsort(frame_column[rows], kind="stable")]
            if len(rows) != episode.length or not np.array_equal(frame_column[rows], np.arange(episode.length)):
                raise LeRobotDatasetError(
                    f"{path}: episode {episode.index} should have frames 0..{episode.length - 1} (meta length "
                    f"{episode.length}), found {len(rows)} rows with frame_index {frame_column[rows][:10].tolist()}..."
                )
            for name, values in ((state_key, state[rows]), (action_key, action[rows])):
                if not np.isfinite(values).all():
                    frame = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
                    raise LeRobotDatasetError(f"{path}: {name!r} of episode {episode.index} frame {frame} is not finite")
            if video_keys:
                check_video_timestamps(path, episode, video_keys, timestamp[rows], fps)
            per_episode[episode.index] = (
                state[rows], action[rows], timestamp[rows], task_index[rows],
                np.stack([np.full(len(rows), file_number), rows], axis=1),
            )
    state, action, timestamp, task_index, image_rows = (
        np.concatenate(parts) for parts in zip(*(per_episode[episode.index] for episode in episodes))
    )
    return _Frames(state, action, timestamp, task_index, image_columns, image_rows)


def check_video_timestamps(path: Path, episode: Episode, video_keys: Sequence[str], timestamps: np.ndarray, fps: float) -> None:
    """Refuse (`LeRobotDatasetError` naming the data file, the episode, its first wrong frame, and the cameras and
    video files it would be read from) timestamps of an episode that would not select its own video frames: frame
    k is the video frame at `from_timestamp + timestamp[k]`, and that frame was recorded at k / fps. A timestamp
    more than half a frame from k / fps (all zeros: every sample would show the first frame) or not finite is
    refused; what remains is within half a frame, and the video reader then requires a decoded frame within its
    tolerance of it."""
    expected = np.arange(len(timestamps)) / fps
    wrong = ~(np.abs(timestamps - expected) <= 0.5 / fps)  # (NaN compares False: refused too)
    if wrong.any():
        frame = int(np.flatnonzero(wrong)[0])
        videos = ", ".join(f"{key!r} ({episode.videos[key].path})" for key in video_keys if key in episode.videos)
        raise LeRobotDatasetError(
            f"{path}: episode {episode.index} frame {frame} has timestamp {timestamps[frame]:.6g} s, but its video "
            f"frame is at {expected[frame]:.6g} s (frame_index / fps {fps:g}; {int(wrong.sum())} of {len(timestamps)} "
            f"frames are more than half a frame off): its frames would be read from the wrong times of cameras {videos}"
        )


def dominating_rows(values: np.ndarray) -> tuple[int, int] | None:
    """(row, dim) of the most extreme value of the first dimension of `values` `[N, D]` whose std is dominated by a
    handful of values: removing its `max(1, N // 10_000)` values farthest from the median shrinks the std more than
    `DOMINATING_STD_FACTOR` times (the remaining std floored at 1e-3 of the remaining values' magnitude, so that a
    dimension that is constant but for one real change, e.g. a gripper closing once, is left alone). None if none.

    >>> data = np.zeros((1000, 2)); data[:, 0] = np.linspace(0, 1, 1000); data[:, 1] = 0.5
    >>> dominating_rows(data) is None
    True
    >>> data[417, 0] = 3e38
    >>> dominating_rows(data)
    (417, 0)
    """
    values = np.asarray(values, np.float64)
    if len(values) < 2:
        return None
    extremes = max(1, len(values) // 10_000)
    for dim in range(values.shape[1]):
        column = values[:, dim]
        deviation = np.abs(column - np.median(column))
        farthest = np.argpartition(deviation, len(column) - extremes)[-extremes:]
        rest = np.delete(column, farthest)
        floor = 1e-3 * max(1.0, float(np.abs(rest).max()))
        if column.std() > DOMINATING_STD_FACTOR * max(float(rest.std()), floor):
            return int(farthest[np.argmax(deviation[farthest])]), dim
    return None


def _decode_image_cell(cell: Any, root: Path, shape: tuple[int, int, int], where: str) -> np.ndarray:
    """A `{bytes, path}` image cell (HF `datasets.Image` storage) -> RGB `[H, W, 3]`: uint8 for the 8-bit modes,
    float32 for mode 'F' (`pi0_torch.processing.images.pil_frame`).

    Refused (`LeRobotDatasetError` naming `where`: the episode, frame and camera) when the cell is null or empty,
    holds no readable image, an image of integer pixels (mode 'I;16', 'I': a depth or 16-bit camera, which an RGB
    conversion would clip to white or black), or an image whose size differs from the camera's `shape` (height,
    width, channels) from meta/info.json. The size is read from the file's header before anything is decoded, so a
    20000 x 20000 PNG costs nothing."""
    if not isinstance(cell, dict) or (cell.get("bytes") is None and not cell.get("path")):
        raise LeRobotDatasetError(f"{where}: the image cell is empty ({cell!r:.80}): expected PNG / JPEG bytes or a path")
    source = io.BytesIO(cell["bytes"]) if cell.get("bytes") is not None else inside_root(root, cell["path"], "image cell path")
    try:
        with Image.open(source) as image:
            size = (image.height, image.width)
            if size == tuple(shape[:2]):
                image.load()
                return pil_frame(image, "the image")
    except Image.DecompressionBombError as error:
        raise LeRobotDatasetError(f"{where}: {first_line(error)}; meta/info.json declares {shape[0]} x {shape[1]} "
                                  "(height x width)") from None
    except (OSError, SyntaxError, ValueError) as error:  # not an image, truncated, a missing file, integer pixels
        raise LeRobotDatasetError(f"{where}: the image cell holds no usable image ({first_line(error)})") from None
    raise LeRobotDatasetError(f"{where}: the image is {size[0]} x {size[1]} (height x width), but meta/info.json declares "
                              f"{shape[0]} x {shape[1]}; refused before decoding")


# ----------------------------------------------------------------------------------------------------------------
# The dataset.
# ----------------------------------------------------------------------------------------------------------------


class LeRobotEpisodeDataset(torch.utils.data.Dataset):
    """Frames of a LeRobot dataset folder as π0 training samples (map-style `torch.utils.data.Dataset`).

    Each item is a dict:

    - `images`: camera feature key -> uint8 `[H, W, 3]` (decoded from the parquet image cells or the mp4 videos);
    - `state`: float32 `[state_dim]`; `prompt`: the frame's task string;
    - `actions`: float32 `[action_horizon, action_dim]`, the actions of this frame and the next horizon-1 frames
      of the same episode; `action_is_pad`: bool `[action_horizon]`, True where the episode had ended and the last
      action is repeated (see the module docstring);
    - `episode_index`, `frame_index`, `index` (position in this dataset).

    Args:
        root: the dataset folder (the one holding `meta/info.json`).
        action_horizon: actions per chunk (the model's `config.action_horizon`).
        episodes: episode indices to use (default all), e.g. a train / held-out split.
        state_key, action_key: the state and action features.
        camera_keys: camera features to return (default every `image` / `video` feature in info.json order).
        short_episodes: what to do with an episode shorter than `action_horizon`: "pad" (keep it, repeat its last
            action; logs a warning), "skip" (drop it; logs a warning) or "error" (raise `LeRobotDatasetError`).
        video_tolerance_s: accepted distance between a frame's timestamp and the decoded video frame time.
        frame_cache_mb: memory for decoded video frames (per process / DataLoader worker).

    ```python
    >>> from pi0_torch.data.synthetic_data import write_synthetic_dataset
    >>> import tempfile
    >>> root = write_synthetic_dataset(tempfile.mkdtemp() + "/reach", num_episodes=2, episode_length=12)
    >>> dataset = LeRobotEpisodeDataset(root, action_horizon=4)
    >>> sample = dataset[0]
    >>> len(dataset), sample["actions"].shape, sample["images"]["observation.images.base"].shape
    (24, (4, 2), (64, 64, 3))

    ```
    """

    def __init__(
        self,
        root: str | Path,
        action_horizon: int,
        *,
        episodes: Sequence[int] | None = None,
        state_key: str = "observation.state",
        action_key: str = "action",
        camera_keys: Sequence[str] | None = None,
        short_episodes: ShortEpisodePolicy = "pad",
        video_tolerance_s: float = 1e-4,
        frame_cache_mb: int = 256,
        progress: bool = False,
    ) -> None:
        if action_horizon < 1:
            raise ValueError(f"action_horizon must be >= 1, got {action_horizon}")
        if short_episodes not in ("pad", "skip", "error"):
            raise ValueError(f"short_episodes must be 'pad', 'skip' or 'error', got {short_episodes!r}")
        self.root = Path(root)
        self.info = read_info(self.root)
        self.fps = float(self.info["fps"])
        self.action_horizon = action_horizon
        self.state_key, self.action_key = state_key, action_key
        self.short_episodes = short_episodes
        features = self.info["features"]
        if state_key == action_key:  # (a policy trained on it would learn to copy its input)
            raise LeRobotDatasetError(f"the action key and the state key are both {state_key!r}: the actions are what "
                                      "the robot is told to do next, another feature (--action-key, --state-key)")
        for role, key in (("state_key", state_key), ("action_key", action_key)):
            if key not in features:
                numeric = [k for k, f in features.items() if f.get("dtype") not in ("image", "video", "string")]
                raise LeRobotDatasetError(f"{role} {key!r} is not a feature of {self.root}; numeric features: {numeric}")
            if len(features[key]["shape"]) != 1:
                raise LeRobotDatasetError(f"feature {key!r} must be a vector, meta/info.json shape is {features[key]['shape']}")
        self.state_dim = int(features[state_key]["shape"][0])
        self.action_dim = int(features[action_key]["shape"][0])
        all_cameras = [k for k, f in features.items() if f.get("dtype") in ("image", "video")]
        self.camera_keys = list(all_cameras if camera_keys is None else camera_keys)
        unknown = [key for key in self.camera_keys if key not in all_cameras]
        if unknown:
            raise LeRobotDatasetError(f"camera_keys {unknown} are not camera features of {self.root}; it has {all_cameras}")
        self.camera_shapes = {key: camera_frame_shape(key, features[key]) for key in self.camera_keys}
        self.tasks = read_tasks(self.root, self.info)

        by_index = {episode.index: episode for episode in read_episodes(self.root, self.info)}
        if episodes is not None:
            unknown_episodes = sorted(set(episodes) - set(by_index))
            if unknown_episodes:
                raise LeRobotDatasetError(f"episodes {unknown_episodes[:10]} are not in {self.root} ({len(by_index)} episodes)")
        selected = [by_index[i] for i in (episodes if episodes is not None else sorted(by_index))]
        self.episodes = self._apply_short_episode_policy(selected, short_episodes)
        if not self.episodes:
            raise LeRobotDatasetError(f"no episodes to read from {self.root} (selected: {episodes}, short_episodes={short_episodes!r})")
        for episode in self.episodes:
            for key in self.camera_keys:
                segment = episode.videos.get(key)
                if segment is not None and not segment.path.is_file():
                    raise FileNotFoundError(f"video file {segment.path} of camera {key!r}, episode {episode.index} is missing")
        image_keys = [key for key in self.camera_keys if features[key]["dtype"] == "image"]
        video_keys = [key for key in self.camera_keys if features[key]["dtype"] == "video"]
        self._frames = _read_frames(
            self.episodes, state_key, action_key, (image_keys, video_keys), (self.state_dim, self.action_dim), self.fps,
            progress,
        )
        lengths = np.array([episode.length for episode in self.episodes], dtype=np.int64)
        self._episode_start = np.concatenate([[0], np.cumsum(lengths)])  # [E + 1]
        self._episode_of_frame = np.repeat(np.arange(len(self.episodes)), lengths)  # [N]
        self._video_tolerance_s = video_tolerance_s
        self._frame_cache_bytes = frame_cache_mb << 20
        self._videos: VideoFrameReader | None = None
        self._chunk_cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def _apply_short_episode_policy(self, episodes: list[Episode], policy: ShortEpisodePolicy) -> list[Episode]:
        short = [episode for episode in episodes if episode.length < self.action_horizon]
        if not short:
            return episodes
        described = ", ".join(f"{e.index} ({e.length} frames)" for e in short[:10]) + (" ..." if len(short) > 10 else "")
        message = f"{len(short)} episode(s) of {self.root} are shorter than the action horizon {self.action_horizon}: {described}"
        if policy == "error":
            raise LeRobotDatasetError(message + "; pass short_episodes='pad' or 'skip' to use the dataset anyway")
        if policy == "skip":
            logger.warning("%s; skipping them", message)
            return [episode for episode in episodes if episode.length >= self.action_horizon]
        logger.warning("%s; their chunks repeat the last action (action_is_pad marks those steps)", message)
        return episodes

    # -- sizes -----------------------------------------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self._episode_start[-1])

    @property
    def episode_indices(self) -> list[int]:
        return [episode.index for episode in self.episodes]

    # -- items -----------------------------------------------------------------------------------------------------

    def episode_chunks(self, position: int) -> tuple[np.ndarray, np.ndarray]:
        """Action chunks of every frame of the episode at `position` in this dataset: float32 `[T, horizon, A]` and
        the padding flags bool `[T, horizon]`.

        The episode's actions are laid out as `[a_0, a_0 .. a_{T-1}, a_{T-1} x (horizon-1)]` (length T + horizon;
        the leading row is a placeholder no chunk selects) and `masks.generate_chunk_data` picks, for window step
        t, steps t+1 .. t+horizon of that sequence, i.e. `a_t .. a_{t+horizon-1}` with the last action repeated
        past the end.
        """
        cached = self._chunk_cache.get(position)
        if cached is not None:
            self._chunk_cache.move_to_end(position)
            return cached
        start, end = self._episode_start[position], self._episode_start[position + 1]
        actions = torch.from_numpy(self._frames.action[start:end])  # [T, A]
        length, horizon = actions.shape[0], self.action_horizon
        padded = torch.cat([actions[:1], actions, actions[-1:].expand(horizon - 1, -1)])  # [T + horizon, A]
        is_pad = torch.arange(length + horizon) > length  # rows after a_{T-1}
        chunks = generate_chunk_data(padded[None], window_size=length, chunk_size=horizon)[0].numpy()
        pad = generate_chunk_data(is_pad[None], window_size=length, chunk_size=horizon)[0].numpy()
        self._chunk_cache[position] = (chunks, pad)
        if len(self._chunk_cache) > 64:
            self._chunk_cache.popitem(last=False)
        return chunks, pad

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for a dataset of {len(self)} frames")
        index = index % len(self)
        position = int(self._episode_of_frame[index])
        episode = self.episodes[position]
        frame_index = index - int(self._episode_start[position])
        chunks, pad = self.episode_chunks(position)
        task_index = int(self._frames.task_index[index])
        if task_index >= 0:
            if task_index not in self.tasks:
                raise LeRobotDatasetError(f"episode {episode.index} frame {frame_index}: task_index {task_index} is not in the tasks table")
            prompt = self.tasks[task_index]
        elif episode.tasks:
            prompt = episode.tasks[0]
        else:
            raise LeRobotDatasetError(f"episode {episode.index} has no task (no task_index column and no episode tasks)")
        return {
            "images": {key: self._image(key, episode, index, frame_index) for key in self.camera_keys},
            "state": self._frames.state[index],
            "actions": chunks[frame_index],
            "action_is_pad": pad[frame_index],
            "prompt": prompt,
            "episode_index": episode.index,
            "frame_index": frame_index,
            "index": index,
        }

    def _image(self, key: str, episode: Episode, index: int, frame_index: int) -> np.ndarray:
        segment = episode.videos.get(key)
        if segment is not None:
            if self._videos is None:
                self._videos = VideoFrameReader(self.fps, self._video_tolerance_s, self._frame_cache_bytes)
            frame = self._videos.frame(segment.path, segment.from_timestamp + float(self._frames.timestamp[index]))
        else:
            file_number, row = self._frames.image_rows[index]
            cell = self._frames.images[key][file_number][int(row)].as_py()
            where = f"{episode.data_path}: episode {episode.index} frame {frame_index}, camera {key!r}"
            frame = _decode_image_cell(cell, self.root, self.camera_shapes[key], where)
        if frame.shape != self.camera_shapes[key]:
            raise LeRobotDatasetError(
                f"camera {key!r}, episode {episode.index}: decoded frame has shape {frame.shape}, but meta/info.json "
                f"declares (height, width, channels) = {self.camera_shapes[key]}"
            )
        return frame

    # -- numeric passes (no image decoding) ------------------------------------------------------------------------

    def iter_state_action_chunks(self) -> Iterator[dict[str, np.ndarray]]:
        """Per episode `{"state": [T, S], "actions": [T, horizon, A]}`, without decoding images.

        The batches `normalization.compute_norm_stats` takes (every axis but the last is a batch axis), so the
        action statistics cover every chunk element as openpi's `compute_norm_stats` does.
        """
        for position in range(len(self.episodes)):
            start, end = int(self._episode_start[position]), int(self._episode_start[position + 1])
            yield {"state": self._frames.state[start:end], "actions": self.episode_chunks(position)[0]}

    def check_value_spread(self) -> None:
        """Refuse (`LeRobotDatasetError`) state or action values that would dominate normalization statistics
        computed from this data, naming the episode, frame, dimension and value: one corrupt action of 3e38 among
        values of about 1 gives a std of 3.9e37, and every real action then normalizes to about 0 ([`dominating_rows`])."""
        for key, values in ((self.state_key, self._frames.state), (self.action_key, self._frames.action)):
            found = dominating_rows(values)
            if found:
                row, dim = found
                position = int(self._episode_of_frame[row])
                frame = row - int(self._episode_start[position])
                others = np.delete(values[:, dim], row)
                raise LeRobotDatasetError(
                    f"{self.root}: {key!r} dim {dim} is {values[row, dim]:.4g} at episode {self.episodes[position].index} "
                    f"frame {frame}, while its other values span [{others.min():.4g}, {others.max():.4g}]: it would "
                    "dominate the normalization statistics (a corrupt value?); fix or drop that episode, or give "
                    "statistics with --norm-stats")

    # -- pickling for DataLoader workers ---------------------------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_videos"] = None  # open containers and decoded frames stay with their process
        state["_chunk_cache"] = OrderedDict()
        return state

    # -- Hugging Face `datasets` -----------------------------------------------------------------------------------

    def hf_features(self) -> datasets.Features:
        """The `datasets.Features` of the samples (images as `datasets.Image`)."""
        return datasets.Features(
            {
                "images": {key: datasets.Image() for key in self.camera_keys},
                "state": datasets.Sequence(datasets.Value("float32"), length=self.state_dim),
                "actions": datasets.Array2D((self.action_horizon, self.action_dim), "float32"),
                "action_is_pad": datasets.Sequence(datasets.Value("bool"), length=self.action_horizon),
                "prompt": datasets.Value("string"),
                "episode_index": datasets.Value("int64"),
                "frame_index": datasets.Value("int64"),
                "index": datasets.Value("int64"),
            }
        )

    def to_hf_dataset(self, streaming: bool = False, cache_dir: str | None = None) -> datasets.Dataset | datasets.IterableDataset:
        """The samples as a Hugging Face `datasets` dataset.

        `streaming=True` gives a `datasets.IterableDataset` whose shards are the episodes (so `.shuffle()`,
        `split_dataset_by_node` and DataLoader workers split by episode) and decodes frames as it goes;
        `streaming=False` materialises an Arrow `datasets.Dataset` (written under `cache_dir`, default the HF cache)
        with `.map` / `.filter` / `.with_transform` at hand. Images come back as PIL images.
        """
        options = dict(
            root=str(self.root), action_horizon=self.action_horizon, state_key=self.state_key,
            action_key=self.action_key, camera_keys=list(self.camera_keys), short_episodes=self.short_episodes,
            video_tolerance_s=self._video_tolerance_s,
        )
        gen_kwargs = {"episodes": self.episode_indices, "options": options}
        if streaming:
            return datasets.IterableDataset.from_generator(_generate_samples, features=self.hf_features(), gen_kwargs=gen_kwargs)
        return datasets.Dataset.from_generator(
            _generate_samples, features=self.hf_features(), gen_kwargs=gen_kwargs, cache_dir=cache_dir
        )


def _generate_samples(episodes: list[int], options: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """Samples of `episodes` in order (the generator behind `LeRobotEpisodeDataset.to_hf_dataset`)."""
    dataset = LeRobotEpisodeDataset(episodes=episodes, progress=False, **options)
    for index in range(len(dataset)):
        yield dataset[index]
