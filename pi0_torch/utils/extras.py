"""Optional features and the pip extras that bring them: a feature used without its extra fails in one line.

`pip install pi0-torch` is the core: loading, converting, running and benchmarking models. The rest comes as extras
(`pyproject.toml` declares the same lists):

| extra | for | brings |
|---|---|---|
| `serve` | `pi0-torch serve`, `eval --policy ws://...` | websockets, msgpack |
| `envs` | the tabletop envs, `pi0-torch eval` / `demo` (and their videos) | gymnasium, av |
| `train` | `pi0-torch train`, LeRobot datasets (`demos` writes them) | datasets, pyarrow, pandas, av, accelerate, matplotlib |
| `kernels` | the fused Triton kernels of sampling on CUDA (torch's CUDA wheels already bring triton) | triton |
| `deploy` | running an exported ONNX policy (`pi0_torch.deploy.ExportedPolicy`; needs no torch) | onnxruntime |
| `export` | `pi0-torch export --format onnx` (and checking the result) | onnx, onnxscript, onnxruntime |
| `quant` | quantized models (`pi0-torch quantize`, `from_pretrained(..., quantization_config=...)`) | torchao |
| `metaworld` | `pi0-torch eval --env metaworld/...` (and `demos`): Meta-World's tasks and scripted experts | envs, metaworld (MuJoCo) |
| `aloha` | `pi0-torch eval --env aloha/...`: ALOHA sim (transfer cube, insertion) as openpi evaluates it | envs, gym-aloha (MuJoCo) |
| `libero` | `pi0-torch eval --env libero/...`: the LIBERO suites as openpi evaluates them | envs, hf-libero (robosuite) |
| `all` | serving, the tabletop envs and training | `serve`, `envs` and `train` (not `kernels` or the benchmarks) |

A module of an optional feature calls [`require_extra`] before it imports what the extra brings, so that a missing
package is named with the command that installs it, not as a `ModuleNotFoundError` from deep inside:

```python
>>> require_extra("serve", "pi0-torch serve", modules=("websockets", "no_such_module"))
Traceback (most recent call last):
    ...
pi0_torch.utils.extras.MissingExtraError: pi0-torch serve needs no_such_module: pip install 'pi0-torch[serve]'

```
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence

# extra -> the modules it brings that pi0-torch imports (the pip distribution names are in pyproject.toml)
EXTRAS: dict[str, tuple[str, ...]] = {
    "serve": ("websockets", "msgpack"),
    "envs": ("gymnasium", "av"),
    "train": ("datasets", "pyarrow", "pandas", "av", "accelerate", "matplotlib"),
    "kernels": ("triton",),
    "deploy": ("onnxruntime",),
    "export": ("onnx", "onnxscript", "onnxruntime"),
    "quant": ("torchao",),
    "metaworld": ("metaworld", "mujoco"),  # (each benchmark's extra also brings envs)
    "aloha": ("gym_aloha", "dm_control", "mujoco"),
    "libero": ("libero", "mujoco", "yaml"),
}
DISTRIBUTIONS = {"libero": "hf-libero", "yaml": "pyyaml"}  # module -> pip distribution, where they differ


class MissingExtraError(ImportError):
    """A feature was used without its extra: `str(error)` is the one line to show (`feature needs module: pip ...`)."""

    def __init__(self, feature: str, module: str, extra: str) -> None:
        self.feature, self.module, self.extra = feature, module, extra
        super().__init__(self.message(feature), name=module)

    def message(self, feature: str) -> str:
        """The one line, naming `feature` (the CLI names its command here)."""
        return f"{feature} needs {self.module}: pip install 'pi0-torch[{self.extra}]'"


def require_extra(extra: str, feature: str, modules: Sequence[str] | None = None) -> None:
    """Raise [`MissingExtraError`] unless every module of `extra` (or only `modules`) is installed; nothing is
    imported. `feature` is what the message says needs it (a module name, or a command)."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; known: {', '.join(EXTRAS)}")
    for module in EXTRAS[extra] if modules is None else modules:
        if importlib.util.find_spec(module) is None:
            raise MissingExtraError(feature, module, extra)
