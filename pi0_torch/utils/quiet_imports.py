"""Third-party imports that announce themselves, made quiet: `import pi0_torch` installs an import hook (no import of
its own, as `pi0_torch.models.auto_registration`'s) under which the named modules run with their announcing loggers
at ERROR, restored afterwards.

transformers imports torchao as soon as `PreTrainedModel` is imported, wherever torchao is installed (the `quant`
extra); torchao 0.17-0.18 then logs a warning for each CUDA extension it cannot load on a CPU machine and torch one
for each of its enums it registers: a dozen lines in a notebook cell that only loaded a model.
"""

from __future__ import annotations

import importlib.abc
import logging
import sys
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import Any

# package -> the loggers its modules' imports announce themselves on
QUIET_IMPORTS: dict[str, tuple[str, ...]] = {"torchao": ("torchao", "torch.utils._pytree")}


def install() -> None:
    """Quiet the imports of `QUIET_IMPORTS` that have not happened yet (once per process)."""
    if not any(isinstance(finder, _QuietImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, _QuietImport())


class _QuietImport(importlib.abc.MetaPathFinder):
    """Finds a module of `QUIET_IMPORTS` (or one of its submodules) with the other finders and runs it with its
    loggers at ERROR."""

    def find_spec(self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None) -> ModuleSpec | None:
        package = fullname.partition(".")[0]  # (its submodules too: they register more as they load)
        if package not in QUIET_IMPORTS or fullname in sys.modules:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        if spec.loader is not None and hasattr(spec.loader, "exec_module"):
            spec.loader = _QuietLoader(spec.loader, QUIET_IMPORTS[package])
        return spec


class _QuietLoader(importlib.abc.Loader):
    def __init__(self, loader: Any, loggers: tuple[str, ...]) -> None:
        self.loader, self.loggers = loader, loggers

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        loggers = [logging.getLogger(name) for name in self.loggers]
        levels = [logger.level for logger in loggers]
        for logger in loggers:
            logger.setLevel(logging.ERROR)
        try:
            self.loader.exec_module(module)
        finally:
            for logger, level in zip(loggers, levels):
                logger.setLevel(level)

    def __getattr__(self, name: str) -> Any:  # get_source, get_code, ... of the real loader
        return getattr(self.loader, name)
