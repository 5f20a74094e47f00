"""The `pi0-torch` console command: `pi0-torch {convert,consolidate,demo,demos,eval,serve,train,bench,export,quantize,doctor} ...`.

Each subcommand lives in its own module, which defines `add_arguments(parser)` and `run(args) -> int`; the module is
imported only when its subcommand runs, so `pi0-torch --help` stays fast (it imports neither torch nor transformers).
A subcommand whose pip extra is missing stops with one line naming it (`pi0_torch.utils.extras`), e.g.
`pi0-torch serve needs websockets: pip install 'pi0-torch[serve]'`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import traceback
from typing import Any

from pi0_torch.utils.extras import MissingExtraError, require_extra

# subcommand -> (module, one-line help, the extras it needs: checked before its module is imported)
COMMANDS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "demo": ("pi0_torch.demo", "Run the shipped demo policy in closed loop on held-out tabletop episodes: success rates and a video.", ("envs",)),
    "convert": ("pi0_torch.conversion.convert", "Convert openpi / LeRobot / transformers checkpoints to pi0-torch folders (and π0 to transformers).", ()),
    "train": ("pi0_torch.training.trainer", "Fine-tune π0 / π0.5 / π0-FAST on a LeRobot dataset with the Hugging Face Trainer (openpi's recipe).", ("train",)),
    "eval": ("pi0_torch.runtime.rollout", "Closed-loop rollouts of a policy (local or ws://) in gymnasium envs: success with 95% intervals.", ()),
    "consolidate": ("pi0_torch.training.fsdp", "Turn a sharded (`train --fsdp`) or LoRA (`train --lora`) checkpoint into a model folder (one process).", ("train",)),
    "serve": ("pi0_torch.runtime.serving", "Serve a policy over openpi's websocket protocol (openpi-client compatible).", ("serve",)),
    "bench": ("pi0_torch.benchmark", "Time generate_actions, a training step and loading; compare with transformers' PI0.", ()),
    "quantize": ("pi0_torch.conversion.quantize", "Quantize a model folder with torchao (int8, int4, fp8): a folder from_pretrained loads quantized.", ("quant",)),
    "export": ("pi0_torch.deploy.export", "Export a π0 / π0.5 model as one verified graph (ONNX or an AOTInductor package) that runs without the model classes.", ()),
    "doctor": ("pi0_torch.doctor", "Check every sampling path of this install on this machine against its reference: one table, pass or FAIL.", ()),
    "demos": ("pi0_torch.envs.demos", "Record scripted-expert demonstrations of a tabletop env as a LeRobot v3.0 dataset.", ("train", "envs")),
}


def bool_mask(text: str) -> list[bool]:
    """Argument type shared by subcommands: `"1,1,0"` -> `[True, True, False]` (e.g. `--delta-action-mask`)."""
    try:
        return [bool(int(v)) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated 0/1 values, got {text!r}") from None


def json_object(text: str) -> dict[str, Any]:
    """Argument type shared by subcommands: a JSON object (e.g. `--metadata`, `--config-overrides`)."""
    try:
        value = json.loads(text)
    except ValueError as error:  # JSONDecodeError, or an integer of more digits than Python converts
        raise argparse.ArgumentTypeError(f"not valid JSON: {str(error)[:200]}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got a JSON {type(value).__name__}")
    return value


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pi0-torch", description="π0 / π0.5 in PyTorch: everyday jobs.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text, extras) in COMMANDS.items():
        # argparse %-formats help strings (not descriptions): a literal % ("95% intervals") must be doubled there
        sub = subparsers.add_parser(name, help=help_text.replace("%", "%%"), description=help_text)
        sub.set_defaults(_module=module_name)
        if argv[:1] == [name]:  # only the chosen command's module is imported, once its extras are there
            missing = _missing_extra(extras, name)
            if missing is None:
                importlib.import_module(module_name).add_arguments(sub)
            else:  # --help still works, and says what to install
                sub.description = f"{help_text}\n\n{missing.message(f'pi0-torch {name}')}\n(its options are listed once it is installed)"
                sub.formatter_class = argparse.RawDescriptionHelpFormatter  # the install line stays one line
                sub.set_defaults(_missing=missing)
    return parser


def _missing_extra(extras: tuple[str, ...], command: str) -> MissingExtraError | None:
    """The first module of `extras` that is not installed (found without importing anything), or None."""
    for extra in extras:
        try:
            require_extra(extra, f"pi0-torch {command}")
        except MissingExtraError as error:
            return error
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        parser = build_parser(argv)
        args, unknown = parser.parse_known_args(argv)  # (--help exits here, a missing extra's included)
        missing = getattr(args, "_missing", None)
        if missing is not None:  # at once, before torch or any other heavy import
            raise missing
        if unknown:
            parser.parse_args(argv)  # argparse's own one-line error for the unknown options
        args._argv = list(argv[1:])  # (the command's options as given: `train --config` tells them from its defaults)
        return int(importlib.import_module(args._module).run(args) or 0)
    except MissingExtraError as error:  # the command's module, or what it runs, needs an extra that is not installed
        print(error.message(f"pi0-torch {argv[0]}"), file=sys.stderr)
        return 1
    except (ImportError, ValueError, AttributeError) as error:
        mismatch = numpy_mismatch(error)
        if mismatch is None:
            raise
        print(f"pi0-torch {argv[0]}: error: {mismatch}", file=sys.stderr)
        return 1


# What importing a compiled package built for another numpy major version raises (pandas, pyarrow, scipy, ...)
_NUMPY_ABI_MESSAGES = ("numpy.dtype size changed", "compiled using NumPy", "numpy.core.multiarray failed to import",
                       "_ARRAY_API not found", "numpy.core._multiarray_umath")


def numpy_mismatch(error: BaseException) -> str | None:
    """One line for an import that failed because the installed numpy is not the major version a compiled package
    was built for (None for any other error): most often a package pinned `numpy<2` into this environment
    (openpi-client 0.1.2 does), and pandas, pyarrow or scipy, built for numpy 2, no longer import."""
    text = str(error)
    if not any(message in text for message in _NUMPY_ABI_MESSAGES):
        return None
    import numpy

    compiled = ("pandas", "pyarrow", "scipy", "datasets", "sklearn", "matplotlib")
    module = getattr(error, "name", None) or next(
        (frame.f_globals.get("__name__", "") for frame, _ in traceback.walk_tb(error.__traceback__)
         if frame.f_globals.get("__name__", "").split(".")[0] in compiled), "")
    package = module.split(".")[0] or "a compiled package"
    return (f"{package} does not import with numpy {numpy.__version__} ({text.strip().splitlines()[0][:120]}): it was "
            "built for another numpy major version. A package pinned numpy here (openpi-client pins numpy<2): "
            "pip install --upgrade 'numpy>=2' here, and keep openpi-client in a virtualenv of its own "
            "(docs/serving.md)")


if __name__ == "__main__":
    sys.exit(main())
