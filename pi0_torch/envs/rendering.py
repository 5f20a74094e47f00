"""Headless MuJoCo rendering: the OpenGL backend is chosen before MuJoCo loads, and checked once.

MuJoCo reads `MUJOCO_GL` when it is first imported: `egl` renders on an NVIDIA GPU, `osmesa` on the CPU (Debian /
Ubuntu: `apt-get install libosmesa6`), `glfw` needs a display. [`configure_mujoco_gl`] keeps a value the user set and
otherwise picks `egl` where an NVIDIA driver is loaded, else `osmesa`; [`check_mujoco_rendering`] renders one tiny
frame and turns a failure into one line that says what to install or set. The benchmark adapters
(`pi0_torch.envs.benchmarks`) call it before they make an environment.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pi0_torch.utils.validation import first_line

BACKENDS = ("egl", "osmesa", "glfw")
_HINTS = {
    "osmesa": "install OSMesa (apt-get install libosmesa6) or, on a machine with an NVIDIA GPU, set MUJOCO_GL=egl",
    "egl": "EGL needs an NVIDIA driver with libEGL; on a CPU set MUJOCO_GL=osmesa (apt-get install libosmesa6)",
    "glfw": "glfw needs a display; headless, set MUJOCO_GL=osmesa (CPU) or egl (NVIDIA GPU)",
}
_checked: set[str] = set()


class RenderingError(OSError):
    """MuJoCo cannot render offscreen with the chosen backend (a system library is missing or unusable); the message
    says what to install or set. An `OSError`, so that `pi0-torch eval` and `demos` print it as their one-line error."""


def nvidia_driver_loaded() -> bool:
    """Whether an NVIDIA kernel driver is loaded (EGL can render on its GPU); nothing is imported."""
    return Path("/proc/driver/nvidia/version").exists() or Path("/dev/nvidia0").exists()


def configure_mujoco_gl() -> str:
    """Set `MUJOCO_GL` (and PyOpenGL's matching `PYOPENGL_PLATFORM`) unless the user did, before MuJoCo is imported;
    returns the backend in force. A backend MuJoCo does not know is refused by name."""
    backend = os.environ.get("MUJOCO_GL") or ("egl" if nvidia_driver_loaded() else "osmesa")
    if backend not in BACKENDS:
        raise RenderingError(f"MUJOCO_GL={backend!r} is not a MuJoCo backend; expected one of {', '.join(BACKENDS)}")
    if "mujoco" not in sys.modules:  # (once MuJoCo is loaded, its backend is fixed)
        os.environ["MUJOCO_GL"] = backend
        if backend != "glfw":
            os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    return os.environ.get("MUJOCO_GL", backend)


def check_mujoco_rendering() -> str:
    """Configure the backend and render one 8x8 frame of a one-sphere scene (once per process); a failure is a
    [`RenderingError`] naming the backend and what to do. Returns the backend."""
    backend = configure_mujoco_gl()
    if backend in _checked:
        return backend
    _load_triton_first()
    try:
        import mujoco

        class Renderer(mujoco.Renderer):
            def __del__(self) -> None:  # (one whose GL context failed to open has no `_mjr_context`: MuJoCo's own
                if "_mjr_context" in self.__dict__:  # `__del__` then prints an AttributeError after our one line)
                    self.close()

        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='0.1'/></worldbody></mujoco>")
        renderer = Renderer(model, 8, 8)
        try:
            renderer.update_scene(mujoco.MjData(model))
            renderer.render()
        finally:
            renderer.close()
    except Exception as error:  # (an absent library surfaces as ImportError, AttributeError or a mujoco.FatalError)
        raise RenderingError(f"MuJoCo cannot render offscreen with MUJOCO_GL={backend} "
                             f"({first_line(error) or type(error).__name__}): {_HINTS[backend]}") from None
    _checked.add(backend)
    return backend


def _load_triton_first() -> None:
    """Load triton's compiler library before the OpenGL driver: OSMesa (and Mesa's EGL) bring their own LLVM, and
    triton's, loaded second (as torch does when a model is first built), crashed the process (a segfault in
    `triton._C.libtriton`). Loaded first, both work."""
    import importlib.util

    if importlib.util.find_spec("triton") is not None:
        try:
            import triton._C.libtriton  # noqa: F401
        except ImportError:  # (a triton without its compiled library: nothing to clash with)
            pass
