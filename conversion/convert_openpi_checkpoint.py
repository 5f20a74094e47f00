"""Convert an openpi π0 / π0.5 checkpoint (orbax, JAX) into a pi0-torch folder; JAX is not needed.

Run from the repository root:

    python conversion/convert_openpi_checkpoint.py --checkpoint-dir ~/.cache/openpi/checkpoints/pi05_droid \\
        --output-dir checkpoints/pi05_droid [--dtype bfloat16] [--asset-id droid] [--tokenizer paligemma_tokenizer.model]

`--checkpoint-dir` is an openpi step folder (`<run>/<step>`, holding `params/` and `assets/`) or its `params`
folder. The output loads with `PI0ForActionGeneration.from_pretrained` (and, with `--tokenizer`,
`PI0Processor.from_pretrained`). Same as `pi0-torch convert --from openpi`; see `pi0_torch.conversion.convert`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when not pip-installed

from pi0_torch.conversion import convert as conversion  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint-dir", required=True, help="openpi <run>/<step> folder or its params folder")
    parser.add_argument("--output-dir", required=True, help="folder to create (absent or empty unless --overwrite)")
    parser.add_argument("--dtype", choices=list(conversion.DTYPES), default="float32", help="weight dtype of the output")
    parser.add_argument("--asset-id", help="which assets/<asset_id>/norm_stats.json to use (needed when there are several)")
    parser.add_argument("--tokenizer", help="PaliGemma SentencePiece model to save with the processor files")
    parser.add_argument("--max-shard-size", default="5GB", help="largest weight file before sharding (default: 5GB)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    forwarded = ["--from", "openpi", "--input", args.checkpoint_dir, "--output-dir", args.output_dir,
                 "--dtype", args.dtype, "--max-shard-size", args.max_shard_size]
    forwarded += ["--asset-id", args.asset_id] if args.asset_id else []
    forwarded += ["--tokenizer", args.tokenizer] if args.tokenizer else []
    forwarded += [flag for flag, on in (("--overwrite", args.overwrite), ("--no-progress", args.no_progress)) if on]
    convert = argparse.ArgumentParser(prog="pi0-torch convert")
    conversion.add_arguments(convert)
    return conversion.run(convert.parse_args(forwarded))


if __name__ == "__main__":
    sys.exit(main())
