"""Checkpoint conversion: openpi (orbax, read without JAX), LeRobot and transformers folders to pi0-torch, and back
(imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.conversion.convert import (
        ConversionError,
        ConversionResult,
        convert_hf_checkpoint,
        convert_openpi_checkpoint,
        export_to_transformers,
    )

_EXPORTS = {
    "ConversionError": "pi0_torch.conversion.convert",
    "ConversionResult": "pi0_torch.conversion.convert",
    "convert_hf_checkpoint": "pi0_torch.conversion.convert",
    "convert_openpi_checkpoint": "pi0_torch.conversion.convert",
    "export_to_transformers": "pi0_torch.conversion.convert",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
