"""A broken triton install must not break everything: torch's compiler imports triton when it is itself imported
(`torch._dynamo`, which transformers' model layers import), so a triton that raises at import, lacks
`triton.language`, or even exits the process made every model import fail with torch's traceback (or exit 3 with no
output). `set_aside_broken_triton` finds that out first and makes `import triton` raise `ImportError` for the rest of
the process, as if triton were not installed: torch then runs without it, the fused kernels are refused naming why
(`pi0_torch.kernels.ops.triton_reason`), and everything else works."""

from __future__ import annotations

import importlib.util
import sys

BROKEN: list[str] = []  # why the installed triton was set aside (empty: it was not)


def set_aside_broken_triton() -> str | None:
    """Import triton once, before torch's compiler does; where that fails (any exception, `SystemExit` included), set
    it aside (see the module docstring) and return why (None: it imports, it is not installed, or it was imported
    before this was called)."""
    if BROKEN:
        return BROKEN[0]
    if "triton" in sys.modules or importlib.util.find_spec("triton") is None:
        return None
    try:
        import triton
        import triton.language  # noqa: F401  (torch._dynamo reads triton.language.dtype at its import)
    except (Exception, SystemExit) as error:
        for name in [name for name in sys.modules if name == "triton" or name.startswith("triton.")]:
            del sys.modules[name]
        sys.modules["triton"] = None  # type: ignore[assignment]  (`import triton` raises ImportError from now on)
        BROKEN.append(f"the installed triton does not import ({type(error).__name__}: {str(error)[:200]}); it is set "
                      "aside for this process: reinstall it (the one torch's CUDA wheels bring) or uninstall it")
        return BROKEN[0]
    return None
