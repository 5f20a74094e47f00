"""Packages whose public names are imported on first use (PEP 562), so that importing a package, `pi0_torch` or
the `pi0-torch` command, does not import torch and transformers until something needs them.

```python
>>> import sys
>>> __getattr__, __dir__ = lazy_exports("pi0_torch.utils", {"OutputPathError": "pi0_torch.utils.files"})
>>> __getattr__("OutputPathError").__name__
'OutputPathError'
>>> __getattr__("nothing")
Traceback (most recent call last):
    ...
AttributeError: module 'pi0_torch.utils' has no attribute 'nothing'

```
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level `__getattr__` and `__dir__` of `package`: `exports` maps each public name to the module that
    defines it, imported when the name is first looked up (then kept on the package)."""

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(exports[name]), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__
