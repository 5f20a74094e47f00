"""Download openpi's published checkpoints and PaliGemma's tokenizer from their public Google Cloud Storage buckets
(and, for π0-FAST, the FAST tokenizer `physical-intelligence/fast` from the Hugging Face hub).

openpi publishes its checkpoints at `gs://openpi-assets/checkpoints/<name>/` (orbax `params/` plus the norm stats
under `assets/<asset_id>/`) and the PaliGemma tokenizer at `gs://big_vision/paligemma_tokenizer.model`. Both buckets
are readable anonymously over HTTPS, so no Google Cloud tools or credentials are needed:

- the JSON listing API (`GET {endpoint}/storage/v1/b/<bucket>/o?prefix=<prefix>/`, paged with `nextPageToken`) gives
  every object's name, size and base64 MD5;
- each object is fetched from `{endpoint}/<bucket>/<object>`; a cut connection is resumed with an HTTP `Range`
  request (a few times within one call, and by the next call after that).

Downloads go into a cache folder, `$PI0_TORCH_CACHE` or `~/.cache/pi0_torch/`, laid out as `<bucket>/<object>`
(e.g. `~/.cache/pi0_torch/openpi-assets/checkpoints/pi05_droid/params/...`). Nothing half-written is ever taken for
a download:
- a file is written as `<file>.part`, verified against the listing's size and MD5, and only then renamed to its
  name (a mismatch deletes it and fails);
- a checkpoint is assembled in a hidden partial folder beside its cache place (`pi0_torch.utils.files`
  `resumable_output_dir`), which is kept when the download fails so that the next call continues it, and is renamed
  into place once every file is verified; a finished checkpoint is used from the cache without any network access.

The endpoint can be redirected with `$PI0_TORCH_GCS_ENDPOINT` (the tests serve a fixture checkpoint from 127.0.0.1).
`PUBLISHED_CHECKPOINTS` records, for openpi's published checkpoints, the settings openpi's training config gives them
that the weights do not store (asset id of the norm stats, action horizon, for π0-FAST the action dims and prompt
length, processor options).

Offline, or behind a firewall: copy a checkpoint folder (`<step>/` with `params/` and `assets/`) and the tokenizer
by other means, and convert with `pi0-torch convert --from openpi --input DIR --tokenizer FILE` (docs/conversion.md).

```python
>>> parse_gcs_url("gs://openpi-assets/checkpoints/pi05_droid/")
('openpi-assets', 'checkpoints/pi05_droid')
>>> PUBLISHED_CHECKPOINTS["pi05_droid"].asset_id, PUBLISHED_CHECKPOINTS["pi05_droid"].action_horizon
('droid', 15)

```
"""

from __future__ import annotations

import base64
import hashlib
import http.client
import json
import logging
import os
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pi0_torch.utils.progress import tqdm

from pi0_torch.conversion.orbax_reader import CheckpointError
from pi0_torch.utils.files import resumable_output_dir
from pi0_torch.utils.validation import first_line

logger = logging.getLogger(__name__)

ENDPOINT_ENV = "PI0_TORCH_GCS_ENDPOINT"
DEFAULT_ENDPOINT = "https://storage.googleapis.com"
CACHE_ENV = "PI0_TORCH_CACHE"
DEFAULT_CACHE = "~/.cache/pi0_torch"
CHECKPOINTS_URL = "gs://openpi-assets/checkpoints"
TOKENIZER_URL = "gs://big_vision/paligemma_tokenizer.model"
FAST_TOKENIZER_REPO = "physical-intelligence/fast"  # on the Hugging Face hub: openpi's FASTTokenizer default
FAST_TOKENIZER_FILES = ["processor_config.json", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json"]
MANIFEST_FILE = ".pi0-torch-download.json"  # the verified listing, written into a finished checkpoint folder
PART_SUFFIX = ".part"
RETRIES = 3  # resumed requests after a cut connection, within one call
_BLOCK = 1 << 20
_TIMEOUT_S = 60


class DownloadError(CheckpointError):
    """A download that failed (network, missing object, checksum mismatch). The message is one line."""


# ---------------------------------------------------------------------------------------------------------------------
# openpi's published checkpoints
# ---------------------------------------------------------------------------------------------------------------------

_ALOHA_DELTAS = (True,) * 6 + (False,) + (True,) * 6 + (False,)  # openpi's make_bool_mask(6, -1, 6, -1)


@dataclass(frozen=True)
class PublishedCheckpoint:
    """What openpi's training config of a published checkpoint sets that its weights do not store."""

    asset_id: str | None = None  # assets/<asset_id>/norm_stats.json; None: the checkpoint's only one (or --asset-id)
    action_horizon: int | None = None  # None: the model's default (π0: 50; π0-FAST: 32)
    action_dim: int | None = None  # π0-FAST: the dims a FAST chunk decodes to (None: 32)
    max_token_len: int | None = None  # None: the model's default
    fast: bool = False  # π0-FAST: converted with the FAST tokenizer physical-intelligence/fast
    delta_action_mask: tuple[bool, ...] | None = None
    value_conversion: str | None = None
    state_in_prompt: bool | None = None  # π0.5: openpi's discrete_state_input (None: the processor's default, True)
    default_prompt: str | None = None  # openpi's InjectDefaultPrompt (for clients that send no prompt)

    def processor_options(self) -> dict[str, Any]:
        options = {"delta_action_mask": list(self.delta_action_mask) if self.delta_action_mask else None,
                   "value_conversion": self.value_conversion, "state_in_prompt": self.state_in_prompt,
                   "default_prompt": self.default_prompt}
        return {key: value for key, value in options.items() if value is not None}

    def config_overrides(self) -> dict[str, Any]:
        """The model settings the weights do not store (`convert_openpi_checkpoint`'s keyword arguments)."""
        settings = {"action_horizon": self.action_horizon, "action_dim": self.action_dim, "max_token_len": self.max_token_len}
        return {key: value for key, value in settings.items() if value is not None}


_LIBERO_DELTAS = (True,) * 6 + (False,)  # openpi's LIBERO configs: the 6 joint actions relative to the state
# From openpi's README checkpoint list and src/openpi/training/config.py (the config of the same name).
PUBLISHED_CHECKPOINTS: dict[str, PublishedCheckpoint] = {
    "pi0_base": PublishedCheckpoint(),
    "pi05_base": PublishedCheckpoint(),
    "pi0_fast_base": PublishedCheckpoint(fast=True),
    "pi0_droid": PublishedCheckpoint(asset_id="droid", action_horizon=10),
    "pi05_droid": PublishedCheckpoint(asset_id="droid", action_horizon=15),
    "pi0_fast_droid": PublishedCheckpoint(asset_id="droid", action_horizon=10, action_dim=8, fast=True),
    "pi0_libero": PublishedCheckpoint(asset_id="physical-intelligence/libero", delta_action_mask=_LIBERO_DELTAS),
    # openpi's pi05_libero: Pi0Config(pi05=True, action_horizon=10, discrete_state_input=False), absolute actions
    "pi05_libero": PublishedCheckpoint(asset_id="physical-intelligence/libero", action_horizon=10, state_in_prompt=False),
    "pi0_fast_libero": PublishedCheckpoint(asset_id="physical-intelligence/libero", action_horizon=10, action_dim=7,
                                           max_token_len=180, delta_action_mask=_LIBERO_DELTAS, fast=True),
    # openpi's pi0_aloha_sim: its aloha_sim client sends no prompt; the config's default_prompt is "Transfer cube"
    "pi0_aloha_sim": PublishedCheckpoint(value_conversion="aloha", default_prompt="Transfer cube"),
    "pi0_aloha_towel": PublishedCheckpoint(asset_id="trossen", delta_action_mask=_ALOHA_DELTAS, value_conversion="aloha"),
    "pi0_aloha_tupperware": PublishedCheckpoint(asset_id="trossen", delta_action_mask=_ALOHA_DELTAS, value_conversion="aloha"),
    "pi0_aloha_pen_uncap": PublishedCheckpoint(asset_id="trossen", delta_action_mask=_ALOHA_DELTAS, value_conversion="aloha"),
}


def published_checkpoint(url: str) -> PublishedCheckpoint | None:
    """The published settings of `gs://openpi-assets/checkpoints/<name>`; None for any other location."""
    bucket, prefix = parse_gcs_url(url)
    parent, _, name = prefix.rpartition("/")
    if f"gs://{bucket}/{parent}" != CHECKPOINTS_URL:
        return None
    return PUBLISHED_CHECKPOINTS.get(name)


def checkpoint_url(name: str) -> str:
    """`gs://openpi-assets/checkpoints/<name>` for a published name; `ValueError` listing the names otherwise."""
    if name not in PUBLISHED_CHECKPOINTS:
        raise ValueError(f"--checkpoint {name!r} is not one of openpi's published checkpoints: {', '.join(PUBLISHED_CHECKPOINTS)}")
    return f"{CHECKPOINTS_URL}/{name}"


# ---------------------------------------------------------------------------------------------------------------------
# bucket access
# ---------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RemoteObject:
    name: str  # object name in its bucket
    size: int  # bytes
    md5: str | None  # hex; None for composite objects, which the bucket lists without one (then only the size is checked)


def parse_gcs_url(url: str) -> tuple[str, str]:
    """`gs://bucket/some/prefix/` -> `("bucket", "some/prefix")`."""
    parsed = urllib.parse.urlparse(url)
    if parsed.scheme != "gs" or not parsed.netloc:
        raise ValueError(f"expected a gs://<bucket>/<path> URL, got {url!r}")
    return parsed.netloc, parsed.path.strip("/")


def cache_dir() -> Path:
    """The download cache: `$PI0_TORCH_CACHE`, or `~/.cache/pi0_torch`."""
    return Path(os.environ.get(CACHE_ENV) or DEFAULT_CACHE).expanduser().absolute()


def _endpoint(endpoint: str | None) -> str:
    return (endpoint or os.environ.get(ENDPOINT_ENV) or DEFAULT_ENDPOINT).rstrip("/")


def _open(url: str, headers: dict[str, str] | None = None) -> http.client.HTTPResponse:
    request = urllib.request.Request(url, headers={"User-Agent": "pi0-torch", **(headers or {})})
    try:
        return urllib.request.urlopen(request, timeout=_TIMEOUT_S)
    except urllib.error.HTTPError as error:
        raise DownloadError(f"{url}: HTTP {error.code} {error.reason}") from None
    except (urllib.error.URLError, OSError) as error:
        reason = getattr(error, "reason", error)
        raise DownloadError(f"cannot reach {url}: {reason} (no network? set {ENDPOINT_ENV} for a mirror, or convert a "
                            "copy made elsewhere: pi0-torch convert --from openpi --input DIR --tokenizer FILE)") from None


def list_objects(bucket: str, prefix: str, endpoint: str | None = None) -> list[RemoteObject]:
    """Every object under `prefix` (folder placeholders skipped), from the bucket's JSON listing API."""
    objects: list[RemoteObject] = []
    page_token = None
    while True:
        query = {"prefix": prefix, "fields": "items(name,size,md5Hash),nextPageToken"}
        if page_token:
            query["pageToken"] = page_token
        url = f"{_endpoint(endpoint)}/storage/v1/b/{urllib.parse.quote(bucket, safe='')}/o?{urllib.parse.urlencode(query)}"
        with _open(url) as response:
            try:
                page = json.loads(response.read())
            except ValueError:
                raise DownloadError(f"{url}: the listing is not JSON") from None
        for item in page.get("items", []):
            if item["name"].endswith("/"):
                continue
            md5 = base64.b64decode(item["md5Hash"]).hex() if item.get("md5Hash") else None
            objects.append(RemoteObject(item["name"], int(item["size"]), md5))
        page_token = page.get("nextPageToken")
        if not page_token:
            return objects


def download_object(
    bucket: str, item: RemoteObject, target: Path, endpoint: str | None = None, on_bytes: Callable[[int], None] = lambda n: None
) -> None:
    """Fetch one object into `target` through `target.part` (continuing a `.part` left by an earlier call), verify
    its size and MD5, then rename it into place. A mismatch deletes the `.part` file and raises `DownloadError`."""
    part = target.with_name(target.name + PART_SUFFIX)
    part.parent.mkdir(parents=True, exist_ok=True)
    url = f"{_endpoint(endpoint)}/{urllib.parse.quote(bucket, safe='')}/{urllib.parse.quote(item.name)}"
    digest = hashlib.md5()
    done = 0
    if part.exists() and part.stat().st_size <= item.size:
        with part.open("rb") as handle:  # re-hash what an earlier call wrote
            for block in iter(lambda: handle.read(_BLOCK), b""):
                digest.update(block)
                done += len(block)
        on_bytes(done)
    else:
        part.unlink(missing_ok=True)
    for attempt in range(RETRIES + 1):
        if done >= item.size:
            break
        if attempt:
            logger.info("%s: connection lost after %d of %d bytes; resuming", item.name, done, item.size)
            time.sleep(0.2 * attempt)
        try:
            with _open(url, {"Range": f"bytes={done}-"} if done else None) as response:
                if done and response.status != 206:  # the server ignored the range: start over
                    on_bytes(-done)
                    digest, done = hashlib.md5(), 0
                with part.open("ab" if done else "wb") as handle:
                    for block in iter(lambda: response.read(_BLOCK), b""):
                        handle.write(block)
                        digest.update(block)
                        done += len(block)
                        on_bytes(len(block))
        except (http.client.HTTPException, ConnectionError, TimeoutError):
            pass  # a cut connection: the next attempt continues from what was written
    if done != item.size:
        if done > item.size:
            part.unlink()
        raise DownloadError(
            f"{url}: got {done} of {item.size} bytes after {RETRIES + 1} attempts; run the same command again to resume"
        )
    if item.md5 is None:
        logger.warning("%s has no MD5 in the bucket's listing: only its size was checked", item.name)
    elif digest.hexdigest() != item.md5:
        part.unlink()
        raise DownloadError(f"{url}: MD5 {digest.hexdigest()} does not match the bucket's {item.md5}; the download was deleted")
    part.replace(target)




# ---------------------------------------------------------------------------------------------------------------------
# checkpoints and files in the cache
# ---------------------------------------------------------------------------------------------------------------------


def _progress(total: int, description: str, enabled: bool) -> tqdm:
    return tqdm(total=total, desc=description, unit="B", unit_scale=True, unit_divisor=1024, disable=not enabled, file=sys.stderr)


def _check_asset_id(url: str, objects: list[RemoteObject], prefix: str, asset_id: str | None) -> None:
    """Fail before downloading when the norm stats the conversion will ask for are not in the checkpoint."""
    marker, suffix = f"{prefix}/assets/", "/norm_stats.json"
    choices = sorted(o.name[len(marker) : -len(suffix)] for o in objects if o.name.startswith(marker) and o.name.endswith(suffix))
    if asset_id is not None and asset_id not in choices:
        raise DownloadError(f"{url} has no norm stats for asset id {asset_id!r}; choices: {', '.join(choices) or 'none'}")
    if asset_id is None and len(choices) > 1:
        raise DownloadError(f"{url} has norm stats for several asset ids; pick one with --asset-id: {', '.join(choices)}")


def download_checkpoint(url: str, *, asset_id: str | None = None, endpoint: str | None = None, progress: bool = False) -> Path:
    """The local copy of the checkpoint folder at `url` (`gs://bucket/prefix`), downloaded into the cache unless it
    is there already. `asset_id` is checked against the listing before anything is downloaded. Raises
    `DownloadError`; what was verified so far stays in the cache's partial folder for the next call."""
    bucket, prefix = parse_gcs_url(url)
    final = cache_dir() / bucket / prefix
    if final.is_dir():  # published only once every file was verified
        return final
    objects = list_objects(bucket, prefix + "/", endpoint)
    if not objects:
        raise DownloadError(f"{url}: no such checkpoint (the bucket lists nothing under it)")
    _check_asset_id(url, objects, prefix, asset_id)
    total = sum(o.size for o in objects)
    logger.info("downloading %s (%d files, %.2f GB) into %s", url, len(objects), total / 1e9, final)
    with resumable_output_dir(final) as folder, _progress(total, f"downloading {prefix.rpartition('/')[2]}", progress) as bar:
        for item in objects:
            target = folder / item.name[len(prefix) + 1 :]
            if target.is_file() and target.stat().st_size == item.size:  # renamed into place only after its check
                bar.update(item.size)
                continue
            download_object(bucket, item, target, endpoint, bar.update)
        manifest = [{"name": o.name, "size": o.size, "md5": o.md5} for o in objects]
        (folder / MANIFEST_FILE).write_text(json.dumps({"url": url, "objects": manifest}, indent=1))
    return final


def download_file(url: str, *, endpoint: str | None = None, progress: bool = False) -> Path:
    """The local copy of the single object at `url`, downloaded into the cache unless it is there already."""
    bucket, name = parse_gcs_url(url)
    target = cache_dir() / bucket / name
    if target.is_file():  # renamed into place only after its check
        return target
    found = [o for o in list_objects(bucket, name, endpoint) if o.name == name]
    if not found:
        raise DownloadError(f"{url}: no such file in the bucket")
    with _progress(found[0].size, f"downloading {target.name}", progress) as bar:
        download_object(bucket, found[0], target, endpoint, bar.update)
    return target


def download_fast_tokenizer() -> Path:
    """The FAST tokenizer folder `physical-intelligence/fast` from the Hugging Face hub (its settings and BPE only,
    never its code), in the hub's cache. Raises `DownloadError` saying how to give a copy instead."""
    from huggingface_hub import snapshot_download

    try:
        return Path(snapshot_download(FAST_TOKENIZER_REPO, allow_patterns=FAST_TOKENIZER_FILES))
    except Exception as error:  # offline, unreachable, rate-limited: whatever the hub client raises
        raise DownloadError(f"cannot download the FAST tokenizer {FAST_TOKENIZER_REPO} from the Hugging Face hub: "
                            f"{first_line(error) or type(error).__name__}; give a copy of it with --fast-tokenizer DIR") from None


@dataclass(frozen=True)
class FetchedCheckpoint:
    """A downloaded openpi checkpoint with what its conversion needs."""

    folder: Path  # the step folder: params/ and assets/
    tokenizer: Path
    asset_id: str | None
    processor_options: dict[str, Any]
    config_overrides: dict[str, Any]
    fast_tokenizer: Path | None = None  # π0-FAST: the FAST tokenizer folder


def fetch_openpi_checkpoint(
    url: str, *, asset_id: str | None = None, tokenizer: str | os.PathLike[str] | None = None,
    fast_tokenizer: str | os.PathLike[str] | None = None, endpoint: str | None = None, progress: bool = False,
) -> FetchedCheckpoint:
    """Download an openpi checkpoint and PaliGemma's tokenizer (unless `tokenizer` is given) into the cache, with
    the settings openpi gives a published checkpoint (`asset_id` overrides its asset id); for a published π0-FAST
    checkpoint also the FAST tokenizer (unless `fast_tokenizer` is given), before the checkpoint."""
    published = published_checkpoint(url) or PublishedCheckpoint()
    asset_id = asset_id or published.asset_id
    if fast_tokenizer is not None:
        fast_tokenizer = Path(fast_tokenizer)
    elif published.fast:
        fast_tokenizer = download_fast_tokenizer()  # small, and it fails fast when the hub is out of reach
    folder = download_checkpoint(url, asset_id=asset_id, endpoint=endpoint, progress=progress)
    local_tokenizer = Path(tokenizer) if tokenizer is not None else download_file(TOKENIZER_URL, endpoint=endpoint, progress=progress)
    return FetchedCheckpoint(folder, local_tokenizer, asset_id, published.processor_options(), published.config_overrides(),
                             fast_tokenizer)
