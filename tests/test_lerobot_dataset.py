"""LeRobot on-disk datasets: layout, action chunks at episode ends, video decoding, broken datasets, HF datasets."""

from __future__ import annotations

import io
import json
import logging
import pickle
import shutil
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image

from pi0_torch.data.lerobot_dataset import (
    MAX_TEMPLATE_WIDTH,
    LeRobotDatasetError,
    LeRobotEpisodeDataset,
    VideoFrameReader,
    read_episodes,
    read_info,
    split_episodes,
)
from pi0_torch.data.synthetic_data import CAMERA_KEY, rollout, sample_scene, write_synthetic_dataset

HORIZON = 5
LENGTHS = [12, 9, 3, 10, 12, 7]  # episode 2 is shorter than the horizon


@pytest.fixture(scope="module")
def datasets_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same six episodes stored with mp4 videos and with PNG images in the parquet."""
    root = tmp_path_factory.mktemp("lerobot")
    for storage in ("video", "image"):
        write_synthetic_dataset(
            root / storage, num_episodes=len(LENGTHS), num_heldout=2, episode_lengths=LENGTHS, image_size=32,
            seed=3, storage=storage, episodes_per_file=4,
        )
    return root


@pytest.fixture()
def copy_of(datasets_dir: Path, tmp_path: Path):
    def make(storage: str) -> Path:
        return Path(shutil.copytree(datasets_dir / storage, tmp_path / storage))

    return make


def _episode_actions(root: Path, episode: int) -> np.ndarray:
    frames = pd.concat(pd.read_parquet(p) for p in sorted((root / "data").glob("chunk-*/*.parquet")))
    rows = frames[frames["episode_index"] == episode].sort_values("frame_index")
    return np.stack(rows["action"].to_numpy()).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- layout


def test_synthetic_dataset_has_lerobot_v3_layout(datasets_dir: Path) -> None:
    root = datasets_dir / "video"
    info = read_info(root)
    assert info["codebase_version"] == "v3.0" and info["total_episodes"] == 6 and info["total_frames"] == sum(LENGTHS)
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    assert info["features"][CAMERA_KEY]["dtype"] == "video"
    # 4 episodes per file -> two data files and two video files
    assert sorted(p.name for p in (root / "data" / "chunk-000").iterdir()) == ["file-000.parquet", "file-001.parquet"]
    assert len(list((root / "videos" / CAMERA_KEY / "chunk-000").glob("*.mp4"))) == 2
    # LeRobot reads meta/tasks.parquet with pandas as a frame indexed by the task string
    tasks = pd.read_parquet(root / "meta" / "tasks.parquet")
    assert tasks.index.name == "task" and list(tasks.columns) == ["task_index"]
    episodes = read_episodes(root, info)
    assert [e.length for e in episodes] == LENGTHS
    # episode 5 is the second one of file-001: its video starts after episode 4's 12 frames
    assert episodes[5].videos[CAMERA_KEY].path.name == "file-001.mp4"
    assert episodes[5].videos[CAMERA_KEY].from_timestamp == pytest.approx(12 / info["fps"])
    assert split_episodes(root, "train") == [0, 1, 2, 3] and split_episodes(root, "heldout") == [4, 5]


def test_scene_needs_image_and_instruction() -> None:
    """The named object decides the action: the same layout with another named color moves elsewhere."""
    rng = np.random.default_rng(0)
    scene = sample_scene(rng)
    other = next(c for c in scene.colors if c != scene.target_color)
    _, actions = rollout(scene, 6)
    _, other_actions = rollout(type(scene)(scene.colors, scene.centers, other, scene.start), 6)
    assert not np.allclose(actions, other_actions)
    states, actions = rollout(scene, 40)
    assert np.linalg.norm(states[-1] + actions[-1] - scene.target) < 0.01  # the reach converges on the target


# ---------------------------------------------------------------------------------------------------- samples


def test_chunks_follow_the_episode_and_repeat_the_last_action(datasets_dir: Path) -> None:
    root = datasets_dir / "image"
    dataset = LeRobotEpisodeDataset(root, HORIZON, progress=False)
    assert len(dataset) == sum(LENGTHS)
    position = 0
    for episode, length in enumerate(LENGTHS):
        actions = _episode_actions(root, episode)
        padded = np.concatenate([actions, np.repeat(actions[-1:], HORIZON, axis=0)])
        for t in range(length):
            sample = dataset[position + t]
            assert sample["episode_index"] == episode and sample["frame_index"] == t
            np.testing.assert_array_equal(sample["actions"], padded[t : t + HORIZON])
            np.testing.assert_array_equal(sample["action_is_pad"], np.arange(t, t + HORIZON) >= length)
        position += length
    last = dataset[LENGTHS[0] - 1]  # the last frame of episode 0: one real action, then repeats
    assert last["action_is_pad"].tolist() == [False] + [True] * (HORIZON - 1)
    assert (last["actions"] == last["actions"][0]).all()


def test_video_and_image_storage_give_the_same_samples(datasets_dir: Path) -> None:
    video = LeRobotEpisodeDataset(datasets_dir / "video", HORIZON, progress=False)
    image = LeRobotEpisodeDataset(datasets_dir / "image", HORIZON, progress=False)
    differences = []
    for index in range(len(video)):
        a, b = video[index], image[index]
        assert a["prompt"] == b["prompt"] and a["prompt"].startswith("move to the ")
        np.testing.assert_array_equal(a["state"], b["state"])
        np.testing.assert_array_equal(a["actions"], b["actions"])
        frame_a, frame_b = a["images"][CAMERA_KEY], b["images"][CAMERA_KEY]
        assert frame_a.shape == frame_b.shape == (32, 32, 3) and frame_a.dtype == np.uint8
        differences.append(np.abs(frame_a.astype(int) - frame_b.astype(int)).mean())
    assert max(differences) < 8  # h264 at crf 8 with 4:2:0 chroma: a few gray levels on average


def test_video_reader_random_access_matches_sequential(datasets_dir: Path) -> None:
    root = datasets_dir / "video"
    path = root / "videos" / CAMERA_KEY / "chunk-000" / "file-000.mp4"
    fps = read_info(root)["fps"]
    count = sum(LENGTHS[:4])
    sequential = VideoFrameReader(fps)
    frames = [sequential.frame(path, k / fps).copy() for k in range(count)]
    shuffled = VideoFrameReader(fps, cache_bytes=2 * frames[0].nbytes)  # almost no cache: every request seeks
    for k in np.random.default_rng(0).permutation(count):
        np.testing.assert_array_equal(shuffled.frame(path, k / fps), frames[k])
    with pytest.raises(LeRobotDatasetError, match="no video frame"):
        sequential.frame(path, (count + 3) / fps)


def test_state_action_pass_matches_items(datasets_dir: Path) -> None:
    dataset = LeRobotEpisodeDataset(datasets_dir / "image", HORIZON, episodes=[1, 3], progress=False)
    states = np.concatenate([batch["state"] for batch in dataset.iter_state_action_chunks()])
    chunks = np.concatenate([batch["actions"] for batch in dataset.iter_state_action_chunks()])
    assert chunks.shape == (LENGTHS[1] + LENGTHS[3], HORIZON, 2)
    for index in range(len(dataset)):
        np.testing.assert_array_equal(states[index], dataset[index]["state"])
        np.testing.assert_array_equal(chunks[index], dataset[index]["actions"])


def test_pickles_for_dataloader_workers(datasets_dir: Path) -> None:
    dataset = LeRobotEpisodeDataset(datasets_dir / "video", HORIZON, episodes=[4, 5], progress=False)
    first = dataset[7]
    clone = pickle.loads(pickle.dumps(dataset))
    np.testing.assert_array_equal(clone[7]["images"][CAMERA_KEY], first["images"][CAMERA_KEY])


# ---------------------------------------------------------------------------------------------------- episode ends


def test_short_episode_policies(datasets_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = datasets_dir / "image"
    with pytest.raises(LeRobotDatasetError, match=r"episode\(s\).*shorter than the action horizon 5: 2 \(3 frames\)"):
        LeRobotEpisodeDataset(root, HORIZON, short_episodes="error", progress=False)
    with caplog.at_level(logging.WARNING):
        skipped = LeRobotEpisodeDataset(root, HORIZON, short_episodes="skip", progress=False)
    assert 2 not in skipped.episode_indices and len(skipped) == sum(LENGTHS) - 3
    assert "skipping them" in caplog.text
    with pytest.raises(LeRobotDatasetError, match="no episodes to read"):
        LeRobotEpisodeDataset(root, HORIZON, episodes=[2], short_episodes="skip", progress=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        padded = LeRobotEpisodeDataset(root, HORIZON, episodes=[2], progress=False)
    assert "repeat the last action" in caplog.text
    first = padded[0]
    assert first["action_is_pad"].tolist() == [False, False, False, True, True]
    np.testing.assert_array_equal(first["actions"][3:], np.repeat(first["actions"][2:3], 2, axis=0))


# ---------------------------------------------------------------------------------------------------- other layouts


def _to_v21(v3_root: Path, v21_root: Path) -> None:
    """Rewrite an image-storage v3.0 dataset in LeRobot's v2.1 layout (one parquet per episode, jsonl metadata)."""
    info = read_info(v3_root)
    frames = pq.read_table(sorted((v3_root / "data").glob("chunk-*/*.parquet"))[0]).schema
    tables = [pq.read_table(p) for p in sorted((v3_root / "data").glob("chunk-*/*.parquet"))]
    table = pa.concat_tables(tables).cast(frames)
    (v21_root / "meta").mkdir(parents=True)
    info.update(
        codebase_version="v2.1",
        data_path="data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        video_path=None,
    )
    (v21_root / "meta" / "info.json").write_text(json.dumps(info))
    tasks = pd.read_parquet(v3_root / "meta" / "tasks.parquet")
    with open(v21_root / "meta" / "tasks.jsonl", "w") as f:
        for task, row in tasks.iterrows():
            f.write(json.dumps({"task_index": int(row["task_index"]), "task": task}) + "\n")
    episodes = pd.read_parquet(v3_root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    with open(v21_root / "meta" / "episodes.jsonl", "w") as f:
        for _, row in episodes.iterrows():
            f.write(json.dumps({"episode_index": int(row["episode_index"]), "tasks": list(row["tasks"]), "length": int(row["length"])}) + "\n")
    episode_column = table["episode_index"].to_numpy()
    for episode in np.unique(episode_column):
        path = v21_root / info["data_path"].format(episode_chunk=0, episode_index=int(episode))
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table.filter(pa.array(episode_column == episode)), path)


def test_reads_lerobot_v21_layout(datasets_dir: Path, tmp_path: Path) -> None:
    _to_v21(datasets_dir / "image", tmp_path / "v21")
    v21 = LeRobotEpisodeDataset(tmp_path / "v21", HORIZON, progress=False)
    v3 = LeRobotEpisodeDataset(datasets_dir / "image", HORIZON, progress=False)
    assert len(v21) == len(v3)
    for index in (0, 13, len(v3) - 1):
        a, b = v21[index], v3[index]
        assert a["prompt"] == b["prompt"]
        np.testing.assert_array_equal(a["actions"], b["actions"])
        np.testing.assert_array_equal(a["images"][CAMERA_KEY], b["images"][CAMERA_KEY])


def test_hf_datasets_map_style_and_streaming(datasets_dir: Path, tmp_path: Path) -> None:
    dataset = LeRobotEpisodeDataset(datasets_dir / "image", HORIZON, episodes=[0, 1], progress=False)
    streamed = list(dataset.to_hf_dataset(streaming=True))
    assert len(streamed) == len(dataset)
    materialised = dataset.to_hf_dataset(cache_dir=str(tmp_path / "hf"))
    assert len(materialised) == len(dataset)
    mapped = materialised.map(lambda row: {"first_dx": row["actions"][0][0]}, remove_columns=["images"])
    for index in (0, 5, len(dataset) - 1):
        sample = dataset[index]
        for row in (streamed[index], materialised[index]):
            assert row["prompt"] == sample["prompt"] and row["frame_index"] == sample["frame_index"]
            np.testing.assert_allclose(np.asarray(row["actions"], np.float32), sample["actions"])
            assert row["action_is_pad"] == sample["action_is_pad"].tolist()
            np.testing.assert_array_equal(np.asarray(row["images"][CAMERA_KEY]), sample["images"][CAMERA_KEY])
        assert mapped[index]["first_dx"] == pytest.approx(float(sample["actions"][0][0]))


# ---------------------------------------------------------------------------------------------------- broken datasets


def test_a_hub_dataset_id_says_how_to_make_a_local_copy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"^lerobot/pusht is no local folder: .* `hf download lerobot/pusht "
                                                r"--repo-type dataset --local-dir data/pusht` .* --dataset data/pusht$"):
        LeRobotEpisodeDataset("lerobot/pusht", HORIZON)


def test_missing_files_are_named(copy_of, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not a LeRobot dataset"):
        LeRobotEpisodeDataset(tmp_path, HORIZON)
    root = copy_of("video")
    (root / "data" / "chunk-000" / "file-001.parquet").unlink()
    with pytest.raises(FileNotFoundError, match=r"file-001.parquet \(episodes \[4, 5\]\) is missing"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)
    LeRobotEpisodeDataset(root, HORIZON, episodes=[0, 1], progress=False)  # the other file's episodes still load
    (root / "videos" / CAMERA_KEY / "chunk-000" / "file-000.mp4").unlink()
    with pytest.raises(FileNotFoundError, match=r"file-000.mp4 of camera 'observation.images.base', episode 0 is missing"):
        LeRobotEpisodeDataset(root, HORIZON, episodes=[0], progress=False)
    shutil.rmtree(root / "meta" / "episodes")
    with pytest.raises(FileNotFoundError, match="no episode metadata"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)


def test_mismatched_feature_shapes(copy_of) -> None:
    root = copy_of("image")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"]["action"]["shape"] = [3]
    info_path.write_text(json.dumps(info))
    with pytest.raises(LeRobotDatasetError, match=r"column 'action' has rows of length 2 .* declares shape \[3\]"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)
    info["features"]["action"]["shape"] = [2]
    info["features"][CAMERA_KEY]["shape"] = [48, 48, 3]
    info_path.write_text(json.dumps(info))
    dataset = LeRobotEpisodeDataset(root, HORIZON, progress=False)
    with pytest.raises(LeRobotDatasetError, match=r"episode 0 frame 0, camera 'observation.images.base': the image is "
                                                  r"32 x 32 \(height x width\), but meta/info.json declares 48 x 48"):
        dataset[0]
    with pytest.raises(LeRobotDatasetError, match="state_key 'observation.joints' is not a feature"):
        LeRobotEpisodeDataset(root, HORIZON, state_key="observation.joints", progress=False)


def test_bad_values_and_inconsistent_metadata(copy_of) -> None:
    root = copy_of("image")
    path = root / "data" / "chunk-000" / "file-000.parquet"
    table = pq.read_table(path)
    actions = table["action"].to_pylist()
    actions[3] = [float("nan"), 0.0]
    pq.write_table(table.set_column(table.schema.get_field_index("action"), "action", pa.array(actions, table.schema.field("action").type)), path)
    with pytest.raises(LeRobotDatasetError, match="'action' of episode 0 frame 3 is not finite"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)
    pq.write_table(table.slice(1), path)  # drop frame 0 of episode 0
    with pytest.raises(LeRobotDatasetError, match=r"episode 0 should have frames 0..11 \(meta length 12\), found 11 rows"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)
    info = json.loads((root / "meta" / "info.json").read_text())
    info["codebase_version"] = "v1.6"
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(LeRobotDatasetError, match="codebase_version v1.6 is not supported"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)


def test_video_shorter_than_metadata(copy_of, tmp_path: Path) -> None:
    """A truncated recording: the metadata promises frames the mp4 does not have."""
    root = copy_of("video")
    fps = read_info(root)["fps"]
    episodes = pd.read_parquet(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    episodes.loc[episodes["episode_index"] == 5, f"videos/{CAMERA_KEY}/from_timestamp"] += 5 / fps
    episodes.to_parquet(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    dataset = LeRobotEpisodeDataset(root, HORIZON, episodes=[5], progress=False)
    dataset[0]  # still inside the file
    with pytest.raises(LeRobotDatasetError, match=r"file-001.mp4: no video frame within .* of t="):
        dataset[len(dataset) - 1]


def test_decodes_av1_video_lerobots_default_codec(tmp_path: Path) -> None:
    """LeRobot v3.0 encodes with libsvtav1 by default; PyAV decodes it (libdav1d) at the same frame times."""
    options = dict(num_episodes=3, episode_lengths=[6, 4, 5], image_size=64, seed=5, episodes_per_file=2)
    av1 = LeRobotEpisodeDataset(write_synthetic_dataset(tmp_path / "av1", codec="libsvtav1", **options), HORIZON, progress=False)
    png = LeRobotEpisodeDataset(write_synthetic_dataset(tmp_path / "png", storage="image", **options), HORIZON, progress=False)
    for index in range(len(png)):
        a, b = av1[index]["images"][CAMERA_KEY], png[index]["images"][CAMERA_KEY]
        assert np.abs(a.astype(int) - b.astype(int)).mean() < 8


# ---------------------------------------------------------------------------------------------------- paths (issue 28.10)


@pytest.mark.parametrize("where", ["image cell", "image cell, absolute", "data_path", "video_path"])
def test_paths_the_dataset_names_stay_inside_it(where: str, copy_of, tmp_path: Path) -> None:
    """An image cell `../../../../../etc/passwd` was opened outside the dataset root. Every path a dataset's own
    files name (image cells, the data and video path templates) is refused when it leads out of the root."""
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"not for the reader")
    root = copy_of("video" if where == "video_path" else "image")
    if where.startswith("image cell"):
        target = str(secret) if where.endswith("absolute") else "../" * 8 + str(secret).lstrip("/")
        for path in sorted((root / "data").glob("chunk-*/*.parquet")):
            table = pq.read_table(path)
            cells = pa.array([{"bytes": None, "path": target}] * len(table), table.schema.field(CAMERA_KEY).type)
            pq.write_table(table.set_column(table.schema.get_field_index(CAMERA_KEY), CAMERA_KEY, cells), path)
        dataset = LeRobotEpisodeDataset(root, HORIZON, progress=False)
        with pytest.raises(LeRobotDatasetError, match="image cell path .* leads outside the dataset folder"):
            dataset[0]
        return
    info = json.loads((root / "meta" / "info.json").read_text())
    key = "data_path" if where == "data_path" else "video_path"
    info[key] = "../" + info[key]
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(LeRobotDatasetError, match=f"meta/info.json {key} '../.*' leads outside the dataset folder"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)


# ---------------------------------------------------------------------------------------------------- malformed inputs (issue 38)


def _replace_column(path: Path, name: str, values: list) -> None:
    table = pq.read_table(path)
    column = pa.array(values, table.schema.field(name).type)
    pq.write_table(table.set_column(table.schema.get_field_index(name), name, column), path)


def _edit_info(root: Path, **changes: object) -> None:
    info = json.loads((root / "meta" / "info.json").read_text())
    (root / "meta" / "info.json").write_text(json.dumps({**info, **changes}))


def _timestamps(root: Path, change: Callable[[np.ndarray], np.ndarray]) -> None:
    """Change the parquet timestamps of episode 1 (frames 12..20 of file-000: episode 0 has 12 frames)."""
    path = root / "data" / "chunk-000" / "file-000.parquet"
    values = pq.read_table(path)["timestamp"].to_numpy().astype(np.float64)
    values[12:21] = change(values[12:21])
    _replace_column(path, "timestamp", values.tolist())


def _from_timestamp(root: Path, value: float) -> None:
    path = root / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    episodes = pd.read_parquet(path)
    episodes.loc[episodes["episode_index"] == 1, f"videos/{CAMERA_KEY}/from_timestamp"] = value
    episodes.to_parquet(path)


TIMESTAMP_FILE = "data/chunk-000/file-000.parquet: episode 1 frame"
BROKEN_VIDEO_TIMES = {  # how the video times of episode 1 are broken -> what the refusal says
    "timestamps all 0": (lambda root: _timestamps(root, np.zeros_like),
                         rf"{TIMESTAMP_FILE} 1 has timestamp 0 s, but its video frame is at 0.1 s .*8 of 9 frames"),
    "timestamps one frame late": (lambda root: _timestamps(root, lambda t: t + 0.1),
                                  rf"{TIMESTAMP_FILE} 0 has timestamp 0.1 s, but its video frame is at 0 s"),
    "timestamps 0.6 frame early": (lambda root: _timestamps(root, lambda t: t - 0.06), rf"{TIMESTAMP_FILE} 0 has timestamp -0.06 s"),
    "timestamps with a NaN": (lambda root: _timestamps(root, lambda t: np.where(np.arange(len(t)) == 4, np.nan, t)),
                        rf"{TIMESTAMP_FILE} 4 has timestamp nan s"),
    "timestamps with an inf": (lambda root: _timestamps(root, lambda t: np.where(np.arange(len(t)) == 2, np.inf, t)),
                              rf"{TIMESTAMP_FILE} 2 has timestamp inf s"),
    "from_timestamp null": (lambda root: _from_timestamp(root, float("nan")),
                           rf"meta/episodes/chunk-000/file-000.parquet: episode 1 has videos/{CAMERA_KEY}/from_timestamp None"),
    "from_timestamp negative": (lambda root: _from_timestamp(root, -1.0), "episode 1 has .*from_timestamp -1.0; expected"),
}


@pytest.mark.parametrize("broken", sorted(BROKEN_VIDEO_TIMES))
def test_video_times_that_select_other_frames_are_refused(broken: str, copy_of) -> None:
    """Issue 38.10: with the parquet timestamps at 0 an episode read its first video frame for every sample (1
    distinct frame of 18) and training went on. A timestamp more than half a frame from frame_index / fps, or not
    finite, is refused when the dataset is opened, naming the data file, episode, frame, camera and video file."""
    root = copy_of("video")
    change, expected = BROKEN_VIDEO_TIMES[broken]
    change(root)
    with pytest.raises(LeRobotDatasetError, match=expected) as refused:
        LeRobotEpisodeDataset(root, HORIZON, progress=False)
    if broken.startswith("timestamps"):  # the data file's: it names the camera and video file; other episodes load
        assert f"'{CAMERA_KEY}' ({root / 'videos' / CAMERA_KEY / 'chunk-000' / 'file-000.mp4'})" in str(refused.value)
        LeRobotEpisodeDataset(root, HORIZON, episodes=[0, 2, 3, 4, 5], progress=False)
    image_only = copy_of("image")  # timestamps select nothing in a dataset of images: not checked
    _timestamps(image_only, np.zeros_like)
    LeRobotEpisodeDataset(image_only, HORIZON, progress=False)


def test_timestamps_within_half_a_frame_select_the_same_frames(copy_of) -> None:
    """Jitter of less than half a frame still selects the recorded frames (LeRobot's reader tolerance then applies)."""
    root = copy_of("video")
    reference = LeRobotEpisodeDataset(root, HORIZON, episodes=[1], progress=False)
    _timestamps(root, lambda t: t + 0.04)
    jittered = LeRobotEpisodeDataset(root, HORIZON, episodes=[1], video_tolerance_s=0.045, progress=False)
    for index in range(len(reference)):
        np.testing.assert_array_equal(jittered[index]["images"][CAMERA_KEY], reference[index]["images"][CAMERA_KEY])


BAD_INFO = {  # meta/info.json field -> values refused by name, and what the refusal says
    "fps": [(0, r"fps must be a finite number > 0, got 0"), (-10, "fps must be .* got -10"),
            (float("nan"), "got nan"), ("30", r"got '30' \(str\)"), (True, r"\(bool\)")],
    "data_path": [
        (5, r"data_path must be a path template string .* got 5 \(int\)"),
        (None, r"data_path must be a path template string .* got None"),
        ("data/{nope}.parquet", r"data_path 'data/\{nope\}.parquet' names the field \{nope\}; its fields are chunk_index, file_index"),
        ("data/{0}.parquet", r"names the field \{0\}"),
        ("data/{chunk_index.__class__}.parquet", r"names the field \{chunk_index.__class__\}"),
        ("data/{chunk_index:0200000000d}.parquet", r"asks for a width of 200000000 characters in \{chunk_index:0200000000d\}"),
        ("data/{chunk_index:.999f}.parquet", f"asks for a width of 999 characters .* at most {MAX_TEMPLATE_WIDTH}"),
        ("data/{chunk_index:{file_index}d}.parquet", r"nests a field"),
        ("data/{chunk_index:s}.parquet", r"cannot be filled \(Unknown format code 's'"),
        ("data/{chunk_index.parquet", r"is not a format string"),
        ("data/" + "x" * 5000, r"data_path 'data/x+ makes paths of 5005 characters; a path has at most 4096"),
        ("data/{chunk_index:032d}" * 200, r"makes paths of 7400 characters"),
    ],
    "video_path": [("videos/{video_key}/{episode_index}.mp4", r"video_path .* names the field \{episode_index\}; its fields "
                                                               r"are video_key, chunk_index, file_index"),
                   (7, "video_path must be a path template string")],
}


@pytest.mark.parametrize("field, value, expected", [(f, v, e) for f, cases in BAD_INFO.items() for v, e in cases],
                         ids=lambda x: str(x)[:40])
def test_info_fields_are_refused_by_name(field: str, value: object, expected: str, copy_of) -> None:
    """Issue 38.14 / 38.15: `{chunk_index:0200000000d}` built a 200 MB path per episode (17.8 s, +1.3 GB) before
    failing, `{nope}` and `5` gave tracebacks, fps 0 and -10 were accepted. Each is refused by name at once."""
    root = copy_of("video")
    _edit_info(root, **{field: value})
    with pytest.raises(LeRobotDatasetError, match=rf"meta/info.json: .*{expected}"):
        LeRobotEpisodeDataset(root, HORIZON, progress=False)


def _png(width: int, height: int, pixels: bytes = b"\x00" * 16) -> bytes:
    """A PNG file whose header says `width` x `height` RGB, with the (compressed) data `pixels`: opening it reads
    only the header, decoding it fails unless the data is whole."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


def _png_bytes(pixels: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


BAD_CELLS = {  # the image cell of episode 1 frame 2 -> what the refusal says after "episode 1 frame 2, camera ...: "
    "null": (None, r"the image cell is empty \(None\)"),
    "neither bytes nor path": ({"bytes": None, "path": None}, "the image cell is empty"),
    "not an image": ({"bytes": b"hello, not a PNG", "path": None}, r"the image cell holds no usable image \(cannot identify"),
    "a truncated PNG": ({"bytes": _png(32, 32), "path": None}, "the image cell holds no usable image"),
    "20000 x 20000": ({"bytes": _png(20000, 20000), "path": None}, r"Image size \(400000000 pixels\) exceeds limit .*"
                      r"meta/info.json declares 32 x 32"),
    "9000 x 9000": ({"bytes": _png(9000, 9000), "path": None}, r"the image is 9000 x 9000 \(height x width\), but "
                    r"meta/info.json declares 32 x 32; refused before decoding"),
    "16-bit": ({"bytes": _png_bytes(np.full((32, 32), 4000, np.uint16)), "path": None},
               r"the image cell holds no usable image \(the image: a PIL image of mode 'I;16' \(integer pixels"),
    "a missing file": ({"bytes": None, "path": "images/gone.png"}, r"the image cell holds no usable image \(.*No such file"),
}


@pytest.mark.parametrize("cell", sorted(BAD_CELLS))
def test_image_cells_that_hold_no_frame_are_refused_naming_episode_and_camera(cell: str, copy_of) -> None:
    """Issue 38.15: a null cell, a cell that is no image and a 20000 x 20000 PNG gave tracebacks (or a decode of
    1.2 GB), a 16-bit PNG (a depth camera) was clipped to white. Each is refused naming the data file, episode,
    frame and camera; the size is checked from the header, before decoding (the truncated 9000 x 9000 PNG would
    fail to decode: its refusal is the size's)."""
    root = copy_of("image")
    path = root / "data" / "chunk-000" / "file-000.parquet"
    cells = pq.read_table(path)[CAMERA_KEY].to_pylist()
    value, expected = BAD_CELLS[cell]
    cells[LENGTHS[0] + 2] = value
    _replace_column(path, CAMERA_KEY, cells)
    dataset = LeRobotEpisodeDataset(root, HORIZON, progress=False)
    dataset[LENGTHS[0] + 1]  # the frame before is whole
    with pytest.raises(LeRobotDatasetError, match=rf"file-000.parquet: episode 1 frame 2, camera '{CAMERA_KEY}': {expected}"):
        dataset[LENGTHS[0] + 2]
