"""Imports every module of the installed pi0_torch, as a user's code might, and reports what each needs.

    python check_modules.py [--extras serve,envs]   # the extras that are installed

Run from outside the clone by .ci/install-check. A module imports, or stops with pi0-torch's one-line
MissingExtraError naming a missing extra; anything else (a ModuleNotFoundError above all: an import that
pyproject.toml does not declare) fails the check. A module that needs an extra which is installed must import.
Prints one line per module needing an extra, and exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import traceback


def _where(error: Exception) -> str:
    """`ModuleNotFoundError: No module named 'scipy' (at pi0_torch/processing/fast_tokenizer.py:44)`."""
    frame = traceback.extract_tb(error.__traceback__)[-1]
    location = frame.filename.split("site-packages/")[-1]
    return f"{type(error).__name__}: {error} (at {location}:{frame.lineno})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--extras", default="", help="comma list of the extras that are installed")
    installed = {extra for extra in parser.parse_args().extras.split(",") if extra}

    import pi0_torch
    from pi0_torch.utils.extras import MissingExtraError

    if "torch" in sys.modules:
        print("FAIL: import pi0_torch imported torch (the package imports lazily)")
        return 1
    failures = 0
    names = sorted(info.name for info in pkgutil.walk_packages(pi0_torch.__path__, "pi0_torch."))
    for name in [n for n in names if not n.endswith(".__main__")]:  # __main__ runs a command
        try:
            importlib.import_module(name)
        except MissingExtraError as error:
            if error.extra in installed:
                print(f"FAIL: {name}: {error} although [{error.extra}] is installed")
                failures += 1
            else:
                print(f"{name}: {error}")
        except Exception as error:
            print(f"FAIL: {name} does not import: {_where(error)}")
            failures += 1
    for public in pi0_torch.__all__:  # every public name resolves with the core alone
        try:
            getattr(pi0_torch, public)
        except Exception as error:
            print(f"FAIL: pi0_torch.{public}: {_where(error)}")
            failures += 1
    print(f"{len(names)} modules, {len(pi0_torch.__all__)} public names: {failures} failure(s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
