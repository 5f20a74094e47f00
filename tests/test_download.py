"""`pi0-torch convert --checkpoint NAME` / `--input gs://...`: openpi's bucket layout served from 127.0.0.1.

The server speaks the two parts of Google Cloud Storage's HTTP API the download uses (the JSON listing, paged, with
base64 MD5s; media downloads with `Range`), serves the pi0_small fixture checkpoint as a published checkpoint and a
small SentencePiece model as PaliGemma's tokenizer, and can cut responses in the middle or list a wrong MD5.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shlex
import socket
import threading
import urllib.parse
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import huggingface_hub.constants
import psutil
import pytest
import torch
from conftest import FIXTURES

from pi0_torch import PI0Config, PI0FastConfig, PI0FastProcessor, PI0Processor
from pi0_torch.cli import main as cli_main
from pi0_torch.conversion.download import (
    CACHE_ENV,
    ENDPOINT_ENV,
    MANIFEST_FILE,
    PART_SUFFIX,
    RETRIES,
    DownloadError,
    download_checkpoint,
    fetch_openpi_checkpoint,
)
from pi0_torch.processing.tokenization import build_test_tokenizer
from pi0_torch.utils.files import OWNER_FILE, OutputPathError, remove_stale_partials

CHECKPOINT = "checkpoints/pi0_droid"  # served under a published name; its assets/reference served as assets/droid
URL = f"gs://openpi-assets/{CHECKPOINT}"
PAGE_SIZE = 4  # small pages, so that the listing's nextPageToken is followed


class FakeBucket(ThreadingHTTPServer):
    """GCS on 127.0.0.1: `objects[(bucket, name)] = bytes`; `cuts[name]` responses of that object stop halfway;
    `bad_md5` names are listed with a wrong MD5; `requests` records (path, Range header) of every request."""

    daemon_threads = True

    def __init__(self, objects: dict[tuple[str, str], bytes]) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.objects = objects
        self.cuts: dict[str, int] = {}
        self.bad_md5: set[str] = set()
        self.requests: list[tuple[str, str | None]] = []

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}"

    def media_requests(self, name: str) -> list[str | None]:
        return [rng for path, rng in self.requests if urllib.parse.unquote(path).endswith("/" + name)]


class _Handler(BaseHTTPRequestHandler):
    server: FakeBucket

    def log_message(self, *args: object) -> None:  # quiet
        pass

    def do_GET(self) -> None:
        self.server.requests.append((self.path.split("?")[0], self.headers.get("Range")))
        url = urllib.parse.urlparse(self.path)
        parts = url.path.split("/")
        if url.path.startswith("/storage/v1/b/"):  # /storage/v1/b/<bucket>/o?prefix=...&pageToken=...
            self._listing(urllib.parse.unquote(parts[4]), urllib.parse.parse_qs(url.query))
        else:  # /<bucket>/<object>
            self._media(urllib.parse.unquote(parts[1]), urllib.parse.unquote("/".join(parts[2:])))

    def _listing(self, bucket: str, query: dict[str, list[str]]) -> None:
        prefix = query.get("prefix", [""])[0]
        names = sorted(n for b, n in self.server.objects if b == bucket and n.startswith(prefix))
        start = int(query.get("pageToken", ["0"])[0])
        items = []
        for name in names[start : start + PAGE_SIZE]:
            data = self.server.objects[bucket, name]
            md5 = hashlib.md5(data + (b"x" if name in self.server.bad_md5 else b"")).digest()
            items.append({"name": name, "size": str(len(data)), "md5Hash": base64.b64encode(md5).decode()})
        page: dict[str, object] = {"items": items} if items else {}
        if start + PAGE_SIZE < len(names):
            page["nextPageToken"] = str(start + PAGE_SIZE)
        self._send(200, json.dumps(page).encode(), {"Content-Type": "application/json"})

    def _media(self, bucket: str, name: str) -> None:
        data = self.server.objects.get((bucket, name))
        if data is None:
            self._send(404, b"not found", {})
            return
        begin, status, headers = 0, 200, {}
        if self.headers.get("Range"):
            begin = int(self.headers["Range"].removeprefix("bytes=").rstrip("-"))
            status, headers = 206, {"Content-Range": f"bytes {begin}-{len(data) - 1}/{len(data)}"}
        body = data[begin:]
        if self.server.cuts.get(name, 0) > 0:  # announce the whole body, send half of it, hang up
            self.server.cuts[name] -= 1
            self.send_response(status)
            for key, value in {**headers, "Content-Length": str(len(body))}.items():
                self.send_header(key, value)
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        self._send(status, body, headers)

    def _send(self, status: int, body: bytes, headers: dict[str, str]) -> None:
        self.send_response(status)
        for key, value in {**headers, "Content-Length": str(len(body))}.items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)


def _fixture_objects(tmp_path: Path) -> dict[tuple[str, str], bytes]:
    """pi0_small as checkpoints/pi0_droid, pi05_small as checkpoints/pi05_droid and pi0_fast_small as
    checkpoints/pi0_fast_droid (norm stats under assets/droid), and a small SentencePiece model as PaliGemma's
    tokenizer."""
    objects = {}
    for variant, name in (("pi0_small", "pi0_droid"), ("pi05_small", "pi05_droid"), ("pi0_fast_small", "pi0_fast_droid")):
        step = FIXTURES / variant / "ckpt" / "0"
        for path in sorted(p for p in step.rglob("*") if p.is_file()):
            relative = path.relative_to(step).as_posix().replace("assets/reference/", "assets/droid/")
            objects["openpi-assets", f"checkpoints/{name}/{relative}"] = path.read_bytes()
    build_test_tokenizer(save_to=tmp_path / "tokenizer.model")
    objects["big_vision", "paligemma_tokenizer.model"] = (tmp_path / "tokenizer.model").read_bytes()
    return objects


@pytest.fixture
def bucket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[FakeBucket]:
    server = FakeBucket(_fixture_objects(tmp_path))
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    monkeypatch.setenv(ENDPOINT_ENV, server.endpoint)
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    yield server
    server.shutdown()
    server.server_close()


def _cached(tmp_path: Path) -> Path:
    return tmp_path / "cache" / "openpi-assets" / CHECKPOINT


def _largest(server: FakeBucket) -> str:
    names = [n for b, n in server.objects if b == "openpi-assets" and n.startswith(CHECKPOINT + "/")]
    return max(names, key=lambda n: len(server.objects["openpi-assets", n]))


def _partial_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(PART_SUFFIX) or ".partial-" in p.name]


def test_convert_published_checkpoint_downloads_then_uses_the_cache(bucket: FakeBucket, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`pi0-torch convert --checkpoint pi0_droid`: the whole checkpoint (paged listing) and the tokenizer are
    downloaded byte for byte, converted with openpi's pi0_droid settings (asset id droid, action horizon 10); a
    second conversion reads the cache and makes no request."""
    assert cli_main(["convert", "--checkpoint", "pi0_droid", "--output-dir", str(tmp_path / "out"), "--no-progress"]) == 0
    cached = _cached(tmp_path)
    served = {(b, n): data for (b, n), data in bucket.objects.items() if b == "big_vision" or n.startswith(CHECKPOINT + "/")}
    for (bucket_name, name), data in served.items():
        assert (tmp_path / "cache" / bucket_name / name).read_bytes() == data, name
    manifest = json.loads((cached / MANIFEST_FILE).read_text())
    assert len(manifest["objects"]) == len(served) - 1 > PAGE_SIZE
    assert sorted(p.name for p in (tmp_path / "cache" / "openpi-assets" / "checkpoints").iterdir()) == ["pi0_droid"]
    assert _partial_files(tmp_path / "cache") == []
    assert PI0Config.from_pretrained(tmp_path / "out").action_horizon == 10
    processor = PI0Processor.from_pretrained(tmp_path / "out")
    assert processor.action_horizon == 10 and processor.tokenizer.vocab_size == build_test_tokenizer().vocab_size

    bucket.requests.clear()
    assert cli_main(["convert", "--from", "openpi", "--input", URL, "--output-dir", str(tmp_path / "again"), "--no-progress"]) == 0
    assert bucket.requests == []


def test_cut_download_resumes_with_range_requests(bucket: FakeBucket, tmp_path: Path) -> None:
    """A connection cut in the middle is continued from the bytes already written (an HTTP Range request), within
    the call; when every retry is cut, the call fails, keeps the verified files and the partial file, publishes
    nothing, and the next call continues where it stopped."""
    largest = _largest(bucket)
    size = len(bucket.objects["openpi-assets", largest])
    bucket.cuts[largest] = 1
    folder = download_checkpoint(URL, asset_id="droid")
    assert bucket.media_requests(largest) == [None, f"bytes={size // 2}-"]
    assert (folder / largest.removeprefix(CHECKPOINT + "/")).read_bytes() == bucket.objects["openpi-assets", largest]

    other = tmp_path / "cache2"
    bucket.requests.clear()
    bucket.cuts[largest] = RETRIES + 1  # every attempt of this call is cut
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CACHE_ENV, str(other))
        with pytest.raises(DownloadError, match="run the same command again to resume"):
            download_checkpoint(URL)
        final = other / "openpi-assets" / CHECKPOINT
        assert not final.exists()
        (partial,) = final.parent.iterdir()
        assert partial.name == ".pi0_droid.partial-resumable"
        part = partial / (largest.removeprefix(CHECKPOINT + "/") + PART_SUFFIX)
        written = part.stat().st_size
        assert 0 < written < size
        finished = {p.relative_to(partial).as_posix() for p in partial.rglob("*") if p.is_file() and not p.name.startswith(".pi0")}
        finished.discard(part.relative_to(partial).as_posix())
        assert finished  # files before the cut one were completed and kept

        bucket.requests.clear()
        assert download_checkpoint(URL) == final
        assert bucket.media_requests(largest) == [f"bytes={written}-"]
        assert all(bucket.media_requests(name) == [] for name in finished)  # verified files are not fetched again
        assert (final / largest.removeprefix(CHECKPOINT + "/")).read_bytes() == bucket.objects["openpi-assets", largest]
        assert _partial_files(other) == []


def test_checksum_mismatch_is_refused_and_nothing_is_left_half_written(bucket: FakeBucket, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A file whose bytes do not hash to the listed MD5 is deleted and the conversion fails with a one-line error;
    no checkpoint is published in the cache and no output folder appears."""
    bucket.bad_md5.add(_largest(bucket))
    assert cli_main(["convert", "--checkpoint", "pi0_droid", "--output-dir", str(tmp_path / "out"), "--no-progress"]) == 1
    error = capsys.readouterr().err
    assert error.startswith("error: ") and "does not match the bucket's" in error and len(error.strip().splitlines()) == 1
    assert not _cached(tmp_path).exists() and not (tmp_path / "out").exists()
    assert not [p for p in (tmp_path / "cache").rglob("*") if p.name.endswith(PART_SUFFIX)]


def test_refusals_before_downloading(bucket: FakeBucket, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Asset ids the checkpoint does not have, and an occupied output folder, fail before any file is downloaded."""
    with pytest.raises(DownloadError, match="no norm stats for asset id 'trossen'; choices: droid"):
        fetch_openpi_checkpoint(URL, asset_id="trossen")
    assert all(path.startswith("/storage/v1/") for path, _ in bucket.requests)  # the listing only
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "file").write_text("x")
    bucket.requests.clear()
    assert cli_main(["convert", "--checkpoint", "pi0_droid", "--output-dir", str(tmp_path / "busy")]) == 1
    assert "holds files that pi0-torch did not write" in capsys.readouterr().err and bucket.requests == []


def test_published_fast_checkpoint_converts_with_its_settings(
    bucket: FakeBucket, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`convert --checkpoint pi0_fast_droid`: the checkpoint comes from the bucket, the FAST tokenizer from the
    Hugging Face hub or `--fast-tokenizer`; openpi's pi0_fast_droid settings apply (8 action dims, 10 steps, asset id
    droid). When the hub cannot be reached and no copy is given, the error says so before the checkpoint downloads."""
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)  # never the real hub, here or elsewhere
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    fast = FIXTURES / "pi0_fast_small"
    command = ["convert", "--checkpoint", "pi0_fast_droid", "--tokenizer", str(fast / "tokenizer.model"), "--no-progress"]
    assert cli_main([*command, "--output-dir", str(tmp_path / "offline")]) == 1
    error = capsys.readouterr().err
    assert "FAST tokenizer physical-intelligence/fast" in error and "--fast-tokenizer DIR" in error
    assert len(error.strip().splitlines()) == 1 and bucket.requests == [] and not (tmp_path / "offline").exists()

    assert cli_main([*command, "--fast-tokenizer", str(fast / "fast_tokenizer"), "--output-dir", str(tmp_path / "out")]) == 0
    config = PI0FastConfig.from_pretrained(tmp_path / "out")
    assert (config.action_dim, config.action_horizon) == (8, 10)
    processor = PI0FastProcessor.from_pretrained(tmp_path / "out")
    assert processor.action_tokenizer.vocab_size == 512 and "norm stats: " in capsys.readouterr().out


def test_readme_quick_start_runs_as_written(bucket: FakeBucket, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's Quick start, copied verbatim: its `pi0-torch` command (run in this process; the bucket serves
    the small π0.5 fixture as pi05_droid), then its Python block, then its GPU block with "cuda" read as "cpu" (there
    `capture_sampling` leaves sampling eager)."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    section = readme.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    (command,) = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    code, gpu_code = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    program, *arguments = shlex.split(command)
    assert program == "pi0-torch"
    monkeypatch.chdir(tmp_path)
    assert cli_main(arguments) == 0
    names: dict = {}
    exec(compile(code, "README.md", "exec"), names)
    assert tuple(names["chunk"].shape) == (1, 15, 32) and tuple(names["actions"].shape) == (1, 15, 8)
    assert torch.isfinite(names["loss"])
    exec(compile(gpu_code.replace('"cuda"', '"cpu"'), "README.md", "exec"), names)
    assert names["model"].dtype == torch.bfloat16 and names["model"].sampling_captured
    assert tuple(names["chunk"].shape) == (1, 15, 32) and torch.isfinite(names["chunk"]).all()


def test_readme_offline_quick_start_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """The README's "Quick start without a network", verbatim: its command converts this clone's π0.5 fixture with a
    test tokenizer and no download; the quick start's Python then runs on the result. Converted without
    `--tokenizer`, the folder has no processor: the summary says so, and loading one says how to add it."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    section = readme.split("## Quick start without a network", 1)[1].split("\n## ", 1)[0]
    (command,) = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    (code,) = re.findall(r"```python\n(.*?)```", readme.split("## Quick start\n", 1)[1], flags=re.S)[:1]
    program, *arguments = shlex.split(command)
    assert program == "pi0-torch" and arguments[-2:] == ["--tokenizer", "test"]
    (tmp_path / "tests").symlink_to(Path(__file__).parent)  # the clone's fixtures, where the command expects them
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(ENDPOINT_ENV, "http://127.0.0.1:9")  # nothing listens there: a download would fail
    assert cli_main(arguments) == 0
    assert "processor: written" in capsys.readouterr().out
    names: dict = {}
    exec(compile(code.replace("converted/pi05_droid", "converted/pi05_small"), "README.md", "exec"), names)
    assert tuple(names["chunk"].shape) == (1, 50, 32) and tuple(names["actions"].shape) == (1, 50, 8)

    bare = [*arguments[: arguments.index("--output-dir")], "--output-dir", "converted/bare"]
    assert cli_main(bare) == 0
    assert "processor: none: it needs --tokenizer" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError, match="converted without a processor: convert again with --tokenizer"):
        PI0Processor.from_pretrained("converted/bare")


def test_a_download_held_by_a_live_run_is_left_alone(bucket: FakeBucket, tmp_path: Path) -> None:
    """The resumable partial folder of a run that is still alive is neither used nor removed (a second download of
    the same checkpoint is refused); once that owner is gone, the next call takes it over. Cleaning up stale partial
    folders never removes a resumable one."""
    partial = _cached(tmp_path).with_name(".pi0_droid.partial-resumable")
    partial.mkdir(parents=True)
    parent = psutil.Process(os.getppid())  # alive for the whole test, and not this process
    owner = {"host": socket.gethostname(), "pid": parent.pid, "started": parent.create_time()}
    (partial / OWNER_FILE).write_text(json.dumps(owner))
    with pytest.raises(OutputPathError, match="being written by another run"):
        download_checkpoint(URL)
    assert bucket.media_requests(_largest(bucket)) == []
    (partial / OWNER_FILE).write_text(json.dumps({**owner, "started": 0.0}))  # that run is gone
    assert remove_stale_partials(partial.parent) == [] and partial.is_dir()
    assert download_checkpoint(URL) == _cached(tmp_path) and not partial.exists()
