"""pytest settings for the package's own modules (`make test` runs their doctests): a module whose doctest renders
MuJoCo scenes is left out, with a note, where MuJoCo cannot render offscreen (no EGL or OSMesa)."""

from __future__ import annotations

import importlib.util

collect_ignore: list[str] = []
if all(importlib.util.find_spec(module) is not None for module in ("gymnasium", "metaworld")):
    from pi0_torch.envs.rendering import RenderingError, check_mujoco_rendering

    try:
        check_mujoco_rendering()
    except RenderingError as error:
        print(f"conftest: the doctests of pi0_torch/envs/metaworld.py are skipped: {error}")
        collect_ignore.append("pi0_torch/envs/metaworld.py")
