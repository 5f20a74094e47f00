"""`AutoConfig` and `AutoModel` know pi0-torch's models once `pi0_torch` is imported, while `import pi0_torch`
itself imports neither torch nor transformers.

    import pi0_torch
    from transformers import AutoModel
    model = AutoModel.from_pretrained("converted/pi05_droid")   # a PI0ForActionGeneration

Two moments make that work without importing transformers early:

- transformers looks the config class up by `config.json`'s `model_type` in `AutoConfig`'s registry before any
  pi0-torch code runs, so the configs are registered as soon as that registry's module
  (`transformers.models.auto.configuration_auto`) exists: at once when it is already imported, otherwise right after
  transformers imports it ([`install`], called by `import pi0_torch`).
- The model classes (and `AutoProcessor`'s [`PI0Processor`]) are registered when a pi0-torch config is created
  ([`register_models`], called by the configs' `__init__`): `AutoModel.from_pretrained`, `AutoModel.from_config` and
  `AutoProcessor.from_pretrained` all hold a config before they look a class up. Registering them together with the configs could import transformers' modeling code while transformers
  is still importing it (its `modeling_utils` imports the config registry).
"""

from __future__ import annotations

import importlib.abc
import sys
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import Any

CONFIG_REGISTRY_MODULE = "transformers.models.auto.configuration_auto"

_models_registered = False


def install() -> None:
    """Register the configs now if transformers' config registry is imported, else right after it is."""
    if CONFIG_REGISTRY_MODULE in sys.modules:
        register_configs()
    elif not any(isinstance(finder, _AfterRegistryImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, _AfterRegistryImport())


def register_configs() -> None:
    """`AutoConfig` maps the model types `pi0_torch` and `pi0_fast_torch` to [`PI0Config`] and [`PI0FastConfig`]."""
    from transformers import AutoConfig

    from pi0_torch.models.configuration_pi0 import PI0Config
    from pi0_torch.models.configuration_pi0_fast import PI0FastConfig

    for config_class in (PI0Config, PI0FastConfig):
        AutoConfig.register(config_class.model_type, config_class, exist_ok=True)


def register_models() -> None:
    """`AutoModel` maps [`PI0Config`] to [`PI0ForActionGeneration`] and [`PI0FastConfig`] to
    [`PI0FastForActionGeneration`], and `AutoProcessor` [`PI0Config`] to [`PI0Processor`] (once per process; the
    processor module itself imports no transformers: it runs in a torch-free deploy install)."""
    global _models_registered
    if _models_registered:
        return
    _models_registered = True  # first: importing the model modules must not come back here
    try:
        from transformers import AutoModel, AutoProcessor

        from pi0_torch.models.configuration_pi0 import PI0Config
        from pi0_torch.models.configuration_pi0_fast import PI0FastConfig
        from pi0_torch.models.modeling_pi0 import PI0ForActionGeneration
        from pi0_torch.models.modeling_pi0_fast import PI0FastForActionGeneration
        from pi0_torch.processing.processing_pi0 import PI0Processor

        AutoModel.register(PI0Config, PI0ForActionGeneration, exist_ok=True)
        AutoModel.register(PI0FastConfig, PI0FastForActionGeneration, exist_ok=True)
        AutoProcessor.register(PI0Config, PI0Processor, exist_ok=True)
    except BaseException:
        _models_registered = False
        raise


class _AfterRegistryImport(importlib.abc.MetaPathFinder):
    """Finds transformers' config registry module with the other finders and has [`register_configs`] run right
    after the module has; then leaves `sys.meta_path`. Every other import passes by untouched."""

    def find_spec(self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None) -> ModuleSpec | None:
        if fullname != CONFIG_REGISTRY_MODULE:
            return None
        sys.meta_path.remove(self)
        for finder in sys.meta_path:
            spec = finder.find_spec(fullname, path, target) if hasattr(finder, "find_spec") else None
            if spec is not None:
                break
        else:
            return None
        if spec.loader is not None and hasattr(spec.loader, "exec_module"):
            spec.loader = _RegisterConfigsAfter(spec.loader)
        return spec


class _RegisterConfigsAfter(importlib.abc.Loader):
    """A module loader that runs [`register_configs`] once the module it loads has run."""

    def __init__(self, loader: Any) -> None:
        self.loader = loader

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self.loader.exec_module(module)
        register_configs()

    def __getattr__(self, name: str) -> Any:  # get_source, get_code, ... (tracebacks, inspect) of the real loader
        return getattr(self.loader, name)
