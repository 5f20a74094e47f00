"""pytest settings for the whole repository (loaded before tests/conftest.py and before any module is collected):

- without a GPU, the fused Triton kernels run in triton's interpreter (`tests/test_kernels.py`): `TRITON_INTERPRET=1`
  must be set before triton is first imported, which the MuJoCo check below does;
- `make test` runs the doctests of the package's modules: a module whose doctest renders MuJoCo scenes is left out,
  with a note, where MuJoCo cannot render offscreen (no EGL or OSMesa).
"""

from __future__ import annotations

import importlib.util
import os

import torch

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

collect_ignore: list[str] = []
if all(importlib.util.find_spec(module) is not None for module in ("gymnasium", "metaworld")):
    from pi0_torch.envs.rendering import RenderingError, check_mujoco_rendering

    try:
        check_mujoco_rendering()
    except RenderingError as error:
        print(f"conftest: the doctests of pi0_torch/envs/metaworld.py are skipped: {error}")
        collect_ignore.append("pi0_torch/envs/metaworld.py")
