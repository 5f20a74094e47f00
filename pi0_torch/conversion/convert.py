"""Convert openpi, LeRobot and transformers π0 / π0.5 checkpoints into pi0-torch folders (and π0 back to transformers).

`pi0-torch convert --from openpi|lerobot|transformers --input SRC --output-dir DST` writes a folder that
`PI0ForActionGeneration.from_pretrained(DST)` loads: `config.json`, safetensors weights (`model.safetensors`, or
`model-0000i-of-0000N.safetensors` shards plus `model.safetensors.index.json` above `--max-shard-size`, as
`save_pretrained` does), and the processor files: openpi's `norm_stats.json` (from `assets/<asset_id>/` of an openpi
checkpoint), plus `processor_config.json` and the tokenizer when `--tokenizer` is given, so that
`PI0Processor.from_pretrained(DST)` works too.

How it stays safe on a 12 GB checkpoint:
- streaming: the output layout (every tensor's name, shape and byte range in its shard) is planned from the config
  before any weight is read; each tensor is written into its place as soon as it is produced and then dropped. An
  openpi leaf is read one layer at a time (a leaf stored as one big chunk is decompressed once, as a stream, and
  spilled per layer to a scratch folder), so memory stays near the largest single tensor (π0's 2.1 GB float32 text
  embedding), not the model;
- validation first: every leaf must be used and every parameter filled, with the shapes the inferred config
  needs; leftovers are reported by name before anything is written;
- atomic output: everything goes into a hidden partial folder next to DST that is renamed into place at the end;
  any failure removes it, and a partial folder left by a killed run is removed by the next run
  (`pi0_torch.utils.files`). An existing non-empty DST is replaced only with `overwrite=True` and only when
  pi0-torch wrote all of it, and never when it is, contains or lies inside the input.

This module is the `pi0-torch convert` command over the conversions: `pi0_torch.conversion.convert_openpi` (openpi ->
pi0-torch), `pi0_torch.conversion.convert_hf` (LeRobot / transformers <-> pi0-torch), both writing through
`pi0_torch.conversion.output_folder` (the streaming writer, the processor files, the checks and the result).

```python
>>> import tempfile
>>> from pi0_torch import PI0ForActionGeneration
>>> from pi0_torch.conversion.convert import convert_openpi_checkpoint
>>> result = convert_openpi_checkpoint("tests/fixtures/openpi/pi0_small/ckpt/0", tempfile.mkdtemp() + "/pi0", progress=False)
>>> sorted(p.name for p in result.output_dir.iterdir())  # and the manifest of the files pi0-torch wrote
['.pi0-torch-manifest.json', 'config.json', 'model.safetensors', 'norm_stats.json']
>>> PI0ForActionGeneration.from_pretrained(result.output_dir).config.pi05
False

```
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

from safetensors import SafetensorError

from pi0_torch.cli import bool_mask
from pi0_torch.conversion.convert_hf import convert_hf_checkpoint, export_to_transformers
from pi0_torch.conversion.convert_openpi import convert_openpi_checkpoint
from pi0_torch.conversion.download import CACHE_ENV, PUBLISHED_CHECKPOINTS, checkpoint_url, fetch_openpi_checkpoint
from pi0_torch.conversion.orbax_reader import CheckpointError, first_line
from pi0_torch.conversion.output_folder import DTYPES, ConversionError
from pi0_torch.processing.robot_spaces import CONVERSIONS
from pi0_torch.utils.files import OutputPathError, check_output_dir

SOURCES = ("openpi", "lerobot", "transformers")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--from", dest="source", choices=[*SOURCES, "pi0-torch"],
                        help="input format (pi0-torch only with --to transformers; default with --checkpoint: openpi)")
    parser.add_argument("--to", dest="target", default="pi0-torch", choices=["pi0-torch", "transformers"],
                        help="output format (default: pi0-torch; transformers = PI0ForConditionalGeneration, π0 only)")
    parser.add_argument("--input", help="openpi <run>/<step> or <step>/params folder (or gs://... to download it), or a safetensors model folder")
    parser.add_argument("--checkpoint", choices=list(PUBLISHED_CHECKPOINTS), metavar="NAME",
                        help=f"download one of openpi's published checkpoints (with its asset id and processor settings) into "
                        f"${CACHE_ENV} (default ~/.cache/pi0_torch) and convert it: {', '.join(PUBLISHED_CHECKPOINTS)}")
    parser.add_argument("--output-dir", required=True, help="folder to create (must be absent or empty unless --overwrite)")
    parser.add_argument("--dtype", choices=list(DTYPES), default=None, help="weight dtype of the output (default: float32; export: as stored)")
    parser.add_argument("--asset-id", help="openpi: which assets/<asset_id>/norm_stats.json to use (needed when there are several)")
    parser.add_argument("--norm-stats", help="lerobot/transformers: an openpi norm_stats.json for the processor files (default for a LeRobot "
                        "folder: its policy_preprocessor_step_*_normalizer_processor.safetensors)")
    parser.add_argument("--tokenizer", help="PaliGemma SentencePiece model (e.g. paligemma_tokenizer.model) to save with the "
                        "processor, or test: a small tokenizer trained offline (trials and tests only, as train --tokenizer test)")
    parser.add_argument("--fast-tokenizer", help="openpi π0-FAST: the FAST action tokenizer folder (physical-intelligence/fast "
                        "layout), saved in the output's fast_tokenizer/")
    parser.add_argument("--action-horizon", type=int, help="actions per chunk (not stored in the weights; π0-FAST DROID / "
                        "LIBERO: 10; default: the FAST tokenizer's time_horizon, else the model's default)")
    parser.add_argument("--action-dim", type=int, help="π0-FAST: action dims a FAST chunk decodes to (DROID 8, LIBERO 7; "
                        "default: the FAST tokenizer's action_dim, else 32)")
    parser.add_argument("--max-token-len", type=int, help="prompt length in tokens (π0-FAST LIBERO: 180; default: the model's)")
    parser.add_argument("--delta-action-mask", type=bool_mask, metavar="1,1,...,0", help="processor: action dims the "
                        "checkpoint predicts relative to the state (openpi's DeltaActions; ALOHA: 1,1,1,1,1,1,0,1,1,1,1,1,1,0)")
    parser.add_argument("--value-conversion", choices=sorted(CONVERSIONS), help="processor: the robot's value "
                        "conversion the checkpoint was trained with (aloha: openpi's adapt_to_pi)")
    parser.add_argument("--max-shard-size", default="5GB", help="largest weight file before sharding (default: 5GB)")
    parser.add_argument("--quantize", metavar="SCHEME", help="write the converted model quantized (the quant extra: "
                        "torchao; int8, int8-dynamic, int4, fp8, fp8-weight; see pi0-torch quantize)")
    parser.add_argument("--quantize-device", default="cpu", help="with --quantize: where the model will run (cpu or cuda)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if not args.quantize:
        return _convert(args)
    from pi0_torch.conversion.quantize import QuantizationError, check_scheme, quantize_folder
    from pi0_torch.utils.extras import MissingExtraError, require_extra

    try:  # (before converting many GB: the scheme, the extra, the output folder)
        require_extra("quant", "pi0-torch convert --quantize", modules=("torchao",))
        check_scheme(args.quantize, args.quantize_device)
        if args.target == "transformers":
            raise QuantizationError("--quantize writes a pi0-torch folder, not --to transformers")
        output = Path(args.output_dir).expanduser()
        check_output_dir(output, args.overwrite)
    except MissingExtraError as error:
        print(f"error: {error.message('pi0-torch convert --quantize')}", file=sys.stderr)
        return 1
    except (QuantizationError, OutputPathError) as error:
        print(f"error: {first_line(error)}", file=sys.stderr)
        return 1
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{output.name}.float-", dir=output.parent) as scratch:
        converted = argparse.Namespace(**{**vars(args), "output_dir": str(Path(scratch) / "model"), "overwrite": False})
        if (code := _convert(converted)) != 0:
            return code
        try:
            folder = quantize_folder(converted.output_dir, output, args.quantize, args.quantize_device,
                                     overwrite=args.overwrite)
        except (ValueError, OSError) as error:
            print(f"error: --quantize {args.quantize}: {first_line(error)}", file=sys.stderr)
            return 1
    print(f"quantized ({args.quantize}, for {args.quantize_device}) into {folder}")
    return 0


def _convert(args: argparse.Namespace) -> int:
    try:
        if args.target == "transformers":
            if args.source != "pi0-torch":
                raise ConversionError("--to transformers exports a pi0-torch folder: convert first, then use --from pi0-torch")
            written = export_to_transformers(args.input, args.output_dir, dtype=args.dtype, overwrite=args.overwrite,
                                             progress=not args.no_progress)
            print(f"wrote {written}")
            return 0
        options = {"delta_action_mask": args.delta_action_mask, "value_conversion": args.value_conversion}
        overrides: dict[str, Any] = {}
        if args.checkpoint or (args.input or "").startswith("gs://"):
            if args.checkpoint and args.input or (args.source or "openpi") != "openpi":
                raise ConversionError("--checkpoint NAME and gs:// inputs are openpi checkpoints: give one of them, with --from openpi or no --from")
            check_output_dir(Path(args.output_dir).expanduser(), args.overwrite)  # before a download of many GB
            fetched = fetch_openpi_checkpoint(args.input or checkpoint_url(args.checkpoint), asset_id=args.asset_id,
                                              tokenizer=args.tokenizer, fast_tokenizer=args.fast_tokenizer,
                                              progress=not args.no_progress)
            args.source, args.input, args.asset_id, args.tokenizer = "openpi", fetched.folder, fetched.asset_id, fetched.tokenizer
            args.fast_tokenizer = fetched.fast_tokenizer
            options = {**fetched.processor_options, **{k: v for k, v in options.items() if v is not None}}
            overrides = fetched.config_overrides
        if args.source is None or args.input is None:
            raise ConversionError("give --from and --input (or --checkpoint NAME for openpi's published checkpoints)")
        common = dict(dtype=args.dtype or "float32", tokenizer=args.tokenizer, overwrite=args.overwrite,
                      max_shard_bytes=args.max_shard_size, progress=not args.no_progress,
                      processor_options={k: v for k, v in options.items() if v is not None})
        overrides.update({name: getattr(args, name) for name in ("action_horizon", "action_dim", "max_token_len")
                          if getattr(args, name) is not None})  # the flags win over a published checkpoint's settings
        if args.source == "openpi":
            if args.norm_stats:
                raise ConversionError("--norm-stats is for lerobot/transformers inputs; openpi's come from assets/ (--asset-id)")
            result = convert_openpi_checkpoint(args.input, args.output_dir, asset_id=args.asset_id, fast_tokenizer=args.fast_tokenizer,
                                               **common, **overrides)
        elif args.source in ("lerobot", "transformers"):
            if args.asset_id:
                raise ConversionError("--asset-id selects openpi assets; for lerobot/transformers use --norm-stats")
            if args.fast_tokenizer:
                raise ConversionError("--fast-tokenizer is for openpi π0-FAST checkpoints")
            result = convert_hf_checkpoint(args.input, args.output_dir, norm_stats=args.norm_stats, **common, **overrides)
        else:
            raise ConversionError("--from pi0-torch needs --to transformers")
    except (CheckpointError, OutputPathError, OSError) as error:
        print(f"error: {first_line(error)}", file=sys.stderr)
        return 1
    except SafetensorError as error:  # a truncated or foreign weights file in a pi0-torch / transformers input
        print(f"error: {args.input}: the weights are not a readable safetensors file ({first_line(error)}); the folder is "
              "damaged (convert or copy it again)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("error: interrupted; nothing was written", file=sys.stderr)
        return 130
    print(result.summary())
    return 0
