"""LeRobot on-disk datasets: layout, action chunks at episode ends, video decoding, broken datasets, HF datasets."""

from __future__ import annotations

import json
import logging
import pickle
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pi0_torch.data.lerobot_dataset import (
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
    with pytest.raises(LeRobotDatasetError, match=r"decoded frame has shape \(32, 32, 3\).*\(48, 48, 3\)"):
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
